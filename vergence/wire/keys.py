"""Every Zenoh key expression of vergence, built and parsed in one place (plain strings: no zenoh import).

A rig's keys all live under vergence/<rig>/:

    frame                   messages.Frame, from the capture
    preview                 messages.Preview, from the capture
    fixate                  messages.Fixate, from a user (`vergence fixate`)
    hold                    messages.Hold, from a user (`vergence latency`): the reducer commands nothing
    correlation/<worker>    messages.Correlation, from worker <worker>
    decision                messages.Decision, from the reducer
    profile                 messages.Profile, from the reducer
    command                 messages.Command, from the reducer
    workers                 the reducer's membership evidence (JSON)
    motor_state             messages.MotorState, from the actuator
    status/<role>/<id>      a process's counters (JSON)
    alive/<role>/<id>       a process's liveliness token (no payload)

The builders raise ValueError on a rig, role or id that would not make one key chunk (empty, or holding a
"/"); parse() never raises: a key that is not one of the above parses to None. A rig may be a wildcard ("*")
where a key expression (a subscription, or a put to every rig) is meant."""

from __future__ import annotations

from typing import NamedTuple

__all__ = ["ROOT", "REPLAY_RIG", "KINDS", "SIMPLE", "NAMED", "Key", "parse", "kind_of", "prefix", "key", "frame",
           "preview", "fixate", "hold", "correlation", "correlations", "decision", "profile", "command", "workers",
           "motor_state", "status", "statuses", "alive", "alives", "everything"]

ROOT = "vergence"
REPLAY_RIG = "replay"  # where `vergence replay` publishes by default: no actuator listens there

FRAME, PREVIEW, FIXATE, DECISION, PROFILE = "frame", "preview", "fixate", "decision", "profile"
COMMAND, WORKERS, MOTOR_STATE, HOLD = "command", "workers", "motor_state", "hold"
CORRELATION, STATUS, ALIVE = "correlation", "status", "alive"
# kinds whose key is exactly vergence/<rig>/<kind>
SIMPLE = (FRAME, PREVIEW, FIXATE, DECISION, PROFILE, COMMAND, WORKERS, MOTOR_STATE, HOLD)
# kinds followed by a name: correlation/<worker>, status/<role>/<id>, alive/<role>/<id>
NAMED = (CORRELATION, STATUS, ALIVE)
KINDS = SIMPLE + NAMED


def _chunk(what: str, value: str) -> str:
    if not isinstance(value, str) or not value or "/" in value:
        raise ValueError(f"{what} {value!r}: must be a non-empty key chunk without '/'")
    return value


def prefix(rig: str) -> str:
    """vergence/<rig>/ (with the slash)."""
    return f"{ROOT}/{_chunk('rig', rig)}/"


def key(rig: str, kind: str) -> str:
    """vergence/<rig>/<kind> for one of SIMPLE."""
    if kind not in SIMPLE:
        raise ValueError(f"kind {kind!r}: not one of {', '.join(SIMPLE)}")
    return prefix(rig) + kind


def frame(rig: str) -> str:
    return key(rig, FRAME)


def preview(rig: str) -> str:
    return key(rig, PREVIEW)


def fixate(rig: str) -> str:
    return key(rig, FIXATE)


def hold(rig: str) -> str:
    return key(rig, HOLD)


def decision(rig: str) -> str:
    return key(rig, DECISION)


def profile(rig: str) -> str:
    return key(rig, PROFILE)


def command(rig: str) -> str:
    return key(rig, COMMAND)


def workers(rig: str) -> str:
    return key(rig, WORKERS)


def motor_state(rig: str) -> str:
    return key(rig, MOTOR_STATE)


def correlation(rig: str, worker: str) -> str:
    """vergence/<rig>/correlation/<worker>: one worker's correlations."""
    return f"{prefix(rig)}{CORRELATION}/{_chunk('worker id', worker)}"


def correlations(rig: str) -> str:
    """vergence/<rig>/correlation/*: every worker's correlations."""
    return correlation(rig, "*")


def status(rig: str, role: str, ident: str) -> str:
    """vergence/<rig>/status/<role>/<id>: a process's counters."""
    return f"{prefix(rig)}{STATUS}/{_chunk('role', role)}/{_chunk('id', ident)}"


def statuses(rig: str) -> str:
    """vergence/<rig>/status/**: every process's counters."""
    return f"{prefix(rig)}{STATUS}/**"


def alive(rig: str, role: str, ident: str) -> str:
    """vergence/<rig>/alive/<role>/<id>: a process's liveliness token."""
    return f"{prefix(rig)}{ALIVE}/{_chunk('role', role)}/{_chunk('id', ident)}"


def alives(rig: str, role: str | None = None) -> str:
    """vergence/<rig>/alive/** (every token), or vergence/<rig>/alive/<role>/* (one role's)."""
    return f"{prefix(rig)}{ALIVE}/**" if role is None else alive(rig, role, "*")


def everything(rig: str) -> str:
    """vergence/<rig>/**: every message of the rig (the liveliness tokens are apart: alives)."""
    return prefix(rig) + "**"


class Key(NamedTuple):
    """A parsed key: rig, kind (one of KINDS) and rest, everything after vergence/<rig>/."""

    rig: str
    kind: str
    rest: str

    def under(self, rig: str) -> str:
        """The same key under another rig."""
        return prefix(rig) + self.rest

    @property
    def name(self) -> str:
        """After the kind: the worker of correlation/<worker>, '<role>/<id>' of status and alive, else ''."""
        return self.rest[len(self.kind) + 1:] if self.kind in NAMED else ""

    @property
    def role(self) -> str:
        """status and alive: the process's role, else ''."""
        return self.name.split("/", 1)[0] if self.kind in (STATUS, ALIVE) else ""

    @property
    def ident(self) -> str:
        """status and alive: the process's id; correlation: the worker's id; else ''."""
        if self.kind == CORRELATION:
            return self.name
        return self.name.split("/", 1)[1] if self.kind in (STATUS, ALIVE) else ""


def kind_of(rest: str) -> str | None:
    """The kind (one of KINDS) of the part of a key after vergence/<rig>/, or None when it is none of the keys
    above (an unknown kind, a name missing, an empty chunk). correlation needs <worker>, status and alive
    <role>/<id>; a name may hold further chunks (a claim from the wire: the callers decide what to make of it)."""
    if rest in SIMPLE:
        return rest
    parts = str(rest).split("/")
    if not all(parts):
        return None
    if (parts[0] == CORRELATION and len(parts) >= 2) or (parts[0] in (STATUS, ALIVE) and len(parts) >= 3):
        return parts[0]
    return None


def parse(key_expr: str) -> Key | None:
    """vergence/<rig>/<rest> as a Key, or None when it is not under vergence/<rig>/ or kind_of(rest) is None."""
    root, _, tail = str(key_expr).partition("/")
    rig, _, rest = tail.partition("/")
    if root != ROOT or not rig:
        return None
    kind = kind_of(rest)
    return None if kind is None else Key(rig, kind, rest)
