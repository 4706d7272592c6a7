"""The simulated rig: two cameras rotating about their optical centres in front of a rectified pair.

A camera whose rotation (camera to world) is R sees the pixel p of the unrotated image at K_v R^T K^-1 p,
so its view is cv2.warpPerspective(image, K_v R^T K^-1). K = [[f,0,cx],[0,f,cy],[0,0,1]] with the
principal point (cx, cy) = (W // 2, H // 2) of the source pair (the pixel the network's fovea is centred
on), K_v the same for the rendered view. A positive pan (R_y) turns the camera toward increasing image x
(the content moves left in the view), a positive tilt (R_x) toward decreasing y (up).

Two gimbals:
- "helmholtz" (default), R = R_x(tilt) R_y(pan): both cameras pan on one tilting platform, the rig of
  ALGORITHM.md ("two cameras on a common tilt axis"). The tilt turns about the baseline, so the rows of the
  rectified pair stay epipolar: the fixated point is on the same row in both views (no vertical disparity),
  and the slave is converged at pan atan((X - d - cx) / sqrt(f^2 + (Y - cy)^2)).
- "fick", R = R_y(pan) R_x(tilt) (each camera tilts on its own pan joint): converged at atan((X - d - cx) / f)
  exactly, but when Y != cy the fixated point sits a few pixels off the slave's centre row (up to 2-5 px at
  20-25 degrees of pan on Middlebury), which the paper's network (no vertical search) cannot absorb.

The master's pan and tilt are set once so that its view centre shows the fixation pixel (X, Y) of LEFT.
The slave shares the tilt and pans; it is converged when the fixated point (disparity d at (X, Y)) is on
its view's centre column."""

from __future__ import annotations

import math

import cv2
import numpy as np

from ..io.images import read_image
from ..spec import Key, parse
from .moving import MovingRig
from .optics import GIMBALS, Kept, Region, homography, option_number, rotation
from .scene import generate

__all__ = ["Rig", "rotation", "homography"]


def _read_gray(path: str, what: str) -> np.ndarray:
    try:
        return read_image(path)
    except ValueError as e:
        raise ValueError(f"{what}: {e}") from None


def _read_disparity(path: str, scale: float) -> np.ndarray:
    try:
        img = read_image(path, cv2.IMREAD_UNCHANGED)
    except ValueError as e:
        raise ValueError(f"disparity: {e}") from None
    if img.ndim == 3:
        img = img[..., 0]
    d = img.astype(np.float32) / float(scale)
    d[img == 0] = np.nan  # Middlebury: 0 is unknown
    return d


