"""The slow tests' long computations, as top-level functions of their arguments (so that tests/background.py can do
them ahead in its worker processes, which import them by name): closed loops of the simulated rig, draws of
Middlebury points, and the layout's imports in fresh interpreters. Each is deterministic (seeded): done here or
there, the result is the same. The loops return their Steps without the layer-4 scores (vergence.sim.loop.Step.scores),
which no test of these reads and which would be 20 MB a run to carry back."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

import vergence
from middlebury import load, points, visible
from vergence.tools import evaluate
from vergence.head.control import ControlSettings
from vergence.head.timing import CameraTiming
from vergence.tools.evaluate import IDEAL_MOTOR, P_CONTROL, started_off
from vergence.sim.loop import closed_loop, frames_to_converge
from vergence.sim.moving import Head, MovingRig

F, B = 500.0, 0.06
HEAD = Head(B, F)  # tests/scenarios/test_tracking.py's head: b = 0.06 m, f = 500 px


def _lean(steps) -> list:
    return [dataclasses.replace(s, scores=None) for s in steps]


# -- tests/scenarios/test_tracking.py ----------------------------------------------------------------------------

def track(spec: str, mode: str = "predictive", rate: float = 60.0, frames: int = 300, seed: int = 0,
          noise: float = 0.0, start_px: float = 0.0) -> list:
    """The moving rig of `spec` on HEAD (seeded, with sensor noise), its slave started start_px off the truth, in
    `vergence sim`'s loop with the controller of `mode`: the Steps."""
    rig = MovingRig(spec, HEAD, seed=seed, noise=noise)
    rig.start_pan_rad = rig.pan_off_truth(start_px)
    return _lean(closed_loop(rig, frames, None, ControlSettings(mode=mode), None, rate))


def late(motion: str, latency: float, rate: float = 60.0, frames: int = 300, seed: int = 4, noise: str | None = None,
         **timing) -> list:
    """`vergence sim --motion M --focal 500 --rate R --frames N --camera-latency L ...` (the slave starting
    parallel, pan 0), the run's Steps."""
    from vergence.head.timing import CameraTiming

    rig = MovingRig.from_options(motion=motion, focal="500", seed=str(seed), noise=noise)
    return _lean(closed_loop(rig, frames, None, ControlSettings(), None, rate,
                             timing=CameraTiming(latency, **timing), seed=seed))


def bench_tracking(hzs: tuple[float, ...], rates: tuple[float, ...], seconds: float) -> list[dict]:
    """vergence.tools.bench.bench_tracking's rows (`vergence bench tracking`)."""
    from vergence.tools.bench import bench_tracking as rows

    return rows(hzs=hzs, rates=rates, seconds=seconds)


def p_still(gain: float) -> list:
    """The p controller at `gain`, the image 100 ms old when read, on a still target with sensor noise: 120
    frames at 60 Hz."""
    from vergence.head.timing import CameraTiming

    rig = MovingRig.from_options(motion="still:z=0.8", focal="500", noise="2", seed="6")
    return _lean(closed_loop(rig, 120, None, ControlSettings(mode="p", gain=gain), None, 60,
                             timing=CameraTiming(0.1)))


# -- tests/vergence/sim/test_loop.py ------------------------------------------------------------------------------

def loop_outcomes(name: str, seed: int, n: int, gain: float = 1.0, offset: float = 0.0) -> tuple[bool, ...]:
    """Whether the loop converges (within 1 px by frame 5, staying there) at each of n visible points of `seed`
    (starts 10-40 px off, drawn from seed + 1000), the slave camera at gain / offset: a tuple of bools. The first
    m of n points (and their starts) are the m points of the same seed drawn alone. (The loop of
    test_loop.run: 8 frames, the ideal motor, the p controller, default Params.)"""
    rng = np.random.default_rng(seed + 1000)
    out = []
    for x, y in points(name, n=n, seed=seed, margin=60, mask=visible(name)):
        rig = started_off(*load(name), x, y, rng, gain=gain, offset=offset)
        n_conv = frames_to_converge(list(closed_loop(rig, 8, vergence.Params(), motor=IDEAL_MOTOR,
                                                     control=P_CONTROL)))
        out.append(n_conv is not None and n_conv <= 5)
    return tuple(out)


