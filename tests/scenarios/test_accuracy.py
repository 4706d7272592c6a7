"""The network on real stereo pairs with ground truth (../shared/data/middlebury).

Points: random fovea centres per scene (seeded) whose ground truth is valid. For the default mode, valid also
means visible to the slave camera: an occluded point's content is not in the slave image at all, so no answer
can be right there (see middlebury.visible). The faithful check uses every known point.

The quick tests use 100 points of seed 0; the slow ones 500 points on each of seeds 0-4 with the slave image as
is, and on seeds 0-2 with the slave at another gain (slave = gain * I + offset, clipped: 1.3 / +20 and
0.7 / -15), and hold every seed (not the mean) to a floor: a rule tuned on one draw has to hold on the others."""

from __future__ import annotations

import functools

import cv2
import numpy as np
import pytest

import background
import sweeps
import vergence
from vergence.tools import evaluate
from vergence.tools.evaluate import GAINS
from middlebury import SCENES, load, needs_data, points, visible
from references import ref_winner

pytestmark = needs_data

N = 500


@pytest.mark.parametrize("name", SCENES)
def test_faithful_mode_gives_the_reference_winner(name):
    left, right, _ = load(name)
    pts = points(name, seed=0)
    got = [vergence.match(left, right, p, vergence.FAITHFUL).decision.k for p in pts]
    want = [ref_winner(name, x, y) for x, y in pts]
    assert got == want


@functools.lru_cache(maxsize=None)
def slave_image(name: str, gain: float = 1.0, offset: float = 0.0) -> np.ndarray:
    return evaluate.gained(load(name)[1], gain, offset)


@functools.lru_cache(maxsize=None)
def draw(name: str, seed: int, n: int, gain: float = 1.0, offset: float = 0.0, faithful: bool = False):
    """(share of points answered confidently, share of those within 1 px, share of all points within 1 px) for
    n visible points of `seed`, the slave at gain / offset (sweeps.draw: vergence.match at each point, the slave
    image slave_image's; the slow test's draws are done ahead in the background, tests/background.py)."""
    return background.get(sweeps.draw, name, int(seed), int(n), float(gain), float(offset), bool(faithful))


# Seed 0, 100 points (default Params): confident / within 1 px of those: cones 85 / 100 %, teddy 92 / 98.9 %,
# tsukuba 89 / 95.5 %, venus 93 / 100 %. Tsukuba's four misses of 89 on this draw (2 px at three points, 6 px at
# one) are one answer in 1.1 points here; on the 500-point draws of seeds 0-4 (the slow tests) it is right at 96.8 %
# or more on every seed (94.5 % before min_margin 0.25 and the support weights' new scales), so its floor here is
# 0.95 and the others' 0.97.
QUICK_RIGHT = {"cones": 0.97, "teddy": 0.97, "tsukuba": 0.95, "venus": 0.97}

@pytest.mark.parametrize("name", SCENES)
def test_default_mode_is_confident_and_right(name):
    conf, good, _ = draw(name, 0, 100)
    assert conf >= 0.85, f"confident at only {conf:.0%} of points"
    assert good >= QUICK_RIGHT[name], f"only {good:.1%} of confident answers within 1 px"


@pytest.mark.parametrize("name", SCENES)
def test_default_mode_beats_the_paper_where_confident(name):
    """Wherever the extended network commits, it is at least as often right as the paper's network overall."""
    conf, good, _ = draw(name, 0, 100)
    _, _, paper_good = draw(name, 0, 100, faithful=True)
    assert conf >= 0.85 and good > paper_good


# Floors per scene, (coverage, right among confident), for every seed and gain. Measured (this commit, 500 points
# per seed), worst seed: equal gain (seeds 0-4) / gain 1.3, +20 and 0.7, -15 (seeds 0-2):
#   cones   86.0 / 97.8 %   88.4 / 98.4 %   87.8 / 97.8 %
#   teddy   91.2 / 97.0 %   91.2 / 95.5 %   91.4 / 97.0 %
#   tsukuba 90.2 / 97.0 %   91.2 / 96.0 %   90.4 / 93.8 %
#   venus   92.2 / 98.5 %   92.2 / 98.9 %   92.0 / 98.7 %
# (main before this branch: cones 86.6 / 96.9, teddy 92.8 / 95.5, tsukuba 88.4 / 94.5, venus 94.6 / 97.7 % at equal
# gain; tsukuba's coverage 83.2 and 81.8 % under the two gains.) The targets (coverage >= 85 %, >= 97 %
# right on every seed) hold at equal gain on all four (tsukuba and teddy at 97.0 % on their worst seed); under the
# gains cones and venus meet them, teddy (95.5 % at 1.3, +20) and tsukuba (96.0 and 93.8 %) are short of 97 %
# right (coverage is met). The floors sit about a point under the worst. With clip_fallback (the default since the
# service does it too; the figures above are without): equal gain the same on every seed; under gain coverage up by
# 0-0.4 points and right among confident within 0.2 points on every seed (worst seeds: cones 88.6 / 98.2 % at 1.3,
# +20, teddy 91.6 / 95.5 %, tsukuba 90.6 / 93.8 % at 0.7, -15; the rest unchanged).
FLOORS = {
    "cones": (0.85, 0.97),
    "teddy": (0.90, 0.945),
    "tsukuba": (0.89, 0.935),
    "venus": (0.91, 0.975),
}
SEEDS_AT = {"equal": range(5), "bright": range(3), "dark": range(3)}
for _gain in GAINS:
    for _name in SCENES:
        for _seed in SEEDS_AT[_gain]:
            background.ahead(sweeps.draw, _name, _seed, N, *map(float, GAINS[_gain]), False,
                             tests="test_accuracy_holds_on_every_seed")


