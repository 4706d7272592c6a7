"""`vergence bench faults` (issue #35): each of the simulator's lies (vergence.sim.faults) at 30 and 60 Hz, with and
without 66 ms of camera latency, on the moving target and on the still scene, in `vergence sim`'s loop (virtual
time, f 500 px, b 0.06 m): how long the loop took to name the fault, how far the slave went past the pan the last
decision before the lie asked for (a reversed camera: from where it started), the commands sent during the fault,
and how long after the lie ended the fault had cleared with the slave camera within 1 px of the truth (its own pan:
after a slip the shaft stays off by what the motor moved while the coupling slipped); and the same runs
without a lie, whose faults are false ones. Two lies that are no faults, each from the start: `focal_true` (the
images at 1.6 x the focal length the loop is told, on a third scene too, a target stepping between 0.6 and 1.0 m
every second): when the loop named the focal length and the ratio it measured, and how far the steps after that
overshot; `backlash` (0.2 deg, with encoder noise 0.05 deg): its tracking error against the clean runs', both pooled
over the camera turned rigidly by each of SHIFTS_DEG from its encoder (`zero=`: where the motor's whole ticks fall on
the target's path; one such draw alone moved a clean run's RMS by up to 40 %, docs/FAULTS.md). Every row has the RMS
error of the slave camera (its own pan, not the shaft's) over its last 3 s. One dict per row."""

from __future__ import annotations

import math

__all__ = ["bench_faults", "LIES"]

# the lie of each row, over WINDOW; None: the clean run (its faults are false ones)
LIES = (None, "freeze", "slip", "reverse", "stall", "freeze_master", "black", "focal_true", "backlash")
SCENES = {"moving": "sine:z=0.8,amp=0.3,hz=0.5", "still": "still:z=0.8", "steps": "square:z0=0.6,z1=1.0,hz=0.5"}
FOCAL_TRUE = 1.6  # focal_true: the images' focal length over the one told (500 px)
NOISY = "backlash=0.2:encoder_noise=0.05"  # backlash: the motor's lies that are no fault
WINDOW = (1.0, 3.0)  # s: the lie from 1 to 3 s (reverse: from the start, the whole run)
SECONDS = 6.0
STILL_OFF_PX = 60.0  # the still scene: the slave starts this far off, and the lie begins as it corrects
SHIFTS_DEG = (0.0, 0.022, 0.044, 0.066)  # backlash: across a Dynamixel's 0.088 deg tick


def _spec(lie: str | None, start: float) -> str:
    if lie in (None, "focal_true"):
        return ""
    if lie == "backlash":
        return NOISY
    if lie == "reverse":
        return "reverse"
    return f"{lie}={start:g}-{WINDOW[1]:g}"


def _rms(steps) -> float:
    """The RMS of the slave camera's own error (not the shaft's: backlash leaves them apart) over the last 3 s."""
    late = [s.camera_error_px for s in steps if s.t_s >= SECONDS - 3.0]
    return math.sqrt(sum(e * e for e in late) / len(late))


def _focal_row(steps, stepping: bool) -> dict:
    """focal_true's figures: when the focal length was named and the ratio measured at the end, and on the stepping
    target the largest overshoot of a step (its error past 0, against its first frame's sign) begun after the naming
    (None: no step, or another scene)."""
    named = next((s for s in steps if s.focal_ratio is not None), None)
    over = None
    if named is not None and stepping:
        for k in range(int(named.t_s) + 1, int(SECONDS)):
            seg = [s for s in steps if k <= s.t_s < k + 1]
            if len(seg) > 1 and abs(seg[0].error_px) > 5:  # a step began here
                sign = math.copysign(1.0, seg[0].error_px)
                over = max(over or 0.0, max(max(0.0, -sign * s.error_px) for s in seg))
    return dict(focal_named_s=None if named is None else named.t_s, focal_ratio=steps[-1].focal_ratio,
                overshoot_px=over)