# -- tests/scenarios/test_accuracy.py ------------------------------------------------------------------------------

def draw(name: str, seed: int, n: int, gain: float = 1.0, offset: float = 0.0, faithful: bool = False):
    """(share of points answered confidently, share of those within 1 px, share of all points within 1 px) for
    n visible points of `seed`, the slave at gain / offset."""
    left, right, disp = load(name)
    slave = evaluate.gained(right, gain, offset)
    params = vergence.FAITHFUL if faithful else vergence.Params()
    res = [(vergence.match(left, slave, p, params), disp[p[1], p[0]])
           for p in points(name, n=n, seed=seed, mask=visible(name))]
    right_ = [abs(m.offset_px + d) <= 1.0 for m, d in res]
    confident = [r for (m, _), r in zip(res, right_) if m.confident]
    return len(confident) / n, sum(confident) / max(1, len(confident)), sum(right_) / n



# -- tests/vergence/tools/test_faults.py -------------------------------------------------------------------------------

def faults(rates: tuple[float, ...], latencies: tuple[float, ...], seeds: tuple[int, ...], lies: tuple) -> list[dict]:
    """vergence.tools.faults.bench_faults's rows (`vergence bench faults`: virtual time, so done anywhere alike)."""
    from vergence.tools.faults import bench_faults

    return bench_faults(rates=rates, latencies=latencies, seeds=seeds, lies=lies)


# -- tests/vergence/head/test_doubt.py ---------------------------------------------------------------------------------

def teddy_rig(**kw):
    """Middlebury's Teddy on the simulated rig, fixated at (400, 240), 640 x 480."""
    from middlebury import ROOT
    from vergence.sim import Rig

    d = ROOT / "teddy"
    return Rig.from_options(left=str(d / "left.png"), right=str(d / "right.png"), disparity=str(d / "disparity.png"),
                            dscale="4", size="640x480", fixate="400,240", **kw)


def middlebury_lie(name: str, fixate: tuple[int, int], lie: str, fixations: dict, latency: float, seed: int,
                   frames: int):
    """Middlebury's `name` on the simulated rig (640 x 480, f 500 px, sensor noise 1) fixated at `fixate` of its left
    image, the slave converged there, lying as the spec `lie` says, the fovea moved as `fixations` says ({frame: (x,
    y)}), at 60 Hz with the images `latency` old: (the rig, its Steps)."""
    import json

    from middlebury import ROOT
    from vergence.sim import Rig
    from vergence.sim.faults import FAULT_KEYS, Faults
    from vergence.sim.fixation import truth_at
    from vergence.spec import parse

    s = json.loads((ROOT / "scenes.json").read_text())[name]
    rig = Rig.from_options(left=str(ROOT / s["left"]), right=str(ROOT / s["right"]),
                           disparity=str(ROOT / s["disparity"]), dscale=str(s["disparity_scale"]), size="640x480",
                           fixate="{},{}".format(*fixate), focal="500", noise="1")
    rig.start_pan_rad = truth_at(rig, 320, 240)[0]
    faults = Faults.take(parse(lie, FAULT_KEYS, "test"))
    return rig, list(closed_loop(rig, frames, None, ControlSettings(), None, 60.0, fixations=fixations,
                                 timing=CameraTiming(latency), faults=faults, seed=seed))


def teddy_lie(lie: str, latency: float) -> list:
    """Teddy at 60 Hz with sensor noise 1, the fovea moved at frame 30 to (150, 200), the slave lying (`lie`: freeze
    or slip) from 0.4 to 2.4 s, the image `latency` old when read: the loop's Steps over 5 s."""
    from vergence.sim.faults import FAULT_KEYS, Faults
    from vergence.spec import parse

    faults = Faults.take(parse(f"{lie}=0.4-2.4", FAULT_KEYS, "test"))
    return _lean(closed_loop(teddy_rig(noise="1"), 300, None, ControlSettings(), None, 60.0, fixations={30: (150, 200)},
                             timing=CameraTiming(latency), faults=faults, seed=0))


