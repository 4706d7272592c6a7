"""`vergence replay FILE [--speed X] [--only KIND ...]`: publish a recording again, at its own pace.

Replays frames, previews, correlations, decisions and profiles under the rig `replay` (REPLAY_RIG), or
--rig. Never commands or motor states, and never where a motor listens: a replay must not move a motor. It
refuses (exit 2) a rig with a live actuator (its liveliness token), since a live reducer there would turn
the replayed frames into commands; under the deploy/ access rules the replay role may publish only under
vergence/replay/. Status messages and liveliness events are not replayed either. No router within --wait
seconds (default 5): one line, exit 1.

Frames are re-planned onto the workers alive now (their liveliness tokens), because the recorded plan names
workers of the recorded run: live workers then compute them, and a live reducer reproduces the recorded
profiles exactly (layer 4 does not depend on how k is split). Their capture time is moved to the replay's
clock (same spacing), so a reducer that is already running takes them as new frames; frame ids and every
other field are as recorded. To recompute only: `--only frame`, with workers and a reducer running.

`--view FILE.rrd|web[:PORT]|spawn` publishes nothing: it turns the recording into the cockpit of
`vergence view` (services/observe/view.py), saved, served to a browser or shown in the native viewer.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time

import zenoh

from vergence.wire import keys
from vergence.stages.frames import plan_shards
from vergence.wire.messages import Frame, MessageError, replace
from vergence.io.mcap_file import McapReader, is_mcap
from vergence.io.recording import Reader, RecordingError

from services.runtime import session
from services.runtime.args import number
from services.runtime.node import Node

log = logging.getLogger("vergence.replay")
# the kinds (vergence.wire.keys) a replay publishes again; REPLAY_RIG: where by default (no actuator listens there)
KINDS = (keys.FRAME, keys.PREVIEW, keys.CORRELATION, keys.DECISION, keys.PROFILE)
REPLAY_RIG = keys.REPLAY_RIG


def configure(p: argparse.ArgumentParser) -> None:
    session.add_options(p)
    p.add_argument("file", metavar="FILE", help="a recording made by `vergence record` (FILE.mcap: its MCAP file)")
    p.add_argument("--speed", type=number(0, 1000, note="0: as fast as possible"), default=1.0, metavar="X",
                   help="1 = as recorded, 2 = twice as fast, 0 = as fast as possible (default 1)")
    p.add_argument("--only", action="append", choices=KINDS, metavar="KIND",
                   help=f"replay only these kinds, repeatable: {', '.join(KINDS)} (default: all)")
    session.add_wait(p)
    p.add_argument("--wait-workers", type=number(0, 3600), default=5.0, metavar="S",
                   help="how long to wait for live workers before replaying frames (default 5)")
    p.add_argument("--view", metavar="FILE.rrd|web[:PORT]|spawn",
                   help="publish nothing: turn the recording into `vergence view`'s Rerun cockpit, saved to "
                        "FILE.rrd, served to a browser, or in the native viewer (the [view] extra)")


class Workers:
    """The live workers of the target rig, from their liveliness tokens."""

    def __init__(self):
        self.ids: set[str] = set()
        self.lock = threading.Lock()

    def on_sample(self, sample) -> None:
        k = keys.parse(str(sample.key_expr))
        if k is None or k.kind != keys.ALIVE:
            return
        wid = k.ident
        with self.lock:
            (self.ids.add if sample.kind == zenoh.SampleKind.PUT else self.ids.discard)(wid)

    def snapshot(self) -> list[str]:
        with self.lock:
            return sorted(self.ids)


def replan(payload: bytes, workers: list[str], t_shift_ns: int) -> bytes:
    """A recorded frame with the plan of the live workers and its exposure and read times moved by t_shift_ns."""
    f = Frame.from_bytes(payload)
    plan = plan_shards(workers, f.k_count) if workers else f.plan
    return replace(f, plan=plan, t_capture_ns=f.t_capture_ns + t_shift_ns,
                   t_read_ns=f.t_read_ns + t_shift_ns if f.t_read_ns else 0).to_bytes()


def main(conf: zenoh.Config, stop: session.Stop, path: str, rig: str | None = None, speed: float = 1.0,
         only: list[str] | None = None, wait_workers: float = 5.0, wait: float = session.CLIENT_WAIT_S) -> int:
    kinds = set(only or KINDS)
    try:
        reader = McapReader(path) if is_mcap(path) else Reader(path)
    except RecordingError as e:
        print(f"vergence replay: {e}", file=sys.stderr)
        return 2
    rig = rig or REPLAY_RIG
    sent = skipped = bad = 0
    pubs_early: dict[str, zenoh.Publisher] = {}
    # no router within --wait: session.NoRouter, said in one line by services/ops/cli.py (exit 1)
    with reader, Node("replay", rig, conf, stop, log=log, timeout=wait, quiet=True) as node:
        s, health = node.session, node.health
        if any(r.ok for r in s.liveliness().get(keys.alives(rig, "actuator"), timeout=1.0)):
            print(f"vergence replay: an actuator is alive on {keys.prefix(rig)}: a reducer there would turn the "
                  f"replayed frames into motor commands. Replay under another rig (--rig; default "
                  f"{REPLAY_RIG}) and run workers and a reducer with that --rig", file=sys.stderr)
            return 2
        workers = Workers()
        node.liveliness_subscriber(keys.alives(rig, "worker"), workers.on_sample, history=True)
        node.ready()
        if "frame" in kinds:
            deadline = time.monotonic() + wait_workers
            while not workers.snapshot() and time.monotonic() < deadline and not stop.wait(0.05):
                pass
            if not workers.snapshot():
                log.warning("no live worker on %s: frames keep their recorded plan "
                            "and nobody will compute them", keys.alives(rig, "worker"))
            else:
                # a new session learns the subscribers' routes from the router a moment after it opens; a
                # put before that reaches nobody (the capture waits likewise): wait, bounded, for them
                pub = s.declare_publisher(keys.frame(rig))
                while not pub.matching_status.matching and time.monotonic() < deadline and not stop.wait(0.02):
                    pass
                stop.wait(0.1)  # the reducer's route is matched; let the workers' routes land too
                pubs_early = {keys.frame(rig): pub}
        pubs: dict[str, zenoh.Publisher] = dict(pubs_early)
        t0_rec = t0_now = None
        shift = 0
        try:
            for rec in reader:
                if stop.is_set():
                    break
                k = keys.parse(rec.key)
                kind = k.kind if k is not None else None
                if rec.event != "put" or kind not in kinds:
                    skipped += 1
                    health.count("skipped")
                    continue
                if t0_rec is None:
                    t0_rec, t0_now = rec.t_ns, time.monotonic()
                    shift = time.time_ns() - rec.t_ns
                if speed > 0:
                    delay = t0_now + (rec.t_ns - t0_rec) / 1e9 / speed - time.monotonic()
                    if delay > 0 and stop.wait(delay):
                        break
                payload = rec.payload
                if kind == "frame":
                    try:
                        payload = replan(payload, workers.snapshot(), shift)
                    except MessageError as e:
                        bad += 1
                        health.count("bad_frames")
                        log.warning("recorded frame skipped: %s", e)
                        continue
                key = k.under(rig)
                pub = pubs.get(key)
                if pub is None:
                    pub = pubs[key] = s.declare_publisher(key)
                pub.put(payload)
                sent += 1
                health.count("sent")
        except RecordingError as e:
            print(f"vergence replay: {e}", file=sys.stderr)
            return 2
        note = " (the last record was truncated)" if reader.truncated else ""
        log.info("replayed %d messages to %s, skipped %d, bad %d%s", sent, keys.prefix(rig), skipped, bad, note)
    return 0


def run(args: argparse.Namespace) -> int:
    if args.view:
        from services.observe import view

        return view.view_recording(args.file, args.view, args.rig, session.Stop())
    if not args.speed >= 0:
        print("vergence replay: --speed must be >= 0", file=sys.stderr)
        return 2
    return main(session.config_from_args(args), session.Stop(), args.file, args.rig, args.speed, args.only,
                args.wait_workers, args.wait)
