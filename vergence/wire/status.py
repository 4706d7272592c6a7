"""The status every process publishes on vergence/<rig>/status/<role>/<id>, and the reducer's workers report on
vergence/<rig>/workers: JSON on the wire (recordings hold them), decoded here, once, for every reader (the
monitor, the cockpit, the ROS 2 bridge and its /diagnostics, MCAP files, `vergence fixate`, the capture).

A status is a claim like any message: decode_status() refuses (MessageError) what is not a JSON object, a role or
id that is not a short string, counters that are not integers in 0..2^53, a pid or time that is not an integer; a
role's own fields (a reducer's `gatherer`, a capture's `clipped` shares, `replica`, `fixate_rejection`, the
rates...) are kept as their JSON values in `extra`, read through the typed accessors below, which take only
plausible values. The encoding stays the services' (services.runtime.health builds the dict).
"""

from __future__ import annotations

import math
from typing import Any

import msgspec

from .messages import MessageError

__all__ = ["Status", "WorkerEvidence", "WorkersReport", "decode_status", "status_of", "decode_report", "report_of"]

MAX_BYTES = 1 << 16  # a status or a report longer than this is not believed (a real one is under 4 KB)
MAX_COUNT = 2 ** 53  # a counter beyond this is not an integer a JSON reader keeps exactly
MAX_NAME = 128
CORE = ("role", "id", "pid", "t_ns", "counters", "bad", "exiting")


class Status(msgspec.Struct, frozen=True, kw_only=True):
    """One process's status: who (role, id, pid), when (t_ns), its counters and bad-message counts, whether it
    said it exits, and the role's own fields (extra)."""

    role: str
    id: str
    pid: int = 0
    t_ns: int = 0
    counters: dict[str, int] = {}
    bad: dict[str, int] = {}
    exiting: bool = False
    extra: dict[str, Any] = {}

    def get(self, name: str, default=None):
        """A role's own field (its JSON value), or default."""
        return self.extra.get(name, default)

    @property
    def bad_total(self) -> int:
        return sum(self.bad.values())

    def to_dict(self) -> dict:
        """As on the wire: the core fields (pid and t_ns when given: 0 is none), then the role's own."""
        d = {"role": self.role, "id": self.id, **({"pid": self.pid} if self.pid else {}),
             **({"t_ns": self.t_ns} if self.t_ns else {}), "counters": dict(self.counters), "bad": dict(self.bad)}
        if self.exiting:
            d["exiting"] = True
        d.update(self.extra)
        return d

    def gatherer(self) -> dict[str, int]:
        """A reducer's gatherer counters (frames, complete, dropped, superseded, ...): the plausible ones."""
        g = self.extra.get("gatherer")
        return {k: v for k, v in g.items() if _count(v)} if isinstance(g, dict) else {}

    def clipped(self) -> dict[str, float]:
        """A capture's clipped shares of the fovea's rows per camera (master, slave), each in 0..1."""
        c = self.extra.get("clipped")
        if not isinstance(c, dict):
            return {}
        return {cam: float(v) for cam, v in c.items() if cam in ("master", "slave") and _number(v, 0.0, 1.0)}

    def fault(self) -> tuple[str, str] | None:
        """A reducer's named fault (vergence.head.doubt: slave_frozen, reversed, stalled, master_frozen) and what to
        check, or None; a name that is not one of them is not believed."""
        from ..choices import Fault

        f, note = self.extra.get("fault"), self.extra.get("fault_note")
        if isinstance(f, str) and f in tuple(Fault):
            return f, note[:400] if isinstance(note, str) else ""
        return None

    def search(self) -> int | None:
        """A reducer searching for its lost target (vergence.head.search): the sweeps of the range that found nothing
        so far, or None when it does not search (or says nothing plausible)."""
        n = self.extra.get("sweeps_empty", 0)
        return n if self.extra.get("searching") is True and _count(n) else None

    def search_note(self) -> str | None:
        """What a search says to a person (`vergence monitor`, /diagnostics at WARN), or None when none runs."""
        n = self.search()
        if n is None:
            return None
        return "searching: no confident match at the fovea" + (
            f"; {n} sweep{'s' if n > 1 else ''} of the pan range found nothing: is the point visible to the slave "
            "camera (hidden behind a nearer object, or out of its view)?" if n else "")

    def texture_note(self) -> str | None:
        """What a reducer says of a fovea with no texture (its last frame: black or flat), or None."""
        if self.extra.get("no_texture") is not True:
            return None
        return ("no texture at the fovea (a black or flat image: a lens cap, the light off, a blank surface, a camera "
                "sending black frames): the loop abstains and the slave holds")

    def fixate_rejection(self) -> tuple[int, str] | None:
        """A capture's refusal of a fixate request: (the request's t_ns, why), or None."""
        r = self.extra.get("fixate_rejection")
        if isinstance(r, dict) and _time(r.get("t_ns")) and isinstance(r.get("why"), str):
            return r["t_ns"], r["why"][:300]
        return None

    def number(self, name: str, lo: float = -math.inf, hi: float = math.inf) -> float | None:
        """A role's own numeric field (published_hz, pending, ...) when it is a number within lo..hi, else None."""
        v = self.extra.get(name)
        return float(v) if _number(v, lo, hi) else None


