"""Benchmarks of the library, each against baselines measured in the same run (interleaved), so that the
ratios hold on a noisy, shared machine. No zenoh here: the pipeline benchmark lives in services/."""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from ..network import kernel, retina
from ..network.match import match
from ..network.params import Params

__all__ = ["KernelCase", "CASES", "bench_kernel", "bench_match", "bench_messages", "message_samples", "numpy_correlate",
           "opencv_correlate"]


@dataclass(frozen=True)
class KernelCase:
    width: int
    window: int
    rows: int  # V = 2R + 1

    @property
    def name(self) -> str:
        return f"W={self.width} w={self.window} V={self.rows}"


CASES = [KernelCase(W, w, v) for W in (640, 1920, 3840) for w in (15, 31) for v in (1, 33)]


def opencv_correlate(fovea: np.ndarray, band: np.ndarray) -> np.ndarray:
    """What an OpenCV user would reach for: TM_SQDIFF of each float32 feature plane, summed."""
    f = fovea.astype(np.float32)
    b = band.astype(np.float32)
    return sum(cv2.matchTemplate(b[c], f[c], cv2.TM_SQDIFF) for c in range(f.shape[0]))


def numpy_correlate(fovea: np.ndarray, band: np.ndarray) -> np.ndarray:
    """A plain vectorised numpy L1 over all (v, k) at once, one window pixel at a time."""
    c, w, _ = fovea.shape
    nv, kk = band.shape[1] - w + 1, band.shape[2] - w + 1
    b = band.astype(np.int16)
    s = np.zeros((nv, kk), np.int32)
    for p in range(c):
        for i in range(w):
            for j in range(w):
                s += np.abs(b[p, i : i + nv, j : j + kk] - np.int16(fovea[p, i, j]))
    return 255.0 * w * w - s / 3.0


def _inputs(case: KernelCase, seed: int = 0):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 256, (case.window + case.rows + 1, case.width + 2), dtype=np.uint8),
                           (5, 5), 1.0)
    band = retina.planes(img)
    h = case.window // 2
    r = (case.rows - 1) // 2
    cx = case.width // 2
    fovea = np.ascontiguousarray(band[:, r : r + case.window, cx - h : cx + h + 1])
    return fovea, band


def _median_ms(samples: list[float]) -> float:
    return float(np.median(samples) * 1e3)


def bench_kernel(cases=CASES, repeats: int = 7, min_time: float = 0.02, numpy_limit: float = 2.0,
                 progress=None) -> list[dict]:
    """For each case, the implementations in turn (A B C A B C ...): medians in ms and ratios. OpenCV runs
    with its default threads; correlate on one (workers are processes: the parallelism is theirs).
    The numpy baseline is skipped (None) for cases where one call takes longer than numpy_limit seconds."""
    rows = []
    for case in cases:
        fovea, band = _inputs(case)
        impls = {"correlate": lambda: kernel.correlate(fovea, band), "opencv": lambda: opencv_correlate(fovea, band),
                 "numpy": lambda: numpy_correlate(fovea, band)}
        kernel.correlate(fovea, band)  # compile / warm
        t0 = time.perf_counter()
        impls["numpy"]()
        if time.perf_counter() - t0 > numpy_limit:
            del impls["numpy"]
        times: dict[str, list[float]] = {k: [] for k in impls}
        for _ in range(repeats):
            for name, fn in impls.items():
                n, t0 = 0, time.perf_counter()
                while True:
                    fn()
                    n += 1
                    el = time.perf_counter() - t0
                    if el >= min_time or name == "numpy":
                        break
                times[name].append(el / n)
        med = {k: _median_ms(v) for k, v in times.items()}
        row = {"case": case.name, "width": case.width, "window": case.window, "rows": case.rows,
               "correlate_ms": med["correlate"], "opencv_ms": med["opencv"], "numpy_ms": med.get("numpy"),
               "opencv_threads": cv2.getNumThreads(), "ratio_vs_opencv": med["correlate"] / med["opencv"],
               "ratio_vs_numpy": med["correlate"] / med["numpy"] if "numpy" in med else None}
        rows.append(row)
        if progress:
            progress(row)
    return rows


