"""The settings that are one of a few words, as enums (issue #34): which camera is the master, the gimbal, the
photometric mapping, the controller's mode. StrEnum: each member is its word (equal to the string, printed and
encoded as it), so settings files, JSON and `vergence sim`'s output are the same as with plain strings."""

from __future__ import annotations

from enum import StrEnum

__all__ = ["Side", "Gimbal", "Photometric", "ControlMode", "Fault", "check"]


class Side(StrEnum):
    """Which camera is the master (the fixed one): the other pans."""

    LEFT = "left"
    RIGHT = "right"


class Gimbal(StrEnum):
    """helmholtz: both cameras pan on one tilting platform (the paper's rig); fick: each camera tilts on its own
    pan joint."""

    HELMHOLTZ = "helmholtz"
    FICK = "fick"


class Photometric(StrEnum):
    """How the slave's gray levels are mapped onto the master's (vergence.network.retina.photometric)."""

    NONE = "none"
    AFFINE = "affine"
    HISTOGRAM = "histogram"


class ControlMode(StrEnum):
    """p: a proportional step per decision; predictive: a filter and predictors aimed at when the command acts."""

    P = "p"
    PREDICTIVE = "predictive"


class Fault(StrEnum):
    """What the loop found wrong with its own eyes or motor (vergence.head.doubt): it holds until it clears."""

    SLAVE_FROZEN = "slave_frozen"
    REVERSED = "reversed"
    STALLED = "stalled"
    MASTER_FROZEN = "master_frozen"


def check(kind: type[StrEnum], value, name: str) -> None:
    """ValueError `name=value: must be one of ...` unless value is one of kind's words."""
    if value not in tuple(kind):
        raise ValueError(f"{name}={value!r}: must be one of {', '.join(kind)}")
