"""A stereo scene the package generates itself: textured fronto-parallel planes at several depths.

The pair is rectified and consistent by construction: every layer is a texture defined in LEFT coordinates
with an integer disparity d, so a point at column x of LEFT is at column x - d of RIGHT on the same row,
and the nearer layer hides the farther one in both images. The disparity map of LEFT is exact (no
unknown pixels), so the converged pan of any fixation point is known. No external data, deterministic by
seed."""

from __future__ import annotations

import functools
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

__all__ = ["Scene", "generate", "texture"]


@dataclass(frozen=True)
class Scene:
    """A rectified pair (uint8 gray, equal size) and the disparity of LEFT in pixels (NaN: unknown)."""

    left: np.ndarray
    right: np.ndarray
    disparity: np.ndarray


def texture(rng: np.random.Generator, h: int, w: int, mean: float = 128.0,
            contrast: float = 48.0) -> np.ndarray:
    """Multi-scale noise (fine grain to blobs) as uint8: textured at every scale the network looks at.

    The coarse scales are drawn on a grid 1/4 as fine and upsampled (the same look, a fraction of the
    time)."""
    acc = np.zeros((h, w), np.float32)
    for sigma, weight, step in ((0.8, 0.6, 1), (2.0, 1.0, 1), (1.25, 1.0, 4), (3.0, 0.8, 4)):
        n = rng.standard_normal((-(-h // step), -(-w // step)), dtype=np.float32)
        n = cv2.GaussianBlur(n, (0, 0), sigma)
        if step > 1:
            n = cv2.resize(n, None, fx=step, fy=step, interpolation=cv2.INTER_CUBIC)[:h, :w]
        acc += weight * n / (n.std() + 1e-6)
    acc = (acc - acc.mean()) / (acc.std() + 1e-6)
    return np.clip(mean + contrast * acc, 0, 255).astype(np.uint8)


def generate(seed: int = 0, size: tuple[int, int] = (960, 720)) -> Scene:
    """A background plane (d = 8 px) and boxes and discs at 12..40 px, one of them on the image centre.

    size is (W, H) of the pair; the rig renders smaller views out of it, so that a rotated camera still
    sees texture instead of the black outside of the images. Drawing it takes half a second of a core; every
    process of a sim rig draws the same one (`vergence up`'s check of its --source, the capture, its standby, each
    restart), so a drawn scene is kept: in this process (its arrays read-only) and on disk (cache_dir(), under a
    name with this file's digest and numpy's and OpenCV's versions: a change draws anew; the KEEP newest). The
    same arrays either way."""
    return _cached(int(seed), (int(size[0]), int(size[1])))


def cache_dir() -> Path:
    """Where drawn scenes are kept: $XDG_CACHE_HOME/vergence/scenes (~/.cache/vergence/scenes)."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "vergence" / "scenes"


KEEP = 16  # scenes kept on disk (4 MB each at the default size)


@functools.lru_cache(maxsize=4)
def _cached(seed: int, size: tuple[int, int]) -> Scene:
    # the drawing is this file's code run by numpy's generator and OpenCV's filters: any of them changed, drawn anew
    code = Path(__file__).read_bytes() + f"{np.__version__} {cv2.__version__}".encode()
    digest = hashlib.sha1(code).hexdigest()[:12]
    path = cache_dir() / f"scene-{seed}-{size[0]}x{size[1]}-{digest}.npz"
    sc = None
    try:
        with np.load(path) as z:
            sc = Scene(z["left"], z["right"], z["disparity"])
    except (OSError, KeyError, ValueError):  # not kept yet (or unreadable: drawn again, and kept anew)
        pass
    if sc is None:
        sc = _draw(seed, size)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npz")
            np.savez(tmp, left=sc.left, right=sc.right, disparity=sc.disparity)
            os.replace(tmp, path)  # whole or not at all, for a process drawing it at the same time
            for old in sorted(path.parent.glob("scene-*.npz"), key=lambda p: p.stat().st_mtime)[:-KEEP]:
                old.unlink(missing_ok=True)
        except OSError:  # a read-only home: drawn in every process, as before
            pass
    for a in (sc.left, sc.right, sc.disparity):
        a.setflags(write=False)
    return sc


def _draw(seed: int, size: tuple[int, int]) -> Scene:
    rng = np.random.default_rng(seed)
    w, h = size
    dmax = 48
    wide = w + dmax
    # (disparity, mask in LEFT coordinates over the wide canvas): far to near.
    layers: list[tuple[int, np.ndarray]] = [(8, np.ones((h, wide), bool))]
    objects = []
    for _ in range(7):
        d = int(rng.integers(12, 41))
        cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
        objects.append((d, cx, cy))
    # One object on the centre, so that the default fixation has a clear depth.
    objects.append((24, w // 2, h // 2))
    objects.sort(key=lambda o: o[0])
    for i, (d, cx, cy) in enumerate(objects):
        m = np.zeros((h, wide), np.uint8)
        rx, ry = int(rng.integers(w // 16, w // 6)), int(rng.integers(h // 12, h // 5))
        if i % 2:
            cv2.ellipse(m, (cx, cy), (rx, ry), 0, 0, 360, 1, -1)
        else:
            cv2.rectangle(m, (cx - rx, cy - ry), (cx + rx, cy + ry), 1, -1)
        layers.append((d, m.astype(bool)))
    left = np.zeros((h, w), np.uint8)
    right = np.zeros((h, w), np.uint8)
    disp = np.zeros((h, w), np.float32)
    for d, mask in layers:
        # Each surface its own brightness and contrast, so that the objects show.
        tex = texture(rng, h, wide, float(rng.uniform(70, 185)), float(rng.uniform(28, 50)))
        ml = mask[:, :w]
        left[ml] = tex[:, :w][ml]
        disp[ml] = d
        # RIGHT(x) = layer(x + d): the layer's texture and mask shifted left by d.
        mr = mask[:, d:d + w]
        right[mr] = tex[:, d:d + w][mr]
    return Scene(left, right, disp)
