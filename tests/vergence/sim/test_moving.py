"""vergence.sim.moving: the moving target's views. The renderer warps each plane over the columns it can reach only
(_columns); here against warping every column, as it did before, byte for byte."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from vergence.sim.moving import MovingRig, _columns
from vergence.sim.optics import Region


def _every_column(rig: MovingRig, z: float, pan: float, region: Region | None) -> np.ndarray:
    """The pinhole view warped over its whole width, plane after plane (the renderer before _columns)."""
    size = rig.size if region is None else region.size
    hb = rig._homography(rig.bg_tex.shape, rig.bg_s, rig.bg_m, (0.0, 0.0), pan)
    if region is not None:
        hb = region.matrix @ hb
    out = cv2.warpPerspective(rig.bg_tex, hb, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    planes = [(z, rig._tex_mask, rig.target_s, 0.0)] + ([(rig.side_m, *rig._side)] if rig._side is not None else [])
    for pz, tex_mask, s, x in sorted(planes, key=lambda p: -p[0]):
        h = rig._homography(tex_mask.shape, s, pz, (0.0, 0.0), pan, x)
        if region is not None:
            h = region.matrix @ h
        tm = cv2.warpPerspective(tex_mask, h, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                 borderValue=(0, 0, 0, 0))
        a = tm[..., 1].astype(np.float32) * np.float32(1 / 255)
        out = np.rint(out * (1 - a) + tm[..., 0]).astype(np.uint8)
    return out


@pytest.mark.parametrize("opts", [dict(motion="sine:z=0.7,amp=0.25,hz=0.3", seed="11"),
                                  dict(motion="sine:z=0.5,amp=0.1,hz=1", seed="12", side="1.1", focal="700"),
                                  dict(motion="step:z0=0.4,z1=1.5,at=0.5", seed="13", size="320x240")],
                         ids=["demo-like", "side square", "small"])
def test_a_view_warped_over_the_columns_its_planes_reach_equals_one_warped_over_every_column(opts):
    rig = MovingRig.from_options(**opts)
    w, h = rig.size
    rng = np.random.default_rng(int(opts["seed"]))
    regions = [None, Region.band(w, h // 2 - 14, h // 2 + 15), Region.band(w, 0, 9), Region.scaled((w, h), (160, 120)),
               Region.window(-40, h // 3, w - 100, h // 3 + 60)]
    for i in range(40):
        z = float(rng.uniform(0.3, 1.6))
        # a few far turns: the target off the view, or its plane behind the camera (then every column)
        pan = float(rng.uniform(-1.3, 1.3)) if i % 5 == 0 else float(rng.uniform(-0.2, 0.2))
        region = regions[i % len(regions)]
        assert np.array_equal(rig._pinhole(z, (0.0, 0.0), pan, region), _every_column(rig, z, pan, region)), (z, pan)


def test_the_columns_a_plane_reaches():
    """The target straight ahead reaches the middle columns only; turned away, none; reaching behind, all."""
    rig = MovingRig.from_options(motion="sine:z=0.8,amp=0.3,hz=0.2", seed="1")
    w = rig.size[0]
    h = rig._homography(rig._tex_mask.shape, rig.target_s, 0.8, (0.0, 0.0), 0.0)
    c0, c1 = _columns(h, rig._tex_mask.shape, w)
    half = rig.target_m / 2 / 0.8 * rig.focal_px  # the target's half width in pixels at 0.8 m
    assert c0 == pytest.approx(w / 2 - half, abs=4) and c1 == pytest.approx(w / 2 + half, abs=4) and 0 < c0 < c1 < w
    away = rig._homography(rig._tex_mask.shape, rig.target_s, 0.8, (0.0, 0.0), math.radians(60))
    assert _columns(away, rig._tex_mask.shape, w)[1] <= _columns(away, rig._tex_mask.shape, w)[0]
    behind = rig._homography(rig._tex_mask.shape, rig.target_s, 0.8, (0.0, 0.0), math.radians(120))
    assert _columns(behind, rig._tex_mask.shape, w) == (0, w)


def test_the_background_held_by_a_camera_is_warped_once_and_every_view_is_the_same_bytes():
    """The background stands still: its warp is kept per (camera centre, pan, region) (the last 4), so the master's
    band (pan 0 always) is warped once over a run, and every view (master and slave, bands, whole, previews, a lens's)
    equals one rendered with nothing kept."""
    opts = dict(motion="sine:z=0.8,amp=0.3,hz=0.5", seed="21", side="1.5", k1="-0.1")
    kept, fresh = MovingRig.from_options(**opts), MovingRig.from_options(**opts)
    w, h = kept.size
    for k in range(60):
        t, pan = k / 60, -0.07 + 0.002 * (k % 7)
        region = [None, Region.band(w, 200 + k % 5, 240), Region.scaled(kept.size, (160, 120))][k % 3]
        for view in (lambda r: r.master_view(t, region), lambda r: r.slave_view(pan, t, region)):
            fresh._bg.clear()
            assert np.array_equal(view(kept), view(fresh))
    assert len(kept._bg) == 4
    band = Region.band(w, 220, 250)
    first = kept.master_view(0.0, band)
    warps = []
    real = cv2.warpPerspective
    try:
        cv2.warpPerspective = lambda src, *a, **kw: (warps.append(src.shape), real(src, *a, **kw))[1]
        again = kept.master_view(0.5, band)  # the target moved: its plane is warped again, the background is not
    finally:
        cv2.warpPerspective = real
    assert kept.bg_tex.shape not in warps and warps and not np.array_equal(first, again)


def test_the_target_is_sampled_exactly_to_rounding():
    """The target's texels reach the view as bilinear samples of them at the exact sub-pixel position, rounded: a
    triangle wave of 8 grey levels a texel (its rows alike), the target at depths that put it at sub-pixel offsets and
    scales, the master's row through its middle within 0.5 grey level of np.interp of the texels (its texture and
    mask warped as one 4-channel image; a 2-channel warp placed pixels on a 1/32 px grid: 0.55 off here)."""
    n = 64
    wave = np.minimum(np.arange(n) % 62, 62 - np.arange(n) % 62) * 8  # 0..248..0, a kink every 31 texels
    tex = np.tile(wave.astype(np.uint8), (n, 1))
    worst = 0.0
    for z in (0.61, 0.737, 0.8, 0.93):
        rig = MovingRig(f"still:z={z}", target_tex=tex, target_m=0.12, bg_m=3.0)
        view = rig.master_view()
        f, (cx, cy) = rig.focal_px, rig.head.principal
        s = rig.target_s
        u0 = (rig.target_tex.shape[1] - 1) / 2.0
        xs = np.arange(view.shape[1])
        u = (xs - cx) * z / (f * s) + u0  # each column's texel position (the master's plane is fronto-parallel)
        inside = (u >= 1) & (u <= rig.target_tex.shape[1] - 2)
        want = np.interp(u[inside], np.arange(rig.target_tex.shape[1]), rig.target_tex[0].astype(float))
        worst = max(worst, float(np.abs(view[cy, inside] - want).max()))
        assert inside.sum() > 50
    assert worst <= 0.5 + 1e-6, worst
