"""The live cockpit: the rig's messages logged to a Rerun recording stream under the entity paths of ENTITIES
(see services/observe/view.py for the paths and the timelines)."""

from __future__ import annotations

import collections
import json
import logging
import math

import numpy as np

from vergence.wire import keys
from vergence.wire.messages import Command, Frame, MessageError, MotorState, Preview, Profile, Decision
from vergence.observe.monitor import decode
from vergence.wire.status import status_of

log = logging.getLogger("vergence.view")
# what the cockpit subscribes to under vergence/<rig>/
WATCHED = (keys.preview, keys.frame, keys.decision, keys.profile, keys.command, keys.motor_state, keys.statuses)
# the key kinds the cockpit logs (vergence.observe.monitor.decode decodes them)
SHOWN = (keys.PREVIEW, keys.FRAME, keys.DECISION, keys.PROFILE, keys.COMMAND, keys.MOTOR_STATE, keys.STATUS)
ENTITIES = {
    "rig/master": "the master's preview image",
    "rig/master/fovea": "the fovea, a box on the master image",
    "rig/slave": "the slave's preview image",
    "rig/slave/match": "where the fovea matched, a box on the slave image",
    "rig/correlation": "layer 4's scores on the winning row, relative: 0 at the row's worst k, 1 at its best "
                       "(bar chart over the offset k - k_centre, px)",
    "rig/correlation/winner": "the winner's bar, wide, green when confident, orange when abstaining",
    "rig/readout": "the decision in large print: offset, confidence, window, pan (markdown)",
    "pan/slave": "the slave pan at capture, degrees",
    "pan/motor": "the pan the motor reports, degrees",
    "pan/goal": "the motor's goal, degrees",
    "pan/command": "the pan commanded, degrees",
    "pan/truth": "the converged pan, degrees (frames that carry the truth)",
    "depth": "the fixated distance, metres (decisions that carry it); depth/sigma its uncertainty",
    "decision/confidence": "the decision's confidence, 0..1",
    "decision/confident": "1 when the camera may move, else 0",
    "decision/offset_px": "how far right of the fovea's column its match lies in the slave, px",
    "decision/window": "the fovea side the frame was decided with, px",
    "latency/decision_ms": "capture to decision, ms",
    "workers/alive": "the number of live workers",
    "workers/<id>": "1 while worker <id> is alive, 0 after",
    "status/<role>/<id>": "each process's status message (text log)",
    "fault": "the reducer's named fault and what to check (ERROR), or its clearing (INFO), when it changes",
}

CONFIDENT, ABSTAINING = (40, 220, 60), (230, 150, 30)  # the match box's and the winner's bar's colours
PROFILE_COLOUR = (120, 135, 160)  # the profile's other bars: grey-blue, so that the winner's stands out
READOUT_NS = 100_000_000  # the readout at most every 0.1 s of capture time: read by a person, not a plot
WINNER_WIDTH = 7.0  # the winner's bar, in k (a k is about a pixel of the view at 1600 px)


def relative(row) -> np.ndarray:
    """A profile row scaled from its worst score (0) to its best (1): layer 4's scores sit near 255 w^2 with a
    spread of a few per cent, so on an axis from 0 every bar looks the same; relative, the winner is the one
    bar at 1. A flat row (no texture) is all 0."""
    row = np.asarray(row, np.float64)
    lo, hi = float(row.min()), float(row.max())
    return (row - lo) / (hi - lo) if hi > lo else np.zeros_like(row)


def readout(v) -> str:
    """The decision in large print (markdown: a heading is the one text Rerun draws large; the boxes' labels
    have a fixed small font)."""
    mark = "confident" if v.confident else "abstains"
    return (f"## {v.offset_px:+.1f} px, confidence {v.confidence:.2f} ({mark})\n\n"
            f"### window {v.window} px, k {v.k}, pan {math.degrees(v.pan_rad):+.2f} deg\n\n"
            f"frame {v.frame}")


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