def bench_match(repeats: int = 400, seed: int = 0) -> dict:
    """vergence.match for one point of a 640 x 480 pair (default and faithful params), after warm-up,
    interleaved; and what the layer-1 features and the kernel take of it."""
    rng = np.random.default_rng(seed)
    big = cv2.GaussianBlur(rng.integers(0, 256, (480, 700), dtype=np.uint8), (5, 5), 1.2)
    master, slave = big[:, :640].copy(), big[:, 12:652].copy()
    default, paper = Params(), Params.paper()
    x, y = 320, 240
    fns = {"match": lambda: match(master, slave, None, default),
           "match_faithful": lambda: match(master, slave, None, paper),
           "features": lambda: retina.features(master, slave, (x, y), 15, default.vsearch)}
    fovea, band = retina.features(master, slave, (x, y), 15, default.vsearch)
    fns["kernel"] = lambda: kernel.correlate(fovea, band)
    for fn in fns.values():
        for _ in range(20):
            fn()
    times: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    return {k + "_ms": _median_ms(v) for k, v in times.items()}


def message_samples() -> dict:
    """One message of each hot kind at the pipeline's sizes: 640 x 480, w = 15, R = 6, two workers."""
    from ..wire import messages as M

    W, w, R = 640, 15, 6
    K, rows = W - w + 1, 2 * R + 1
    return {
        "frame": M.Frame(rig="head", frame=7, t_capture_ns=123, pan_rad=0.1, width=W, height=480, x=320, y=240,
                         window=w, vsearch=R, focal_px=512.0, fovea=bytes((w + 2) ** 2),
                         band=bytes((w + 2 * R + 2) * (W + 2)), plan=[["a-1", 0, K // 2], ["b-2", K // 2, K]],
                         master_band=bytes((w + 2) * (W + 2))),
        "correlation": M.Correlation(rig="head", frame=7, t_capture_ns=1, worker="a-1", k0=0, k1=K // 2, rows=rows,
                             scores=np.zeros((rows, K // 2)).tobytes(), t_done_ns=5),
        "decision": M.Decision(rig="head", frame=7, t_capture_ns=1, t_reduced_ns=2, window=w, k=3, k_sub=3.2,
                              v_shift=0, k_centre=3, direction=0, magnitude=0, offset_px=0.2, confidence=0.5,
                              confident=True, texture=9.0, pan_rad=0.0, x=320, y=240),
        "command": M.Command(rig="head", frame=7, t_capture_ns=1, pan_rad=0.2, correction_rad=0.01, direction=1,
                             magnitude_px=3.0, confidence=0.4, t_sent_ns=9),
    }


def bench_messages(repeats: int = 9, number: int = 2000) -> list[dict]:
    """Decode (msgspec, checked: Class.from_bytes) and encode time per message kind, in us (median over repeats
    of the best of 3 x number), against msgpack.unpackb of the same bytes to a dict (a parse, no checks), the
    baseline, interleaved in the same run."""
    import statistics
    import timeit

    import msgpack

    rows = []
    for kind, msg in message_samples().items():
        data, cls = msg.to_bytes(), type(msg)
        t: dict[str, list[float]] = {"decode_us": [], "msgpack_us": [], "encode_us": []}
        for _ in range(repeats):
            for name, fn in (("decode_us", lambda: cls.from_bytes(data)),
                             ("msgpack_us", lambda: msgpack.unpackb(data, raw=False)),
                             ("encode_us", msg.to_bytes)):
                t[name].append(min(timeit.repeat(fn, number=number, repeat=3)) / number * 1e6)
        r = {"kind": kind, "bytes": len(data), **{k: statistics.median(v) for k, v in t.items()}}
        r["vs_msgpack"] = r["decode_us"] / r["msgpack_us"]
        rows.append(r)
    return rows


def bench_tracking(hzs=(0.25, 0.5, 1.0, 2.0), rates=(30.0, 60.0, 120.0), modes=("p", "predictive"),
                   seconds: float = 5.0, seed: int = 0, baseline_m: float = 0.06, focal_px: float = 500.0,
                   progress=None) -> list[dict]:
    """Tracking error of the simulated loop (vergence.sim, virtual time) on `sine:z=0.8,amp=0.3,hz=F` for
    each frequency, camera rate and controller mode, over `seconds` from a converged start, statistics after
    the first second; then `step:z0=1.2,z1=0.6,at=1` at each rate and mode: the frames from the step to
    within 1 px for good, and the overshoot past the new truth. One dict per row (progress(row) as each is
    done)."""
    import math

    from ..head.control import ControlSettings
    from ..sim.loop import closed_loop, tracking_error
    from ..sim.moving import Head, MovingRig

    head = Head(baseline_m, focal_px)
    rows = []

    def loop(spec, rate, mode, frames):
        rig = MovingRig(spec, head, seed=seed)
        rig.start_pan_rad = rig.truth_pan(0.0)
        return list(closed_loop(rig, frames, None, ControlSettings(mode=mode), None, rate))

    for hz in hzs:
        for rate in rates:
            for mode in modes:
                spec = f"sine:z=0.8,amp=0.3,hz={hz:g}"
                steps = loop(spec, rate, mode, int(round(seconds * rate)))
                row = dict(motion=spec, rate_hz=rate, mode=mode, **tracking_error(steps, int(round(rate))),
                           fault_frames=_faulted(steps))
                rows.append(row)
                if progress:
                    progress(row)
    for rate in rates:
        for mode in modes:
            spec = "step:z0=1.2,z1=0.6,at=1"
            steps = loop(spec, rate, mode, int(round(2 * rate)))
            after = [s for s in steps if s.t_s >= 1.0]
            settle = next((i for i in range(len(after)) if all(abs(s.error_px) <= 1.0 for s in after[i:])), None)
            # the step brings the target nearer: the slave starts too far right (positive error); an
            # overshoot is a negative error
            over = max(0.0, -min(s.error_px for s in after))
            row = dict(motion=spec, rate_hz=rate, mode=mode, settle_frames=settle,
                       overshoot_px=over, **tracking_error(steps, int(round(rate)) + (settle or 0)),
                       fault_frames=_faulted(steps))
            rows.append(row)
            if progress:
                progress(row)
    for r in rows:
        for k, v in r.items():
            if isinstance(v, float) and not math.isfinite(v):
                r[k] = None
    return rows


def _faulted(steps) -> int:
    """The frames of a run on which the loop's doubt held a fault (a clean run: none)."""
    return sum(1 for s in steps if s.fault is not None)


CAMERA_VARIANTS = {"-": {}, "skew 8 ms": {"skew_s": 0.008}, "exposure 8 ms": {"exposure_s": 0.008}}


def bench_camera(latencies=(0.0, 0.033, 0.066, 0.1), rates=(30.0, 60.0), hzs=(0.5, 1.0),
                 variants=tuple(CAMERA_VARIANTS), modes=("predictive", "p"), seconds: float = 5.0, seed: int = 0,
                 progress=None) -> list[dict]:
    """Tracking with a real camera's timing (vergence.head.timing.CameraTiming): the image `latency` old when read,
    and each variant (none, the slave exposed 8 ms after the master, an exposure of 8 ms: motion blur), on
    `sine:z=0.8,amp=0.3,hz=F` at each camera rate and controller mode, as `vergence sim --motion ... --focal
    500 --camera-latency L` runs it (the slave starting parallel): RMS and maximum error from the first second
    to `seconds`. One dict per row (progress(row) as each is done)."""
    import math

    from ..head.control import ControlSettings
    from ..sim.loop import closed_loop, tracking_error
    from ..sim.moving import MovingRig
    from ..head.timing import CameraTiming

    rows = []
    for latency in latencies:
        for rate in rates:
            for hz in hzs:
                for variant in variants:
                    for mode in modes:
                        spec = f"sine:z=0.8,amp=0.3,hz={hz:g}"
                        rig = MovingRig.from_options(motion=spec, focal="500", seed=str(seed))
                        timing = CameraTiming(latency, **CAMERA_VARIANTS[variant])
                        steps = list(closed_loop(rig, int(round(seconds * rate)), None, ControlSettings(mode=mode),
                                                 None, rate, timing=timing, seed=seed))
                        e = tracking_error(steps, int(round(rate)))
                        row = dict(motion=spec, latency_ms=round(latency * 1e3, 1), rate_hz=rate, variant=variant,
                                   mode=mode, **{k: (v if math.isfinite(v) else None) if isinstance(v, float) else v
                                                 for k, v in e.items()}, fault_frames=_faulted(steps))
                        rows.append(row)
                        if progress:
                            progress(row)
    return rows
