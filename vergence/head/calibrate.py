"""Calibrating a head on itself (`vergence calibrate`, issue #36): the slave steps through known pans on a still,
textured scene while the reducer is held, and the decisions' offsets are fitted against the motor's own history.

With the slave's pan p at each image's exposure (the delta of vergence.head.latency), a decision's offset at a
fovea u px right of the slave's principal point is f tan(atan(u / f) + p0 - p) - u: f, the focal length in pixels
(the images', whatever the settings say), and p0 the pan at which the slave's fovea sees the master's (the offset is
zero). Both come from one least-squares fit (Gauss-Newton
from the straight line's) over the decisions of images exposed while the motor stood still (during a move a
millisecond of timing is a fraction of a pixel: with them the fit left 0.3-0.5 px of residual and f 0.7-1 % high;
without, 0.01-0.02 px and within 0.2 %), their sigmas from bootstrap resamples of the steps. Whether the image
follows the motor at all is judged as the loop's own check judges it (vergence.head.follows.verdict, on r, the image's
motion over the motor's at the frames' focal length: the timing fit's slope over -focal_px): a camera that turns the
other way than the motor's settings say (offsets that grow with the pan), or an image that does not follow the
steps (a frozen slave camera, a slipping coupling, or a scene that moves), is refused with the check's advice.

With the distance Z of the fixated point (along the master's optical axis through the fovea, measured by the
user), the pan at which the slave should see it follows from the rig's geometry (vergence.head.depth, the master
pan and tilt as its frames say, 0 and 0 on a real head): the difference from p0 is the pan zero's error, the correction
to [actuator.motor] offset_deg. A zero off by e shifts every disparity by f tan(e): 2.6 px at 0.3 deg and f 500.

settings_lines and merge_settings write what was found as TOML: merged into an existing file line by line (its
comments and every other key kept), checked by reading it back.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..choices import Fault
from .depth import depth_from_pans
from .follows import ADVICE, verdict
from .latency import LatencyError, LatencyFit, fit_latency

__all__ = ["AXIS_SIGMA_M", "BIAS_PX", "CalibrationError", "HeadFit", "Solved", "fit_head", "pan_for_depth",
           "slope_focal", "solve_head", "calibration_plan", "merge_settings", "settings_text", "MIN_R2", "MAX_RMS_PX"]

MIN_R2 = 0.98  # of the offsets' variance the motor's motion must explain; a still textured scene gives > 0.999
MAX_RMS_PX = 0.3  # the fit's residual (px); on a still scene and a settled motor the sim leaves 0.01-0.02
# the steps about the present pan, in parts of the amplitude, alternating sides: 17 of them, so that the sub-pixel
# phase of the offsets (where the network's sub-pixel error lies) is sampled finely (with 9 the pan zero of the
# test's head spread over -1.488..-1.531 deg in 11 runs for -1.5, with 17 over -1.497..-1.511 in 7)
LEVELS = (1.0, -1.0, 0.5, -0.5, 0.75, -0.75, 0.25, -0.25, 0.875, -0.875, 0.625, -0.625, 0.375, -0.375, 0.125, -0.125,
          0.0)
SETTLE_S = 0.1  # a decision is used where the motor's pan was the same this long before its image's exposure ...
SETTLED_RAD = math.radians(0.1)  # ... within this (an encoder that flickers by a tick at rest is settled)


class CalibrationError(ValueError):
    """The calibration cannot be made; the message says why and what to do."""


@dataclass(frozen=True)
class HeadFit:
    """focal_px and its sigma; pan0_rad: the pan (as the motor reports it) at which the slave's fovea sees the
    master's, and its sigma; rms_px: the fit's residual; latency: the timing fit (vergence.head.latency) whose
    delta aligned the decisions with the motor; n: decisions used."""

    focal_px: float
    focal_sigma_px: float
    pan0_rad: float
    pan0_sigma_rad: float
    rms_px: float
    r2: float
    latency: LatencyFit
    n: int


def calibration_plan(p0: float, lo: float, hi: float, amplitude_rad: float, hold_s: float) -> list[tuple[float, float]]:
    """[(seconds from the start, pan)]: LEVELS from -amplitude to +amplitude about p0 (alternating sides, so a
    slow drift does not look like a slope), each held hold_s, the last back at p0; every pan within [lo, hi]."""
    out = []
    for i, k in enumerate(LEVELS):
        out.append((i * hold_s, min(hi, max(lo, p0 + k * amplitude_rad))))
    return out


def _model(f: float, p0: float, pan: np.ndarray, u: float) -> np.ndarray:
    """The offset at a fovea u px right of the slave's principal point: f tan(atan(u / f) + p0 - pan) - u."""
    return f * np.tan(math.atan2(u, f) + p0 - pan) - u