class Cockpit:
    """Decodes the rig's messages and logs them to a Rerun recording stream. Malformed messages are counted
    (bad) and skipped; fields that newer messages carry (truth, depth, x/y on the decision) are read with
    defaults, so older and newer peers both work."""

    def __init__(self, rr, recording=None):
        self.rr, self.rec = rr, recording
        self.counts: collections.Counter = collections.Counter()
        self.bad: collections.Counter = collections.Counter()
        self.scale: float | None = None  # preview px per image px (latest preview)
        self.size: tuple[int, int] | None = None  # the full image (width, height), from the frames
        self.at: dict[int, tuple[int, int]] = {}  # frame id -> fovea (x, y), recent frames
        self.point: tuple[int, int] | None = None  # the latest frame's fovea point (the capture keeps it)
        self.decided: set[int] = set()  # frames whose decision was logged (recent)
        self.workers: set[str] = set()
        self.readout_ns: int | None = None  # the capture time of the decision last put in the readout
        self.motor_status: str | None = None  # the latest motor state's status (logged as text when it changes)
        self.fault: tuple[str, str] | None = None  # the reducer's named fault (logged at `fault` when it changes)
        self.search: str | None = None  # what the reducer's search says (logged at `search` when it changes)
        self.texture: str | None = None  # what it says of a fovea with no texture (logged at `texture`)

    # -- helpers -------------------------------------------------------------------------------------------

    def _log(self, path: str, what) -> None:
        self.rr.log(path, what, recording=self.rec)

    def _time(self, frame: int | None, t_ns: int | None) -> None:
        rr = self.rr
        if frame is not None and frame >= 0:
            rr.set_time("frame", sequence=int(frame), recording=self.rec)
        else:
            rr.reset_time(recording=self.rec)
        if t_ns:
            rr.set_time("capture", timestamp=np.datetime64(int(t_ns), "ns"), recording=self.rec)

    def _scalar(self, path: str, value) -> None:
        if _finite(value):
            self._log(path, self.rr.Scalars(float(value)))

    def _remember(self, d: dict, key: int, value) -> None:
        d[key] = value
        if len(d) > 512:  # recent frames only
            for k in sorted(d)[:256]:
                del d[k]

    # -- one sample ----------------------------------------------------------------------------------------

    def feed(self, rest: str, payload: bytes, t_ns: int | None = None) -> str | None:
        """Log one message whose key is vergence/<rig>/<rest>; returns its kind (vergence.wire.keys), or None when
        skipped."""
        kind = keys.kind_of(rest)
        if kind not in SHOWN:
            return None
        try:
            msg = decode(kind, payload)  # the decoding `vergence monitor`'s model uses too
            if kind == keys.STATUS:
                self._status(rest, payload, t_ns)  # the text as it came
            else:
                self._loggers()[kind](msg)
        except (MessageError, ValueError, TypeError) as e:
            self.bad[kind] += 1
            if sum(self.bad.values()) <= 10:
                log.warning("malformed message on %s skipped: %s", rest, e)
            return None
        self.counts[kind] += 1
        return kind

    def _loggers(self) -> dict:
        """Key kind (vergence.wire.keys) -> what logs its decoded message; the kinds the cockpit shows."""
        return {keys.PREVIEW: self._preview, keys.FRAME: self._frame, keys.DECISION: self._decision,
                keys.PROFILE: self._profile, keys.COMMAND: self._command, keys.MOTOR_STATE: self._motor}

    def alive(self, rest: str, present: bool, t_ns: int | None = None) -> None:
        """A liveliness token vergence/<rig>/<rest> (alive/<role>/<id>) appeared or went away."""
        k = keys.Key("", keys.kind_of(rest), rest)
        if k.kind != keys.ALIVE or k.role != "worker" or "/" in k.ident:
            return
        (self.workers.add if present else self.workers.discard)(k.ident)
        self._time(None, t_ns)
        self._scalar(f"workers/{k.ident}", 1.0 if present else 0.0)
        self._scalar("workers/alive", len(self.workers))

    def _preview(self, p: Preview) -> None:
        master, slave = p.images()
        self.scale = p.scale
        if self.size is None and p.scale > 0:  # until a frame says
            self.size = (round(p.width / p.scale), round(p.height / p.scale))
        self._time(p.frame, p.t_capture_ns)
        self._log("rig/master", self.rr.Image(master))
        self._log("rig/slave", self.rr.Image(slave))

    def _frame(self, f: Frame) -> None:
        self.size = (f.width, f.height)
        self._remember(self.at, f.frame, (f.x, f.y))
        self.point = (f.x, f.y)
        truth = getattr(f, "truth_pan_rad", None)
        if _finite(truth):
            self._time(f.frame, f.t_capture_ns)
            self._scalar("pan/truth", math.degrees(truth))

    def _boxes(self, v: Decision) -> None:
        at = (getattr(v, "x", None), getattr(v, "y", None))
        if not all(isinstance(c, int) and c >= 0 for c in at):  # -1: a decision that does not say
            at = self.at.get(v.frame) or self.point
        if at is None:  # the capture's default point: the centre (k_centre = x - w // 2)
            height = self.size[1] if self.size else None
            if height is None:
                return
            at = (v.k_centre + v.window // 2, height // 2)
        if self.scale is None:  # no image to draw them on yet (no preview so far)
            return
        s = self.scale
        x, y = at
        half = (v.window * s / 2, v.window * s / 2)
        # pixel centres: pixel i covers [i, i + 1) in Rerun's image space
        # the numbers are in the readout, large; the boxes keep one short word each
        self._log("rig/master/fovea", self.rr.Boxes2D(centers=[((x + 0.5) * s, (y + 0.5) * s)], half_sizes=[half],
                                                      colors=[(60, 200, 255)], radii=[-1.5], labels=["fovea"]))
        mx, my = x + v.offset_px, y + v.v_shift
        color = CONFIDENT if v.confident else ABSTAINING
        self._log("rig/slave/match", self.rr.Boxes2D(centers=[((mx + 0.5) * s, (my + 0.5) * s)], half_sizes=[half],
                                                     colors=[color], radii=[-1.5], labels=["match"]))

    def _decision(self, v: Decision) -> None:
        if v.frame in self.decided:  # its profile came first and logged it
            return
        self._time(v.frame, v.t_capture_ns)
        self._boxes(v)
        self._scalar("pan/slave", math.degrees(v.pan_rad))
        self._scalar("decision/confidence", v.confidence)
        self._scalar("decision/confident", 1.0 if v.confident else 0.0)
        self._scalar("decision/offset_px", v.offset_px)
        self._scalar("decision/window", v.window)
        t = v.t_capture_ns
        if self.readout_ns is None or not t or not 0 <= t - self.readout_ns < READOUT_NS:
            self.readout_ns = t
            self._log("rig/readout", self.rr.TextDocument(readout(v), media_type=self.rr.MediaType.MARKDOWN))
        if v.t_reduced_ns and v.t_capture_ns:
            self._scalar("latency/decision_ms", (v.t_reduced_ns - v.t_capture_ns) / 1e6)
        depth = getattr(v, "depth_m", None)
        if _finite(depth):
            self._scalar("depth", depth)
            self._scalar("depth/sigma", getattr(v, "depth_sigma_m", None))
        truth = getattr(v, "truth_pan_rad", None)
        if _finite(truth):
            self._scalar("pan/truth", math.degrees(truth))
        self.decided.add(v.frame)
        if len(self.decided) > 512:
            self.decided = set(sorted(self.decided)[256:])

    def _profile(self, p: Profile) -> None:
        if p.frame not in self.decided:  # a rig (or a recording) without decision messages
            self._decision(p)
        self._time(p.frame, p.t_capture_ns)
        scores = p.array()
        row = scores[min(max(p.v_shift + (p.rows - 1) // 2, 0), p.rows - 1)]
        at = np.arange(len(row), dtype=np.float64) - p.k_centre  # the offset each k stands for, px
        self._log("rig/correlation", self.rr.BarChart(relative(row), abscissa=at, color=PROFILE_COLOUR))
        self._log("rig/correlation/winner", self.rr.BarChart(
            [1.0], abscissa=[float(p.k - p.k_centre)], widths=[WINNER_WIDTH],
            color=CONFIDENT if p.confident else ABSTAINING))

    def _command(self, c: Command) -> None:
        self._time(c.frame, c.t_capture_ns)
        self._scalar("pan/command", math.degrees(c.pan_rad))

    def _motor(self, m: MotorState) -> None:
        self._time(m.frame, m.t_capture_ns or m.t_ns)
        self._scalar("pan/motor", math.degrees(m.pan_rad))
        self._scalar("pan/goal", math.degrees(m.goal_rad))
        if m.status != self.motor_status:  # a change of status is an event: disconnected, absent (issue #29), back
            self.motor_status = m.status
            fault = m.status in ("disconnected", "absent")
            self._log("motor/status", self.rr.TextLog(f"motor {m.status}" + (f": {m.note}" if m.note else ""),
                                                      level="ERROR" if fault else "INFO"))

    def _status(self, rest: str, payload: bytes, t_ns: int | None) -> None:
        text = bytes(payload).decode("utf-8")  # decode() found it a JSON object
        self._time(None, t_ns)
        self._log(rest, self.rr.TextLog(text))
        if rest.startswith("status/reducer/"):  # the loop's doubt (issue #35): a fault named or cleared is an event
            st = status_of(json.loads(text))
            fault, note = st.fault(), st.search_note()
            if fault != self.fault:
                self.fault = fault
                self._log("fault", self.rr.TextLog(f"FAULT {fault[0]}: {fault[1]}" if fault else "fault cleared",
                                                   level="ERROR" if fault else "INFO"))
            if note != self.search:  # lost and searching (vergence.head.search), a sweep that found nothing, found
                self.search = note
                self._log("search", self.rr.TextLog(note or "search over", level="WARN" if note else "INFO"))
            if (blind := st.texture_note()) != self.texture:  # black or flat frames: the loop holds
                self.texture = blind
                self._log("texture", self.rr.TextLog(blind or "texture at the fovea again",
                                                     level="WARN" if blind else "INFO"))
