"""Whether the slave's image follows the motor, as one judgement: r, the image's motion over the motor's (at the
frames' focal length: 1 where all is right), judged the same by the loop's check pair by pair (vergence.head.doubt)
and by `vergence calibrate` over its steps (vergence.head.calibrate), and what to check for each fault, in the same
words wherever it is named (the reducer's status, /diagnostics, the monitor, calibrate's and latency's refusals)."""

from __future__ import annotations

from ..choices import Fault

__all__ = ["ADVICE", "FOLLOWS_MAX", "FOLLOWS_MIN", "REVERSED_MAX", "FOCAL_OFF", "focal_off", "verdict"]

FOLLOWS_MIN, FOLLOWS_MAX = 0.5, 2.2  # r in this range: the image follows (r: image motion / motor motion)
REVERSED_MAX = -0.35  # r at most this: the camera turns the other way
FOCAL_OFF = 0.2  # |r - 1| above this: the focal length is off

ADVICE = {
    Fault.SLAVE_FROZEN: "the slave's image does not follow the motor: a frozen slave camera (the driver repeating "
                        "its last image) or a slipping coupling between the motor and the camera; check the "
                        "camera's cable and driver, and the coupling",
    Fault.REVERSED: "the slave's image moves against the motor: the motor turns the other way than the encoder "
                    "says; flip [actuator.motor] direction (or the camera's mounting) and restart",
    Fault.STALLED: "the motor does not follow its commands: stalled, jammed, or its torque off (an overload); "
                   "check the motor's power, its torque and what blocks it",
    Fault.MASTER_FROZEN: "the master camera repeats the same image: a frozen master camera; check its cable and "
                         "driver",
}


def verdict(r: float) -> Fault | None:
    """What r, the slave image's motion over the motor's (as the frames' focal length predicts it), says of the
    camera: Fault.REVERSED at or below REVERSED_MAX (it turns the other way than the encoder says),
    Fault.SLAVE_FROZEN below FOLLOWS_MIN (it does not follow: a frozen camera, a slipping coupling), None where it
    follows (r far from 1: the focal length is off, focal_off). The one judgement of the check here, pair by pair,
    and of `vergence calibrate` on its fit of the steps (vergence.head.calibrate)."""
    if r <= REVERSED_MAX:
        return Fault.REVERSED
    return Fault.SLAVE_FROZEN if r < FOLLOWS_MIN else None


def focal_off(r: float) -> bool:
    """r (as verdict's) far enough from 1 to name the focal length off."""
    return abs(r - 1) > FOCAL_OFF


def fail_kind(r: float) -> str:
    """The kind of a pair that did not follow (vergence.head.doubt): "reversed" where r <= 2 REVERSED_MAX (-0.7: a
    slipping camera's pair, its target's motion mispredicted, reaches -0.6), else "frozen"."""
    return "reversed" if r <= 2 * REVERSED_MAX else "frozen"