def _tan_fit(pan: np.ndarray, off: np.ndarray, f0: float, p00: float,
             u: float = 0.0) -> tuple[float, float, np.ndarray]:
    """(f, p0, residuals) of off = _model(f, p0, pan, u), Gauss-Newton from (f0, p00)."""
    f, p0 = f0, p00
    for _ in range(30):
        q = math.atan2(u, f) + p0 - pan
        sec2 = 1.0 / np.cos(q) ** 2
        r = off - (f * np.tan(q) - u)
        jac = np.stack([np.tan(q) - f * sec2 * u / (f * f + u * u), f * sec2], 1)
        step, *_ = np.linalg.lstsq(jac, r, rcond=None)
        f, p0 = f + float(step[0]), p0 + float(step[1])
        if abs(step[0]) < 1e-9 * max(1.0, abs(f)) and abs(step[1]) < 1e-12:
            break
    return f, p0, off - _model(f, p0, pan, u)


def fit_head(decisions: list[tuple[int, int, float]], states: list[tuple[int, float]],
             moves_ns: list[int] | None = None, u_px: float = 0.0, boots: int = 100, seed: int = 0,
             focal_px: float | None = None) -> HeadFit:
    """decisions: [(stamp ns, read ns, offset px)] of the confident decisions during the steps; states: [(t ns, pan
    rad)] of the motor; moves_ns: when each step was commanded (no decision of an image exposed from SETTLE_S
    after one to a state interval before one is used: the states' interpolation blurs a step's start); u_px: the
    fovea's column less the slave's principal point's (off the axis an image moves f sec^2 faster per radian: 7.5 %
    at 70 px and f 256, which a fit of f tan(p0 - pan) took for the focal length); focal_px: the frames' (the
    settings'), against which the image's motion is judged (verdict; None: its sign alone). Raises
    CalibrationError naming the cause and the fix: too few decisions (no texture), a motor that does not move, a
    camera that turns against it, an image that does not follow it, a poor fit (a moving scene)."""
    d = np.array(sorted(decisions), float) if decisions else np.zeros((0, 3))
    s = np.array(sorted(states), float) if states else np.zeros((0, 2))
    if len(s) >= 10 and np.ptp(s[:, 1]) < math.radians(0.1):
        raise CalibrationError(f"the motor moved {math.degrees(np.ptp(s[:, 1])):.3f} deg while it was commanded to "
                               "step: it does not follow (torque off, at a limit, jammed, or another rig's motor)")
    try:
        lat = fit_latency(decisions, states, either_sign=True, boots=20)
    except LatencyError as e:
        if e.slope is None:
            raise CalibrationError(str(e)) from None
        # the motor moved and the offsets did not follow it: the check's verdict, whatever the ratio says
        raise CalibrationError(f"the image does not follow the motor's steps (r2 {e.r2:.2f}, r "
                               f"{_ratio(e.slope, focal_px):+.2f}): {_why(Fault.SLAVE_FROZEN)}; or the scene "
                               "moved: keep it and the master still, the fovea on a textured surface, and try "
                               "again") from None
    r = _ratio(lat.slope, focal_px)
    if verdict(r) is Fault.REVERSED or lat.slope > 0:
        raise CalibrationError(f"the image moves against the motor ({lat.slope:+.0f} px/rad, r {r:+.2f}, r2 "
                               f"{lat.r2:.3f}): {_why(Fault.REVERSED)}; then calibrate again")
    t0 = d[0, 0]
    t = (d[:, 0] - t0) / 1e9 - lat.delta_s
    st = (s[:, 0] - t0) / 1e9
    # the decisions of images exposed on a settled motor: its pan the same SETTLE_S before and just after (where
    # the pan changes under an exposure, a ms of timing error is a fraction of a pixel: 0.3-0.5 px rms with them)
    pan_at = lambda x: np.interp(x, st, s[:, 1])  # noqa: E731
    inside = (t - SETTLE_S >= st[0]) & (t + 0.01 <= st[-1])
    settled = inside & (np.abs(pan_at(t - SETTLE_S) - pan_at(t)) <= SETTLED_RAD) & \
        (np.abs(pan_at(t + 0.01) - pan_at(t)) <= SETTLED_RAD)
    after = float(np.median(np.diff(st))) + 0.005 if len(st) > 1 else 0.01  # the states' interpolation spans this
    for m in (np.asarray(moves_ns, float) - t0) / 1e9 if moves_ns else ():
        settled &= ~((t - SETTLE_S <= m) & (m <= t + after))
    if settled.sum() < 20:
        raise CalibrationError(f"only {int(settled.sum())} decisions of images exposed while the motor stood still "
                               "(20 at least): hold each step longer (--hold-s) or run the camera faster")
    pan, off = pan_at(t[settled]), d[settled, 2]
    inside = settled
    line = np.polyfit(pan, off, 1)
    f, p0, res = _tan_fit(pan, off, -line[0], -line[1] / line[0], u_px)
    tot = float(np.sum((off - off.mean()) ** 2))
    rms = float(np.sqrt(np.mean(res ** 2)))
    r2 = 1.0 - float(np.sum(res ** 2)) / tot if tot > 0 else 0.0
    if r2 < MIN_R2 or rms > MAX_RMS_PX:
        raise CalibrationError(f"the offsets do not follow the motor well enough (r2 {r2:.4f}, want {MIN_R2}; residual "
                               f"{rms:.2f} px, want at most {MAX_RMS_PX}): keep the scene and the master still, "
                               "point the fovea at a textured surface, and try again")
    # the sigmas: bootstrap over the steps, not the decisions (each pan's sub-pixel error is shared by its
    # decisions: resampling them alone gave 0.03-0.05 px of focal sigma where the error was 0.4-1.1 px)
    step = np.concatenate([[0], np.cumsum(np.abs(np.diff(pan)) > SETTLED_RAD / 2)])
    groups = [np.flatnonzero(step == k) for k in range(step[-1] + 1)]
    rng = np.random.default_rng(seed)
    fs, ps = [], []
    for _ in range(boots):
        i = np.concatenate([groups[k] for k in rng.integers(0, len(groups), len(groups))])
        if np.ptp(pan[i]) < math.radians(0.1):
            continue
        bf, bp, _ = _tan_fit(pan[i], off[i], f, p0, u_px)
        fs.append(bf)
        ps.append(bp)
    return HeadFit(focal_px=f, focal_sigma_px=float(np.std(fs)), pan0_rad=p0, pan0_sigma_rad=float(np.std(ps)),
                   rms_px=rms, r2=r2, latency=lat, n=int(inside.sum()))


