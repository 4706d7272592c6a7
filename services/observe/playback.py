"""Recordings and the simulator into the cockpit's Rerun view: `vergence replay FILE --view TARGET`
(view_recording) and `vergence sim --save` (log_sim_step), under the cockpit's entity paths."""

from __future__ import annotations

import logging
import math
import sys

import numpy as np

from vergence.wire import keys

from services.observe.cockpit import Cockpit
from services.observe.rerun_sdk import APP_ID, MissingExtra, import_rerun
from services.observe.sinks import start

log = logging.getLogger("vergence.view")


def parse_target(text: str) -> dict:
    """`replay --view TARGET`: FILE.rrd (save), web[:PORT] (serve), or spawn (the native viewer)."""
    if text == "spawn":
        return {"spawn": True}
    if text == "web" or text.startswith("web:"):
        port = text.partition(":")[2]
        if port and not port.isdigit():
            raise ValueError(f"--view web:PORT wants a port number, got {text!r}")
        return {"web": True, "port": int(port or 9090)}
    if text.endswith(".rrd"):
        return {"save": text}
    raise ValueError(f"--view wants FILE.rrd, web[:PORT] or spawn, got {text!r}")


def view_recording(path: str, target: str, rig: str | None, stop=None) -> int:
    """`vergence replay FILE --view TARGET`: a `vergence record` file into the cockpit's Rerun view (no Zenoh,
    nothing published). Serving (web, spawn) keeps running until stopped, so the viewer can read it."""
    from vergence.io.recording import Reader, RecordingError

    try:
        sinks = parse_target(target)
        rr = import_rerun()
        reader = Reader(path)
    except (ValueError, MissingExtra, RecordingError) as e:
        print(f"vergence replay: {e}", file=sys.stderr)
        return 2
    rig = rig or reader.header.get("rig") or "head"
    with reader:
        url = start(rr, f"{APP_ID}-{rig}", **sinks)
        if url:
            print(f"vergence replay: the cockpit of the recording is at {url}", file=sys.stderr, flush=True)
        cockpit = Cockpit(rr)
        try:
            for rec in reader:
                k = keys.parse(rec.key)
                if k is None or k.rig != rig:
                    continue
                rest = k.rest
                if rec.event in ("alive", "dead"):
                    cockpit.alive(rest, rec.event == "alive", rec.t_ns)
                elif rec.event == "put":
                    cockpit.feed(rest, rec.payload, rec.t_ns)
        except RecordingError as e:
            print(f"vergence replay: {e}", file=sys.stderr)
            return 2
    log.info("recording %s of rig %s into Rerun: logged %s, bad %s", path, rig, dict(cockpit.counts),
             dict(cockpit.bad))
    if (sinks.get("web") or sinks.get("spawn")) and stop is not None:
        print("vergence replay: serving the view until Ctrl-C", file=sys.stderr, flush=True)
        stop.wait()
    rr.disconnect()
    return 0


def log_sim_step(rr, s, master: np.ndarray, slave: np.ndarray, at: tuple[int, int], rate_hz: float) -> None:
    """`vergence sim --save`: one Step of the simulated loop with the views it was decided on, under the
    cockpit's entity paths (capture time: the virtual clock, from 0)."""
    x, y = at
    if True:
        rr.set_time("frame", sequence=s.frame)
        rr.set_time("capture", duration=s.frame / rate_hz)
        rr.log("rig/master", rr.Image(master))
        rr.log("rig/slave", rr.Image(slave))
        half = [(s.window / 2, s.window / 2)]
        rr.log("rig/master/fovea", rr.Boxes2D(centers=[(x + 0.5, y + 0.5)], half_sizes=half,
                                              labels=[f"fovea {s.window} px"]))
        color = (40, 220, 60) if s.confident else (230, 150, 30)
        rr.log("rig/slave/match", rr.Boxes2D(centers=[(x + s.offset_px + 0.5, y + s.v + 0.5)], half_sizes=half,
                                             colors=[color], labels=[f"{s.offset_px:+.1f} px"]))
        rr.log("rig/correlation", rr.BarChart(np.asarray(s.scores, np.float64)))
        rr.log("pan/slave", rr.Scalars(s.pan_deg))
        if math.isfinite(s.truth_pan_deg):
            rr.log("pan/truth", rr.Scalars(s.truth_pan_deg))
        if s.target_deg is not None:
            rr.log("pan/command", rr.Scalars(s.target_deg))
        rr.log("decision/confidence", rr.Scalars(s.confidence))
        rr.log("decision/confident", rr.Scalars(1.0 if s.confident else 0.0))
        rr.log("decision/offset_px", rr.Scalars(s.offset_px))
        rr.log("decision/window", rr.Scalars(float(s.window)))