@pytest.mark.slow
@pytest.mark.parametrize("gain", list(GAINS))
@pytest.mark.parametrize("name", SCENES)
def test_accuracy_holds_on_every_seed(name, gain, capsys):
    cov_floor, right_floor = FLOORS[name]
    rows = [draw(name, seed, N, *GAINS[gain]) for seed in SEEDS_AT[gain]]
    cov = [r[0] for r in rows]
    right = [r[1] for r in rows]
    with capsys.disabled():
        print(f"\n{name} {gain}: coverage {100 * np.mean(cov):.1f} % (worst {100 * min(cov):.1f}), right among "
              f"confident {100 * np.mean(right):.1f} % (worst {100 * min(right):.1f}); per seed "
              + " ".join(f"{100 * c:.1f}/{100 * r:.1f}" for c, r in zip(cov, right)))
    assert min(cov) >= cov_floor, f"coverage {[round(100 * c, 1) for c in cov]} %"
    assert min(right) >= right_floor, f"right among confident {[round(100 * r, 1) for r in right]} %"


def test_halves_check_ignores_what_the_slave_clipped():
    """A fovea centred 4 px left of where a dark but textured part of the master (levels 2-20) meets a bright
    one: the slave at gain 0.7, -15 clips the dark part to black. The halves check leaves the clipped pixels out
    (a half mostly on them is not asked) and the network answers, right; before, the black halves found their
    best offsets anywhere and it abstained. The same fovea with the slave at equal gain: right as before."""
    rng = np.random.default_rng(7)
    master = cv2.GaussianBlur(rng.integers(40, 220, (120, 200)).astype(np.uint8), (3, 3), 0)
    master[:, 30:100] = cv2.GaussianBlur(rng.integers(2, 21, (120, 70)).astype(np.uint8), (3, 3), 0)
    d = 7
    slave = np.roll(master, -d, axis=1)  # content at master column x lies at slave column x - d
    dim = np.clip(slave.astype(np.float32) * np.float32(0.7) - np.float32(15), 0, 255).astype(np.uint8)
    assert (dim[:, 30 - d : 100 - d] == 0).all()
    params = vergence.Params(max_window=0)
    for img in (slave, dim):
        m = vergence.match(master, img, (96, 60), params)
        assert m.confident and abs(m.offset_px + d) <= 0.5, m.decision


def test_clip_fallback_answers_where_the_clipped_master_leaves_too_little():
    """Teddy, the slave at 1.3, +20: at (41, 164) every window abstains with the master clipped like the slave
    (its fovea flattened at the estimated clip level); with clip_fallback the unclipped master answers, within
    1 px of the truth. A confident answer of the clipped master is never replaced (the first tries are the same)."""
    left, _, disp = load("teddy")
    slave = slave_image("teddy", 1.3, 20.0)
    clipped = vergence.match(left, slave, (41, 164), clip_fallback=False)
    fallback = vergence.match(left, slave, (41, 164))  # clip_fallback is the default
    assert not clipped.confident
    assert fallback.confident and abs(fallback.offset_px + disp[164, 41]) <= 1.0
    for p in points("teddy", n=20, seed=0, mask=visible("teddy")):
        a = vergence.match(left, slave, p, clip_fallback=False)
        if a.confident:
            assert vergence.match(left, slave, p).decision == a.decision


def test_the_service_dynamic_window_falls_back_as_match_does():
    """The same fovea through the service's steps in process (WindowControl's states, make_frame, a worker's
    correlation, the reducer), one frame per state as the capture publishes them: the clipped windows abstain, the
    master was clipped, the unclipped windows follow and the first confident decision is match()'s with
    clip_fallback, field for field, reached after as many frames as match() tried windows."""
    from vergence.head.control import Controller
    from vergence.stages.frames import WindowControl, make_frame, plan_shards
    from vergence.stages.gather import reduce
    from vergence.network.retina import master_clipped
    from vergence.wire.messages import Frame
    from vergence.stages.shards import compute_correlation

    left, _, _ = load("teddy")
    slave = slave_image("teddy", 1.3, 20.0)
    x, y = 41, 164
    params = vergence.Params()
    want = vergence.match(left, slave, (x, y), params)
    wc, seen = WindowControl(params), []
    for fid in range(1, 3 * len(wc.states)):
        w, clip = wc.state
        try:
            f = make_frame(left, slave, rig="r", frame=fid, pan_rad=0.0, focal_px=500.0, params=params,
                           plan=plan_shards(["a"], left.shape[1] - w + 1), at=(x, y), window=w, clip=clip)
        except vergence.BorderError:
            wc.reset()
            continue
        if clip:
            wc.clipped(master_clipped(left, slave, y, w, params))
        f = Frame.from_bytes(f.to_bytes())
        prof, _ = reduce(f, np.atleast_2d(compute_correlation(f, "a").array()), params, Controller())
        seen.append((w, clip, prof.confident))
        if prof.confident:
            break
        wc.update(w, prof.confident, clip)
    assert want.confident and seen[-1] == (want.window, False, True)
    assert seen == [(w, True, False) for w in params.windows()] + \
        [(w, False, w == want.window) for w in params.windows() if w <= want.window]
    d = want.decision
    assert (prof.k, prof.k_sub, prof.v_shift, prof.confident, prof.offset_px) == \
        (d.k, d.k_sub, d.v, d.confident, d.offset_px)