def _why(fault: Fault) -> str:
    """The loop's advice on the fault (vergence.head.follows.ADVICE), without its first clause (what was seen)."""
    return ADVICE[fault].split(": ", 1)[1]


def _ratio(slope: float, focal_px: float | None) -> float:
    """r of vergence.head.follows.verdict from the offsets' slope against the pan (px/rad; -focal where the image
    follows): the image's motion over the motor's at focal_px (without it, the slope's sign)."""
    if focal_px is not None and focal_px > 0 and math.isfinite(focal_px):
        return -slope / focal_px
    return -math.copysign(1.0, slope)


def pan_for_depth(z_m: float, baseline_m: float, focal_px: float, *, master_px: tuple[float, float] = (0.0, 0.0),
                  slave_px: tuple[float, float] | None = None, master_pan_rad: float = 0.0, tilt_rad: float = 0.0,
                  gimbal: str = "helmholtz", master: str = "left", axis_m: float = 0.0) -> float:
    """The slave's pan at which its pixel slave_px (off its principal point; default master_px: the same pixel,
    for cameras with one principal point) sees the point at depth z_m that the master sees at master_px:
    vergence.head.depth.depth_from_pans solved for the slave's pan (bisection)."""
    if not (z_m > 0 and math.isfinite(z_m)):
        raise CalibrationError(f"--distance {z_m}: must be a positive number of metres")
    s = 1.0 if master == "left" else -1.0

    def z(p: float) -> float:
        v = depth_from_pans(master_pan_rad, p, baseline_m, focal_px, tilt_rad=tilt_rad, master_px=master_px,
                            slave_px=master_px if slave_px is None else slave_px, gimbal=gimbal, master=master,
                            axis_m=axis_m)
        return v if math.isfinite(v) else math.inf

    # for a left master the slave (on the right) turns toward negative pans to converge: nearer as it turns
    far = master_pan_rad
    near = next((far - s * a for a in (1.4, 1.2, 1.0, 0.8, 0.6) if z(far - s * a) < math.inf), far - s * 0.4)
    if not z(near) < z_m:
        raise CalibrationError(f"--distance {z_m:g} m: nearer than the rig can converge on (baseline "
                               f"{baseline_m:g} m)")
    for _ in range(200):
        mid = 0.5 * (near + far)
        if z(mid) > z_m:
            far = mid
        else:
            near = mid
    return 0.5 * (near + far)