def _count(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= MAX_COUNT


def _time(v) -> bool:
    """An integer time in ns (0..2^63: time.time_ns's range)."""
    return isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 2 ** 63


def _number(v, lo: float, hi: float) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and lo <= v <= hi


def _name(d: dict, key: str) -> str:
    v = d.get(key)
    if not isinstance(v, str) or not v or len(v) > MAX_NAME:
        raise MessageError(f"status: {key} must be a string of 1..{MAX_NAME} characters")
    return v


def _counts(d: dict, key: str) -> dict[str, int]:
    v = d.get(key, {})
    if not isinstance(v, dict) or not all(isinstance(k, str) and _count(n) for k, n in v.items()):
        raise MessageError(f"status: {key} must map names to integers 0..2^53")
    return dict(v)


def status_of(d: Any) -> Status:
    """A Status from a status's JSON object (a dict), checked as decode_status checks the wire's."""
    if not isinstance(d, dict):
        raise MessageError("status: not a JSON object")
    for key in ("pid", "t_ns"):
        if not _time(d.get(key, 0)):
            raise MessageError(f"status: {key} must be an integer 0..2^63")
    if not isinstance(d.get("exiting", False), bool):
        raise MessageError("status: exiting must be true or false")
    return Status(role=_name(d, "role"), id=_name(d, "id"), pid=d.get("pid", 0), t_ns=d.get("t_ns", 0),
                  counters=_counts(d, "counters"), bad=_counts(d, "bad"), exiting=d.get("exiting", False),
                  extra={k: v for k, v in d.items() if k not in CORE})


def _json(payload: bytes, what: str) -> Any:
    if len(payload) > MAX_BYTES:
        raise MessageError(f"{what}: {len(payload)} bytes, over {MAX_BYTES}")
    try:
        return msgspec.json.decode(bytes(payload))
    except (msgspec.DecodeError, RecursionError, UnicodeDecodeError) as e:
        raise MessageError(f"{what}: not JSON ({e})") from None


def decode_status(payload: bytes) -> Status:
    """The one decoding of a status payload; MessageError saying why it is not believed."""
    return status_of(_json(payload, "status"))


class WorkerEvidence(msgspec.Struct, frozen=True):
    """What the reducer saw of one worker: seconds since its latest fitting correlation (None: never) and the
    frames naming it that expired without its correlation, in a row."""

    age_s: float | None
    misses: int


class WorkersReport(msgspec.Struct, frozen=True, kw_only=True):
    """The reducer's membership evidence (vergence.stages.gather.Gatherer.report, with who sent it and when, and how
    many frames it completed): the capture's Roster plans with it."""

    rig: str = ""
    id: str = ""
    t_ns: int = 0
    frame: int = -1
    complete: int | None = None
    workers: dict[str, WorkerEvidence] = {}


def report_of(d: Any) -> WorkersReport:
    """A WorkersReport from its JSON object, checked (MessageError): workers an object of worker -> {age_s: a
    number >= 0 or null, misses: an integer 0..2^53}; frame and complete integers."""
    if not isinstance(d, dict) or not isinstance(d.get("workers"), dict):
        raise MessageError("workers report: not a JSON object with a workers object")
    workers = {}
    for wid, w in d["workers"].items():
        age = w.get("age_s") if isinstance(w, dict) else None
        if not (isinstance(w, dict) and (age is None or _number(age, 0.0, math.inf)) and _count(w.get("misses", 0))
                and 0 < len(wid) <= MAX_NAME):
            raise MessageError(f"workers report: worker {wid[:40]!r} is not {{age_s, misses}}")
        workers[wid] = WorkerEvidence(None if age is None else float(age), w.get("misses", 0))
    frame, complete = d.get("frame", -1), d.get("complete")
    if not (isinstance(frame, int) and not isinstance(frame, bool)) or not (complete is None or _count(complete)):
        raise MessageError("workers report: frame and complete must be integers")
    return WorkersReport(rig=str(d.get("rig", ""))[:MAX_NAME], id=str(d.get("id", ""))[:MAX_NAME],
                         t_ns=d["t_ns"] if _time(d.get("t_ns")) else 0, frame=frame, complete=complete,
                         workers=workers)


def decode_report(payload: bytes) -> WorkersReport:
    """The one decoding of the reducer's workers report; MessageError saying why it is not believed."""
    return report_of(_json(payload, "workers report"))
