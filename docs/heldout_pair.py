"""Accuracy of the network on any rectified pair with ground truth, drawn as tests/vergence/test_accuracy.py and
tests/vergence/sim/test_loop.py draw Middlebury's (README, "Held out: a real pair never used for tuning").

    python docs/heldout_pair.py static LEFT RIGHT DISP [--dscale S] [--seeds 0,1,2,3,4] [--n 500] [--faithful]
                                       [--set clip_fallback=false]
    python docs/heldout_pair.py loop LEFT RIGHT DISP [--dscale S] [--seeds 3,4,5] [--n 100] [--faithful]

DISP: the left image's disparity in px, a .npz (arr_0; inf, NaN or <= 0 = unknown) or an image (value / S).
static: per gain (the slave as is, 1.3 * I + 20 and 0.7 * I - 15, clipped) and seed, n visible points 40 px from
the border: the share answered confidently and the share of those within 1 px. loop: the closed loop of
tests/vergence/sim/test_loop.py (ideal motor, "p" controller, starts 10-40 px off drawn from seed + 1000, 8 frames;
converged = within 1 px by frame 5 and staying there) at n points per seed 60 px from the border, the same
points and starts at every gain, with each gain's paired difference to equal gain and its standard error. The draws are
tests/middlebury.py's points() and visible() on this pair's own disparity."""

from __future__ import annotations

import argparse
import math

import cv2
import numpy as np

import vergence
from vergence.control import ControlSettings
from vergence.motors import MotorSettings
from vergence.sim import Rig
from vergence.sim.loop import closed_loop, frames_to_converge

GAINS = {"equal": (1.0, 0.0), "bright": (1.3, 20.0), "dark": (0.7, -15.0)}
IDEAL_MOTOR = MotorSettings(tau_s=0.02, latency_s=0.0, max_accel_deg_s2=0.0, quantise=False)
P_CONTROL = ControlSettings(mode="p")


def load_disparity(path: str, scale: float) -> np.ndarray:
    if path.endswith(".npz"):
        d = np.load(path)["arr_0"].astype(np.float64)
    else:
        d = cv2.imread(path, cv2.IMREAD_UNCHANGED).astype(np.float64) / scale
    d[~np.isfinite(d) | (d < 0)] = 0
    return d


def visible(d: np.ndarray) -> np.ndarray:
    """Known and seen by the right camera (tests/middlebury.visible)."""
    h, w = d.shape
    xr = np.where(d > 0, np.arange(w)[None, :] - d, np.inf)
    right_min = np.minimum.accumulate(xr[:, ::-1], axis=1)[:, ::-1]
    shifted = np.concatenate([right_min[:, 1:], np.full((h, 1), np.inf)], axis=1)
    return (d > 0) & ~(shifted < xr + 0.5)


def points(ok: np.ndarray, n: int, seed: int, margin: int) -> list[tuple[int, int]]:
    """tests/middlebury.points."""
    rng = np.random.default_rng(seed)
    h, w = ok.shape
    out = []
    while len(out) < n:
        x, y = int(rng.integers(margin, w - margin)), int(rng.integers(margin, h - margin))
        if ok[y, x]:
            out.append((x, y))
    return out


def gained(img: np.ndarray, g: float, o: float) -> np.ndarray:
    if g == 1.0 and o == 0.0:
        return img
    return np.clip(img.astype(np.float32) * np.float32(g) + np.float32(o), 0, 255).astype(np.uint8)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mode", choices=["static", "loop"])
    ap.add_argument("left")
    ap.add_argument("right")
    ap.add_argument("disp")
    ap.add_argument("--dscale", type=float, default=1.0)
    ap.add_argument("--seeds")
    ap.add_argument("--n", type=int)
    ap.add_argument("--faithful", action="store_true")
    ap.add_argument("--gains", default="equal,bright,dark")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a Params field (repeatable)")
    a = ap.parse_args()
    left = cv2.imread(a.left, cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(a.right, cv2.IMREAD_GRAYSCALE)
    disp = load_disparity(a.disp, a.dscale)
    vis = visible(disp)
    params = vergence.FAITHFUL if a.faithful else vergence.Params()
    if a.set:
        def typed(key: str, text: str):  # as the field's current value: "false" is not a true string
            cur = getattr(params, key, None)
            if isinstance(cur, bool):
                if text.lower() not in ("true", "false", "1", "0"):
                    ap.error(f"--set {key}: true or false, not {text!r}")
                return text.lower() in ("true", "1")
            return type(cur)(text) if isinstance(cur, (int, float)) else text
        params = params.override(**{k: typed(k, v) for k, v in (kv.split("=", 1) for kv in a.set)})
    seeds = [int(s) for s in (a.seeds or ("0,1,2,3,4" if a.mode == "static" else "3,4,5")).split(",")]
    n = a.n or (500 if a.mode == "static" else 100)
    equal = None
    for gname in a.gains.split(","):
        g, o = GAINS[gname]
        if a.mode == "static":
            slave = gained(right, g, o)
            rows = []
            for seed in seeds:
                res = [(vergence.match(left, slave, p, params), disp[p[1], p[0]]) for p in points(vis, n, seed, 40)]
                conf = [abs(m.offset_px + d) <= 1.0 for m, d in res if m.confident]
                rows.append((100 * len(conf) / n, 100 * sum(conf) / max(1, len(conf))))
            print(f"{gname}: confident / right among confident, per seed {seeds}: "
                  + ", ".join(f"{c:.1f}/{r:.1f}" for c, r in rows)
                  + f"; mean {np.mean([c for c, _ in rows]):.1f}/{np.mean([r for _, r in rows]):.1f}, worst "
                  f"{min(c for c, _ in rows):.1f}/{min(r for _, r in rows):.1f} %", flush=True)
            continue
        out = []
        for seed in seeds:
            rng = np.random.default_rng(seed + 1000)
            for x, y in points(vis, n, seed, 60):
                px = float(rng.uniform(10, 40)) * rng.choice([-1, 1])
                base = Rig(left, right, disparity=disp, fixate=(x, y))
                rig = Rig(left, right, disparity=disp, fixate=(x, y),
                          start_pan_deg=math.degrees(base.pan_off_truth(px)), gain=g, offset=o)
                k = frames_to_converge(list(closed_loop(rig, 8, params, motor=IDEAL_MOTOR, control=P_CONTROL)))
                out.append(float(k is not None and k <= 5))
        out = np.array(out)
        line = f"{gname}: converged {100 * out.mean():.1f} % of {out.size} points"
        if gname == "equal":
            equal = out
        elif equal is not None:
            diff = out - equal
            line += (f"; paired against equal gain {100 * diff.mean():+.1f} points, standard error "
                     f"{100 * diff.std(ddof=1) / math.sqrt(diff.size):.1f}")
        print(line, flush=True)


if __name__ == "__main__":
    main()