AXIS_SIGMA_M = 0.005  # the pan axis's offset is told where the points give it to this (else it is not measured)
# a floor under each point's pan sigma: the network's sub-pixel bias on a texture, which no resampling of one point's
# steps shows (three points through `vergence up`, 2026-12-04: 0.012-0.085 px off the simulator's truth)
BIAS_PX = 0.05


def slope_focal(f: float, axis_m: float, baseline_m: float, z_m: float, master_u: float, slave_u: float,
                master: str = "left") -> float:
    """The focal length a pure rotation's fit (fit_head: f tan(atan(u / f) + p0 - pan) - u, whose slope at p0 is
    f + u^2 / f) reads where the slave's pan axis is axis_m behind its optical centre: a pan step dp turns the camera
    by dp and moves its centre by axis_m dp sideways, so the image of the point (z_m deep, seen master_u px off the
    master's principal point and slave_u off the slave's) moves (f + u^2 / f) k dp, k = 1 + axis_m cos(alpha) / rho
    (rho: the point's distance from the slave's centre, alpha: its angle off the slave's axis). A 3 cm axis reads
    6 % more at 0.5 m, 1 % at 3 m."""
    if not axis_m:
        return f
    s, alpha = (1.0 if master == "left" else -1.0), math.atan(slave_u / f)
    x = z_m * master_u / f - s * baseline_m  # the point from the slave's centre at pan 0, then at its pan
    p = math.atan2(x, z_m) - alpha
    rho = math.hypot(x - axis_m * math.sin(p), z_m - axis_m * (math.cos(p) - 1.0))
    k = 1.0 + axis_m * math.cos(alpha) / rho
    slope = k * (f + slave_u * slave_u / f)
    return 0.5 * (slope + math.sqrt(max(slope * slope - 4 * slave_u * slave_u, 0.0)))


@dataclass(frozen=True)
class Solved:
    """solve_head's answer: the pan zero's error (rad), the baseline, the pan axis's offset behind the slave's optical
    centre, the focal length, each with its sigma (0 where not fitted)."""

    zero_rad: float
    baseline_m: float
    baseline_sigma_m: float
    axis_m: float
    axis_sigma_m: float
    focal_px: float
    focal_sigma_px: float