class Rig:
    """Master and slave cameras over a rectified stereo pair (LEFT = master's scene, RIGHT = slave's).

    left, right: uint8 gray images of equal size. disparity: None (unknown), a number (the disparity at
    the fixation point) or a map of LEFT in pixels (NaN: unknown). fixate: (X, Y) in LEFT (default: its
    centre). focal: f in pixels (default 0.8 x view width). size: (W, H) of the views (default: the
    pair's). noise: sigma of Gaussian sensor noise, both cameras, fresh every frame. gain, offset, blur:
    the slave's photometric difference (slave = gain * I + offset) and defocus (Gaussian sigma, px).
    vmis_px: vertical misalignment of the slave, an extra tilt that moves its content down by about vmis_px.
    start_pan_deg: the slave's pan before the loop starts. seed: the noise generator's seed. gimbal:
    "helmholtz" (a common tilt axis, default) or "fick" (see the module's docstring)."""

    def __init__(self, left: np.ndarray, right: np.ndarray, *, disparity=None,
                 fixate: tuple[int, int] | None = None, focal: float | None = None,
                 size: tuple[int, int] | None = None, noise: float = 0.0, gain: float = 1.0,
                 offset: float = 0.0, blur: float = 0.0, vmis_px: float = 0.0, start_pan_deg: float = 0.0,
                 seed: int = 0, gimbal: str = "helmholtz"):
        if left.ndim != 2 or right.ndim != 2 or left.dtype != np.uint8 or right.dtype != np.uint8:
            raise ValueError("left and right must be 2-D uint8 gray images")
        if left.shape != right.shape:
            raise ValueError(f"left and right differ in size: {left.shape[1]} x {left.shape[0]} and "
                             f"{right.shape[1]} x {right.shape[0]}")
        self.left, self.right = left, right
        hs, ws = left.shape
        self.src_size = (ws, hs)
        self.size: tuple[int, int] = tuple(size) if size is not None else (ws, hs)
        if self.size[0] < 16 or self.size[1] < 16:
            raise ValueError(f"size={self.size[0]}x{self.size[1]}: views must be at least 16 x 16")
        self.focal_px: float = float(focal) if focal is not None else 0.8 * self.size[0]
        if not (self.focal_px > 0 and math.isfinite(self.focal_px)):
            raise ValueError(f"focal={focal}: must be a positive number of pixels")
        x, y = fixate if fixate is not None else (ws // 2, hs // 2)
        if not (0 <= x < ws and 0 <= y < hs):
            raise ValueError(f"fixate={x},{y}: outside the {ws} x {hs} pair")
        self.fixation = (int(x), int(y))
        for name, v in (("noise", noise), ("blur", blur)):
            if not (v >= 0 and math.isfinite(v)):
                raise ValueError(f"{name}={v}: must be a finite number >= 0")
        for name, v in (("gain", gain), ("offset", offset), ("vmis", vmis_px), ("pan", start_pan_deg)):
            if not math.isfinite(v):
                raise ValueError(f"{name}={v}: must be a finite number")
        self.noise, self.gain, self.offset, self.blur = float(noise), float(gain), float(offset), float(blur)
        self.vmis_px = float(vmis_px)
        self.start_pan_rad: float = math.radians(start_pan_deg)
        self.disparity_map = disparity if isinstance(disparity, np.ndarray) else None
        if self.disparity_map is not None:
            if self.disparity_map.shape != left.shape:
                raise ValueError("the disparity map must have the size of LEFT")
            self.disparity = float(self.disparity_map[self.fixation[1], self.fixation[0]])
        else:
            self.disparity = float(disparity) if disparity is not None else math.nan
        if gimbal not in GIMBALS:
            raise ValueError(f"gimbal={gimbal!r}: must be one of {', '.join(GIMBALS)}")
        self.gimbal = gimbal
        f, (cxs, cys) = self.focal_px, (ws // 2, hs // 2)
        if gimbal == "helmholtz":
            # Tilt first (about the baseline) brings row Y to the horizon; the pans are then in that plane.
            self.tilt_rad = -math.atan((y - cys) / f)
            fy = math.hypot(f, y - cys)
        else:
            self.tilt_rad = math.atan(-(y - cys) * math.cos(math.atan((x - cxs) / f)) / f)
            fy = f
        self.master_pan_rad = math.atan((x - cxs) / fy)
        self.slave_tilt_rad = self.tilt_rad + math.atan(self.vmis_px / f)
        # The converged slave pan (NaN when the disparity is unknown).
        self.truth_pan_rad: float = math.atan((x - self.disparity - cxs) / fy)
        self._rng = np.random.default_rng(seed)
        self._banks: list[np.ndarray] = []  # per camera: [master, slave]
        self._views = Kept(self.VIEWS)  # the latest slave views rendered: (pan, region) -> view (read-only)
        self._master = self._warp(left, self.master_pan_rad, self.tilt_rad)

    # -- construction from the capture source text ------------------------------------------------------

    KEYS = ("left", "right", "disparity", "dscale", "d", "fixate", "focal", "size", "noise", "gain",
            "offset", "blur", "vmis", "pan", "seed", "gimbal")

    @classmethod
    def from_spec(cls, spec: str):
        """A rig from the text after `sim:` ("" = the generated scene, defaults everywhere).

        Items separated by ':' as key=value: left=PATH, right=PATH (a rectified pair), disparity=PATH
        (ground truth of LEFT, 0 = unknown) with dscale=S (stored value / S = pixels), or d=PX (the
        disparity at the fixation point); fixate=X,Y (default the centre), focal=F (px), size=WxH (views),
        noise=SIGMA, gain=G, offset=O, blur=S, vmis=PX, pan=DEG (the slave's start pan), seed=N,
        gimbal=helmholtz|fick.
        With motion=SPEC (vergence.sim.motion, e.g. motion=sine:z=0.8,amp=0.3,hz=0.5) the scene is the moving
        target on the physical rig instead (vergence.sim.moving.MovingRig.from_options: baseline=M,
        focal=PX, size=WxH, noise, seed, pan, texture=FILE|flat, target=M, bg=M).
        A bad key or value raises ValueError naming it."""
        return cls.from_items(parse(spec, cls.spec_keys(), "sim source"))

    @classmethod
    def spec_keys(cls) -> list[Key]:
        """The keys of from_spec (vergence.spec): text, read by from_options; motion=SPEC takes its own items."""
        keys = cls.KEYS + tuple(k for k in MovingRig.KEYS if k not in cls.KEYS)
        return [Key(k, "spec" if k == "motion" else "str") for k in keys]

    @classmethod
    def from_items(cls, items: dict[str, str | None]):
        """The rig of parsed spec items (None: not given): the moving target's with motion=, else the still one."""
        items = {k: v for k, v in items.items() if v is not None}
        if "motion" in items:
            return MovingRig.from_options(**items)
        physical = sorted(k for k in items if k not in cls.KEYS)
        if physical:
            raise ValueError(f"sim source: {physical[0]}= is the physical rig's: give motion= with it (e.g. "
                             f"sim:motion=still:z=0.8:{physical[0]}={items[physical[0]]})")
        return cls.from_options(**items)

    @classmethod
    def from_options(cls, **items: str | None) -> "Rig":
        """The same as from_spec, from keyword strings (None: default); used by `vergence sim`."""
        items = {k: v for k, v in items.items() if v is not None}

        def num(key, conv=float, default=None):
            return option_number(items, key, conv, default)

        def pair(key, sep, conv):
            if key not in items:
                return None
            try:
                a, b = (conv(p) for p in items[key].lower().split(sep))
            except ValueError:
                raise ValueError(f"sim source: {key}={items[key]!r} must be two numbers as A{sep}B") from None
            return a, b

        opts = dict(fixate=pair("fixate", ",", int), focal=num("focal"), size=pair("size", "x", int),
                    noise=num("noise", default=0.0), gain=num("gain", default=1.0),
                    offset=num("offset", default=0.0), blur=num("blur", default=0.0),
                    vmis_px=num("vmis", default=0.0), start_pan_deg=num("pan", default=0.0),
                    seed=num("seed", int, 0), gimbal=items.get("gimbal", "helmholtz"))
        if ("left" in items) != ("right" in items):
            raise ValueError("sim source: left= and right= go together (a rectified pair)")
        try:
            if "left" in items:
                left, right = _read_gray(items["left"], "left"), _read_gray(items["right"], "right")
                disparity = None
                if "disparity" in items:
                    disparity = _read_disparity(items["disparity"], num("dscale", default=1.0))
                elif "d" in items:
                    disparity = num("d")
                return cls(left, right, disparity=disparity, **opts)
            for key in ("disparity", "dscale", "d"):
                if key in items:
                    raise ValueError(f"sim source: {key}= needs left= and right= (the generated scene "
                                     "knows its own disparity)")
            sc = generate(opts["seed"])
            if opts["size"] is None:
                opts["size"] = (640, 480)
            return cls(sc.left, sc.right, disparity=sc.disparity, **opts)
        except ValueError as e:
            msg = str(e)
            raise ValueError(msg if msg.startswith("sim source") else f"sim source: {msg}") from None

    # -- rendering ----------------------------------------------------------------------------------------

    def _warp(self, img: np.ndarray, pan: float, tilt: float, region: Region | None = None) -> np.ndarray:
        h = homography(self.focal_px, self.src_size, self.size, pan, tilt, self.gimbal)
        if region is not None:
            h = region.matrix @ h
        return cv2.warpPerspective(img, h, self.size if region is None else region.size, flags=cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    _BANK, _PAD = 6, 64

    def noisy(self, img: np.ndarray, camera: int, y0: int = 0) -> np.ndarray:
        """img + Gaussian noise of sigma `noise`, rounded. The noise is cut at a random place out of a few
        fields pre-drawn for this camera (drawing 300 k normals per view took 3-4 ms; this takes well under
        1 ms). Each camera has its own fields: with shared ones, the slave's noise was often the master's
        shifted by a few pixels, a pattern the network matched perfectly on a flat wall and turned to. y0: img
        is the view's rows from y0 on (a band), and gets the noise those rows get in the whole view."""
        if self.noise <= 0:
            return img
        h, w = img.shape
        while len(self._banks) <= camera:
            shape = (self._BANK, self.size[1] + self._PAD, self.size[0] + self._PAD)
            self._banks.append(np.rint(self._rng.standard_normal(shape, dtype=np.float32)
                                       * np.float32(self.noise)).astype(np.int16))
        i, dy, dx = (int(v) for v in self._rng.integers(0, (self._BANK, self._PAD, self._PAD)))
        n = self._banks[camera][i, dy + y0:dy + y0 + h, dx:dx + w]
        return np.clip(img + n, 0, 255).astype(np.uint8)

    def master_view(self, t: float = 0.0, region: Region | None = None) -> np.ndarray:
        """The master's view without sensor noise (the scene is still: the same at every t); region: that part
        of it (vergence.sim.optics.Region)."""
        return self._master if region is None else region.of(self._master)

    def slave_view(self, slave_pan_rad: float, t: float = 0.0, region: Region | None = None) -> np.ndarray:
        """The slave's view at slave_pan_rad (radians) without sensor noise: warped, defocused, its gain;
        region: that part of it (a band is rendered with a margin for the defocus, then cut)."""
        if not math.isfinite(slave_pan_rad):
            raise ValueError(f"slave pan {slave_pan_rad} is not finite")
        # The scene is still: a slave holding its pan sees the same view, rendered once (a band's warp is most of
        # a frame's read, 80 us at 640 x 480, and a converged slave holds). Returned read-only: shared.
        key = (float(slave_pan_rad), None if region is None else region.key)
        view = self._views.get(key)
        if view is None:
            view = self._views.keep(key, self._render_slave(float(slave_pan_rad), region))
            view.setflags(write=False)
        return view

    VIEWS = 8  # slave views kept: the sub-views of an exposure (2 ms each) at one pan, a band and a preview

    def _render_slave(self, slave_pan_rad: float, region: Region | None) -> np.ndarray:
        cut, sigma = None, self.blur
        if region is not None and region.scale:
            sigma *= region.size[0] / self.size[0]
        elif region is not None and self.blur > 0:  # the defocus reads rows around the band: render them too
            y0, y1 = region.y0, region.y0 + region.size[1]
            m = math.ceil(4 * self.blur) + 1
            region = Region.band(self.size[0], max(0, y0 - m), min(self.size[1], y1 + m))
            cut = slice(y0 - region.y0, y1 - region.y0)
        slave = self._warp(self.right, slave_pan_rad, self.slave_tilt_rad, region)
        if sigma > 0:
            slave = cv2.GaussianBlur(slave, (0, 0), sigma)
        if cut is not None:
            slave = slave[cut]
        if self.gain != 1.0 or self.offset != 0.0:
            lin = slave.astype(np.float32) * np.float32(self.gain) + np.float32(self.offset)
            slave = np.clip(lin, 0, 255).astype(np.uint8)
        return slave

    def render(self, slave_pan_rad: float, t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(master, slave) uint8 gray views with sensor noise, the slave panned to slave_pan_rad (radians);
        the scene is still, so the time t does not matter (the moving scene's render takes it too)."""
        slave = self.slave_view(slave_pan_rad, t)
        return self.noisy(self._master, 0), self.noisy(slave, 1)

    # -- ground truth -------------------------------------------------------------------------------------

    @property
    def one_px_rad(self) -> float:
        """atan(1 / f): the pan of one pixel at the view centre (the convergence tolerance)."""
        return math.atan(1.0 / self.focal_px)

    def truth_pan(self, t: float = 0.0) -> float:
        """The converged pan at time t: the scene is still, always truth_pan_rad."""
        return self.truth_pan_rad

    def error_px(self, slave_pan_rad: float, t: float = 0.0) -> float:
        """f tan(pan - truth): how many pixels the slave has turned past the converged pan (positive: too far
        right, the fixated point is then left of the slave's centre). NaN when the truth is unknown."""
        return self.focal_px * math.tan(slave_pan_rad - self.truth_pan_rad)

    def pan_off_truth(self, px: float) -> float:
        """truth + atan(px / f): the slave pan that shows the fixated point px pixels left of its centre."""
        return self.truth_pan_rad + math.atan(px / self.focal_px)