def _row(steps, lie: str | None, start: float, focal: float, scene: str = "moving") -> dict:
    """The figures of one run (see the module's text)."""
    faulted = [s for s in steps if s.fault]
    if lie in (None, "focal_true", "backlash"):
        extra = _focal_row(steps, scene == "steps") if lie == "focal_true" else {}
        return dict(false_fault_frames=len(faulted), rms_px=_rms(steps), **extra)
    end = SECONDS if lie == "reverse" else WINDOW[1]
    before = max((s for s in steps if s.t_s < start and s.confident), key=lambda s: s.t_s, default=steps[0])
    # the pan the last decision before the lie asked for, and how far past it (beyond, in the move's direction)
    asked = before.pan_deg + math.degrees(math.atan(before.offset_px / focal)) if before.confident else before.pan_deg
    way = 1.0 if asked >= before.pan_deg else -1.0
    during = [s for s in steps if start <= s.t_s < end]
    first = next((s for s in faulted if s.t_s >= start), None)
    excursion = max((max(0.0, way * (s.pan_deg - asked)) for s in during), default=0.0)
    if lie == "reverse":  # from the start: how far from where it started
        excursion = max((abs(s.pan_deg - before.pan_deg) for s in during), default=0.0)
    # back: the first frame after the lie with the fault cleared and the slave camera within 1 px of the truth (the
    # camera's own error: a slipped coupling keeps the motor's move during the slip between the shaft and the camera)
    back = None if lie == "reverse" else next(
        (s.t_s - end for s in steps if s.t_s >= end and not s.fault and abs(s.camera_error_px) <= 1), None)
    return dict(fault=first.fault if first else None, diagnosed_s=None if first is None else first.t_s - start,
                excursion_deg=excursion, excursion_px=focal * math.tan(math.radians(excursion)),
                commands_in_fault=sum(1 for s in faulted if s.target_deg is not None and s.t_s < end),
                recovered_s=back, false_fault_frames=sum(1 for s in faulted if s.t_s < start), rms_px=_rms(steps))


def bench_faults(rates=(30.0, 60.0), latencies=(0.0, 0.066), seeds=(0,), lies=LIES, progress=None) -> list[dict]:
    """Every lie x scene x rate x latency x seed (the scene's texture and the noise), as the module says."""
    from ..head.control import ControlSettings
    from ..head.timing import CameraTiming
    from ..sim.faults import FAULT_KEYS, Faults
    from ..sim.loop import closed_loop
    from ..sim.moving import MovingRig
    from ..spec import parse

    rows, clean = [], {}
    for scene in SCENES:
        for lie in lies:
            if scene == "steps" and lie not in (None, "focal_true"):
                continue  # the steps are focal_true's scene (and its clean run's)
            if lie == "freeze_master" and scene == "still":
                continue  # a clean still scene repeats its master: nothing tells a frozen one
            for rate in rates:
                for latency in latencies:
                    for seed in seeds:
                        f = 500.0 * (FOCAL_TRUE if lie == "focal_true" else 1.0)
                        start = 0.0 if lie in ("reverse", "focal_true", "backlash") else (
                            0.05 if scene == "still" else WINDOW[0])

                        def loop(spec: str, scene=scene, rate=rate, latency=latency, seed=seed, f=f):
                            rig = MovingRig.from_options(motion=SCENES[scene], focal=f"{f:g}", seed=str(seed),
                                                         noise="1")
                            rig.start_pan_rad = rig.truth_pan(0.0) - (
                                math.atan(STILL_OFF_PX / f) if scene == "still" else 0.0)
                            return list(closed_loop(rig, int(round(SECONDS * rate)), None, ControlSettings(), None,
                                                    rate, timing=CameraTiming(latency), seed=seed, focal_px=500.0,
                                                    faults=Faults.take(parse(spec, FAULT_KEYS, "bench faults"))))

                        steps = loop(_spec(lie, start))
                        row = dict(lie=lie or "-", scene=scene, rate_hz=rate, latency_ms=round(latency * 1e3),
                                   seed=seed, **_row(steps, lie, start, 500.0, scene))
                        run = (scene, rate, latency, seed)
                        if lie is None:
                            clean[run] = row["rms_px"]
                        elif lie == "backlash":  # (against the clean runs over the same shifts)
                            pairs = [(_rms(loop(f"zero={z:g}")), _rms(loop(f"{NOISY}:zero={z:g}"))) if z else
                                     (clean[run] if run in clean else _rms(loop("")), row["rms_px"])
                                     for z in SHIFTS_DEG]
                            c = math.sqrt(sum(a * a for a, _ in pairs))
                            row["rms_vs_clean"] = math.sqrt(sum(b * b for _, b in pairs)) / c if c > 0 else None
                        rows.append(row)
                        if progress:
                            progress(row)
    return rows