def solve_head(obs, slopes, f: float, baseline_m: float, axis_m: float = 0.0, *, fit_baseline: bool = False,
               fit_axis: bool = False, master: str = "left") -> Solved:
    """The head's geometry from its points (issue #36), least squares weighted by the sigmas (Gauss-Newton from the
    settings, the slopes by finite differences). obs: [(distance, p0, its sigma, pan_for_depth's geometry)], each
    p0 = pan_for_depth(distance, b, f, d) - zero: they give the zero, the baseline where fit_baseline (points at
    two distances or more) and the axis where fit_axis (three or more: a pan axis d behind the optical centre moves
    it d sin(p) sideways as the slave turns, which near points show). slopes: [(a fit's focal length, its sigma,
    its point's distance, master_u, slave_u)] (slope_focal): with any, the focal length is fitted too. The two tell
    each other: an off-centre point's pan turns with the focal length (atan(u / f)), and the slopes' focal length
    with the axis."""
    k = 1 + fit_baseline + fit_axis
    if obs and len(obs) < k:
        raise CalibrationError(f"the zero{', the baseline' * fit_baseline}{' and the pan axis' * fit_axis} need {k} "
                               f"points or more at different distances (given {len(obs)})")
    names = ["zero"] * bool(obs) + ["b"] * fit_baseline + ["d"] * fit_axis + ["f"] * bool(slopes)
    x = {"zero": 0.0, "b": baseline_m, "d": axis_m, "f": f}
    steps = {"zero": 1e-6, "b": 1e-4, "d": 1e-4, "f": 0.01}

    def residuals(x):
        r = [(pan_for_depth(z, x["b"], x["f"], axis_m=x["d"], **kw) - x["zero"] - p0) / sig for z, p0, sig, kw in obs]
        r += [(slope_focal(x["f"], x["d"], x["b"], z, um, us, master) - fi) / sig for fi, sig, z, um, us in slopes]
        return np.array(r)

    jac = np.zeros((len(obs) + len(slopes), 0))
    for _ in range(8 if names else 0):
        r0 = residuals(x)
        jac = np.stack([(residuals({**x, n: x[n] + steps[n]}) - r0) / steps[n] for n in names], axis=1)
        step, *_ = np.linalg.lstsq(jac, -r0, rcond=None)
        for n, v in zip(names, step):
            x[n] += v
        x["b"] = max(1e-3, x["b"])
    cov = np.linalg.pinv(jac.T @ jac) if names else np.zeros((0, 0))
    sig = dict(zip(names, np.sqrt(np.maximum(np.diag(cov), 0.0))))
    return Solved(float(x["zero"]), float(x["b"]), float(sig.get("b", 0.0)), float(x["d"]), float(sig.get("d", 0.0)),
                  float(x["f"]), float(sig.get("f", 0.0)))


def settings_text(values: dict[str, dict[str, float]]) -> str:
    """{table: {key: value}} as TOML lines."""
    out = []
    for table, kv in values.items():
        out.append(f"[{table}]")
        out += [f"{k} = {_value(v)}" for k, v in kv.items()]
    return "\n".join(out)


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(round(v, 6))
    return repr(v) if not isinstance(v, str) else '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'


_HEADER = re.compile(r"^\s*\[\s*([A-Za-z0-9_.\- ]+?)\s*\]\s*(#.*)?$")


def merge_settings(path: str | Path, values: dict[str, dict[str, float]]) -> str:
    """Merge {table: {key: value}} into the TOML file at path (created if missing): a key's line is replaced where
    it is, a missing key is added at the end of its table, a missing table at the end of the file; comments and
    every other key are kept. The result is read back and compared with what was meant before it is written; where
    the file says a key another way (an inline table, a dotted key), CalibrationError says which lines to put in
    by hand, and the file is left alone. Returns the new text."""
    path = Path(path)
    text = path.read_text() if path.exists() else ""
    try:
        before = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise CalibrationError(f"{path}: not TOML ({e}); nothing written") from None
    lines = text.splitlines()
    for table, kv in values.items():
        start = next((i for i, ln in enumerate(lines) if (m := _HEADER.match(ln)) and m.group(1) == table), None)
        if start is None:
            if lines and lines[-1].strip():
                lines.append("")
            lines.append(f"[{table}]")
            lines += [f"{k} = {_value(v)}" for k, v in kv.items()]
            continue
        end = next((i for i in range(start + 1, len(lines)) if _HEADER.match(lines[i]) or
                    lines[i].lstrip().startswith("[[")), len(lines))
        last = start
        for i in range(start + 1, end):
            if lines[i].strip() and not lines[i].lstrip().startswith("#"):
                last = i
        for k, v in kv.items():
            at = next((i for i in range(start + 1, end) if re.match(rf"^\s*{re.escape(k)}\s*=", lines[i])), None)
            if at is not None:
                lines[at] = f"{k} = {_value(v)}"
            else:
                last += 1
                end += 1
                lines.insert(last, f"{k} = {_value(v)}")
    new = "\n".join(lines) + "\n"
    want = _merged(before, values)
    try:
        got = tomllib.loads(new)
    except tomllib.TOMLDecodeError:
        got = None
    if got != want:
        raise CalibrationError(f"{path}: its tables are written in a way this merge does not edit (an inline table "
                               "or dotted keys); nothing written. Put these lines in by hand:\n" +
                               settings_text(values))
    path.write_text(new)
    return new


def _merged(before: dict, values: dict[str, dict[str, float]]) -> dict:
    import copy

    out = copy.deepcopy(before)
    for table, kv in values.items():
        node = out
        for part in table.split("."):
            node = node.setdefault(part, {})
        node.update(kv)
    return out