def late_camera(motion: str, rate: float, latency: float, seed: int) -> list:
    """The moving target at `rate`, the images `latency` old and the loop told they are not (`late=`), noise 1, f 500,
    the slave starting on the truth: the loop's Steps over 12 s."""
    from vergence.sim.faults import FAULT_KEYS, Faults
    from vergence.sim.moving import MovingRig
    from vergence.spec import parse

    rig = MovingRig.from_options(motion=motion, focal="500", seed=str(seed), noise="1")
    rig.start_pan_rad = rig.truth_pan(0.0)
    faults = Faults.take(parse(f"late={latency:g}", FAULT_KEYS, "test"))
    return _lean(closed_loop(rig, int(12 * rate), None, ControlSettings(), None, rate, timing=CameraTiming(latency),
                             faults=faults, seed=seed))


# -- tests/vergence/head/test_search.py --------------------------------------------------------------------------------

def lost(seed: int, kind: int, z: float, latency: float, rate: float = 60.0):
    """The sim's loop from a pan where the target is outside the band: (time first within 1 px or None, largest
    |pan| deg, faults)."""
    rig = MovingRig.from_options(motion=f"still:z={z}", focal="500", seed=str(seed), noise="1")
    truth = rig.truth_pan(0.0)
    rng = np.random.default_rng(seed)
    if kind < 2:
        rig.start_pan_rad = (45 if kind == 0 else -45) * math.pi / 180
    else:
        rig.start_pan_rad = truth + math.atan(rng.uniform(350, 450) * (1 if kind == 2 else -1) / F)
    steps = list(closed_loop(rig, int(4 * rate), None, ControlSettings(), None, rate, timing=CameraTiming(latency),
                             seed=seed))
    found = next((s.t_s for s in steps if abs(s.error_px) <= 1), None)
    return found, max(abs(s.pan_deg) for s in steps), {s.fault for s in steps if s.fault}


# -- tests/test_layout.py ----------------------------------------------------------------------------------------------

def probe(code: str, name: str) -> tuple[str, int, str, str]:
    """`python -c CODE NAME` in a fresh interpreter: (name, exit code, stdout, stderr)."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", code, name], capture_output=True, text=True, timeout=120)
    return name, r.returncode, r.stdout, r.stderr


# -- the command line (tests/vergence/head/test_depth.py) --------------------------------------------------------------

def cli(*args: str, timeout: float = 300):
    """`vergence ARGS...` run to its end (at most timeout s): its CompletedProcess, stdout and stderr as text (as
    procs.run)."""
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "services.ops.cli", *args], capture_output=True, text=True,
                          timeout=timeout)


def match_depth(name: str, baseline: float, focal: float, n: int = 120, seed: int = 11):
    """`vergence match LEFT RIGHT --json --baseline B --focal F --at X,Y ...` on Middlebury `name` at n visible
    points of `seed`."""
    import json

    from middlebury import ROOT

    scene = json.loads((ROOT / "scenes.json").read_text())[name]
    args = ["match", str(ROOT / scene["left"]), str(ROOT / scene["right"]), "--json", "--baseline", str(baseline),
            "--focal", str(focal)]
    for x, y in points(name, n, seed=seed, mask=visible(name)):
        args += ["--at", f"{x},{y}"]
    return cli(*args)


def sim_still_target(d: int, seed: int, *args: str):
    """`vergence sim` on a textured fronto-parallel plane at disparity d (px), a rectified pair with its disparity
    map written to a folder of its own (test_depth.still_target's), with more ARGS."""
    import tempfile
    from pathlib import Path

    import cv2

    from vergence.sim.scene import texture

    w, h = 640, 480
    with tempfile.TemporaryDirectory() as tmp:
        tex = texture(np.random.default_rng(seed), h, w + d)
        paths = [str(Path(tmp) / f"{n}{d}.png") for n in "lrd"]
        cv2.imwrite(paths[0], tex[:, :w])
        cv2.imwrite(paths[1], tex[:, d : d + w])
        cv2.imwrite(paths[2], np.full((h, w), d, np.uint8))
        return cli("sim", "--left", paths[0], "--right", paths[1], "--disparity", paths[2], "--dscale", "1", *args)
