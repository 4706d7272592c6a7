"""A physical rig and a scene that moves in depth: the simulator of dynamic vergence.

The head (Head): two pinhole cameras of focal f px with the principal point at the view centre
(W // 2, H // 2) unless cx=, cy= say otherwise, and radial distortion k1=, k2= (issue #36), the master at the
origin looking along +z, the slave baseline_m to its right (+x), both upright (y down). A point at depth Z on the
master's optical axis has the disparity d = b f / Z, and the slave fixates it at the pan -atan(b / Z) (positive pan
turns the slave toward +x, as everywhere here).

The scene (MovingRig): a textured fronto-parallel target, a square target_m wide centred on the master's
optical axis at the distance Z(t) of a trajectory (vergence.sim.motion), in front of a textured background
plane at bg_m; with side_m, a second textured square standing still at that distance to the right of the target
(its centre seen 0.3 W right of the master's principal point, 0.2 W wide there): a third distance in one view,
for `vergence calibrate`'s pan axis. Each view is rendered from the geometry: the plane-to-view homography
K R^T [s e1, s e2, (0, 0, Z) - C - s (u0, v0, 0)] of each textured plane (s metres per texel, (u0, v0) its
centre texel, C the camera's centre, R its rotation), the target blended over the background through its
warped mask. Time is whatever the caller says (render(pan, t)): virtual in `vergence sim`, the wall clock
since start in the capture's sim source."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..io.images import read_image
from .motion import Motion, parse_motion
from .optics import Kept, Region, intrinsics, option_number, rotation
from .scene import texture

__all__ = ["Head", "MovingRig"]


@dataclass(frozen=True)
class Head:
    """The rig's geometry: baseline (m), focal length (px), view size (W, H), both cameras' principal point
    (cx, cy) (None: the view centre (W // 2, H // 2)) and radial distortion k1, k2 (OpenCV's plumb_bob; 0: a
    pinhole)."""

    baseline_m: float = 0.06
    focal_px: float = 512.0
    size: tuple[int, int] = (640, 480)
    cx: float | None = None
    cy: float | None = None
    k1: float = 0.0
    k2: float = 0.0
    axis_m: float = 0.0  # the slave's pan axis this far behind its optical centre (the centre turns about it)

    def __post_init__(self):
        if not (self.baseline_m > 0 and math.isfinite(self.baseline_m)):
            raise ValueError(f"baseline={self.baseline_m}: must be a positive number of metres")
        if not (self.focal_px > 0 and math.isfinite(self.focal_px)):
            raise ValueError(f"focal={self.focal_px}: must be a positive number of pixels")
        if self.size[0] < 16 or self.size[1] < 16:
            raise ValueError(f"size={self.size[0]}x{self.size[1]}: views must be at least 16 x 16")
        for key, v, most in (("cx", self.cx, self.size[0]), ("cy", self.cy, self.size[1])):
            if v is not None and not 0 <= v <= most:
                raise ValueError(f"{key}={v}: the principal point must lie in the view (0..{most})")
        if not (abs(self.k1) <= 1 and abs(self.k2) <= 1):
            raise ValueError(f"k1={self.k1:g}, k2={self.k2:g}: radial distortion coefficients within +-1")
        if not (abs(self.axis_m) <= 0.5):
            raise ValueError(f"axis={self.axis_m:g}: the pan axis within 0.5 m of the optical centre")
        self.lens  # noqa: B018 (its own checks)

    @property
    def lens(self):
        """Both cameras' vergence.io.lens.Lens (None: pinhole)."""
        if not (self.k1 or self.k2):
            return None
        from ..io.lens import Lens

        return Lens(self.focal_px, *self.principal, k1=self.k1, k2=self.k2)

    @property
    def principal(self) -> tuple[float, float]:
        return (self.cx if self.cx is not None else self.size[0] // 2,
                self.cy if self.cy is not None else self.size[1] // 2)

    def disparity_px(self, z_m: float) -> float:
        """d = b f / Z of a point at depth Z on the master's axis."""
        return self.baseline_m * self.focal_px / z_m

    def slave_centre(self, pan: float) -> tuple[float, float]:
        """The slave's optical centre (x, z) at this pan: (b, 0), turned on a circle about the pan axis axis_m
        behind it."""
        return self.baseline_m + self.axis_m * math.sin(pan), self.axis_m * (math.cos(pan) - 1.0)

    def converged_pan(self, z_m: float) -> float:
        """The slave pan (radians) that fixates the point at depth Z on the master's axis: -atan(b / Z) (with a pan
        axis off the optical centre, the pan at which the centre then sees it there)."""
        p = -math.atan(self.baseline_m / z_m)
        for _ in range(6 if self.axis_m else 0):
            x, z = self.slave_centre(p)
            p = -math.atan2(x, z_m - z)
        return p

    def depth(self, slave_pan_rad: float) -> float:
        """The inverse: the depth on the master's axis the slave fixates at this pan (inf when parallel)."""
        if not slave_pan_rad < 0:
            return math.inf
        x, z = self.slave_centre(slave_pan_rad)
        return z + x / math.tan(-slave_pan_rad)

    @property
    def K(self) -> np.ndarray:
        return intrinsics(self.focal_px, *self.principal)


class _Noise:
    """Per-camera Gaussian sensor noise cut out of a few pre-drawn fields (as vergence.sim.rig.Rig)."""

    BANK, PAD = 6, 64

    def __init__(self, sigma: float, seed: int):
        self.sigma = float(sigma)
        self.rng = np.random.default_rng(seed + 1_000_003)
        self.banks: list[np.ndarray] = []

    def __call__(self, img: np.ndarray, camera: int, size: tuple[int, int] | None = None, y0: int = 0) -> np.ndarray:
        """img with camera's noise; img is rows y0.. of a view of `size` (default: img's own)."""
        if self.sigma <= 0:
            return img
        h, w = img.shape
        vw, vh = size if size is not None else (w, h)
        while len(self.banks) <= camera:
            shape = (self.BANK, vh + self.PAD, vw + self.PAD)
            self.banks.append(np.rint(self.rng.standard_normal(shape, dtype=np.float32)
                                      * np.float32(self.sigma)).astype(np.int16))
        i, dy, dx = (int(v) for v in self.rng.integers(0, (self.BANK, self.PAD, self.PAD)))
        return np.clip(img + self.banks[camera][i, dy + y0:dy + y0 + h, dx:dx + w], 0, 255).astype(np.uint8)


class MovingRig:
    """The head in front of the moving target (see the module's docstring).

    motion: a Motion or its spec text. target_tex: the target's texture (uint8 gray; None: procedural,
    "flat": uniform gray, no texture at all). target_m: the target's width (default: 240 px wide at its
    farthest). bg_m: the background's distance (default max(3, 2 x the farthest target)). noise: sensor
    noise sigma, each camera its own. start_pan_deg: the slave's pan before the loop starts. side_m: the distance
    of a second square standing right of the target (None: none)."""

    # the master looks straight ahead, untilted (both gimbals agree there): for the depth of the fixated point
    master_pan_rad = 0.0
    tilt_rad = 0.0
    gimbal = "helmholtz"

    def __init__(self, motion: Motion | str, head: Head | None = None, *, target_tex: np.ndarray | str | None = None,
                 target_m: float | None = None, bg_m: float | None = None, noise: float = 0.0,
                 start_pan_deg: float = 0.0, seed: int = 0, side_m: float | None = None):
        self.motion = parse_motion(motion) if isinstance(motion, str) else motion
        self.head = head or Head()
        self.size = self.head.size
        self.focal_px = self.head.focal_px
        zmin, zmax = self.motion.z_range
        f = self.focal_px
        self.target_m = float(target_m) if target_m is not None else 240.0 * zmax / f
        self.side_m = None if side_m is None else float(side_m)
        if self.side_m is not None and not (self.side_m > 0 and math.isfinite(self.side_m)):
            raise ValueError(f"side={side_m}: must be a positive distance in metres")
        far = max(zmax, self.side_m or 0.0)
        self.bg_m = float(bg_m) if bg_m is not None else max(3.0, 2.0 * far)
        if not (self.target_m > 0 and math.isfinite(self.target_m)):
            raise ValueError(f"target={target_m}: must be a positive width in metres")
        if not (math.isfinite(self.bg_m) and self.bg_m > far):
            raise ValueError(f"bg={bg_m}: the background must be farther than the target's farthest {zmax:g} m"
                             + (f" and the side square's {self.side_m:g} m" if self.side_m else ""))
        if not (noise >= 0 and math.isfinite(noise)):
            raise ValueError(f"noise={noise}: must be a finite number >= 0")
        if not math.isfinite(start_pan_deg):
            raise ValueError(f"pan={start_pan_deg}: must be a finite number")
        self.start_pan_rad = math.radians(start_pan_deg)
        rng = np.random.default_rng(seed)
        # the target: about one texel per pixel at the middle of its range
        zref = math.sqrt(zmin * zmax)
        n = max(16, int(round(self.target_m * f / zref)))
        if isinstance(target_tex, str) and target_tex == "flat":
            tex = np.full((n, n), 128, np.uint8)
        elif target_tex is not None:
            if not (isinstance(target_tex, np.ndarray) and target_tex.ndim == 2 and target_tex.dtype == np.uint8):
                raise ValueError("texture: must be a 2-D uint8 gray image")
            th, tw = target_tex.shape
            tex = cv2.resize(target_tex, (n, max(16, round(n * th / tw))), interpolation=cv2.INTER_AREA)
        else:
            tex = texture(rng, n, n, float(rng.uniform(110, 150)), 48.0)
        self.target_tex = tex
        self.target_s = self.target_m / tex.shape[1]  # metres per texel
        # the background: one texel per pixel, wide enough for +-60 degrees
        w, h = self.size
        bw, bh = 3 * w + 64, 3 * h + 64
        self.bg_tex = texture(rng, bh, bw, float(rng.uniform(80, 170)), 40.0)
        self.bg_s = self.bg_m / f
        self.noise = _Noise(noise, seed)
        self._tex_mask = _with_mask(tex)
        self._side = None  # (its texture and mask, metres per texel, its centre's x)
        self._bg = Kept(4)  # the background's last warps: (centre, pan, region) -> view (the master's never changes)
        if self.side_m is not None:
            n = max(16, round(0.2 * w))
            stex = texture(rng, n, n, float(rng.uniform(90, 160)), 48.0)
            self._side = (_with_mask(stex),
                          self.side_m / f, 0.3 * w * self.side_m / f)

    # -- geometry ---------------------------------------------------------------------------------------

    def truth_pan(self, t: float) -> float:
        """The converged slave pan at time t: -atan(b / Z(t))."""
        return self.head.converged_pan(self.motion.z(t))

    @property
    def truth_pan_rad(self) -> float:
        return self.truth_pan(0.0)

    def truth_at(self, x: float, y: float, t: float = 0.0) -> float:
        """The converged slave pan at time t for the fovea at the master's pixel (x, y): the pan at which the
        slave shows the point there (on the target, or else on the background) on the same column x. With
        q = P - C (the point from the slave's centre) a pan p puts it at column cx + f tan(atan2(qx, qz) - p);
        the master's centre pixel gives truth_pan(t)."""
        f, (cx, cy) = self.focal_px, self.head.principal
        z = self.motion.z(t)
        u, v = (x - cx) / f, (y - cy) / f
        th, tw = self.target_tex.shape
        if not (abs(u * z) <= self.target_s * tw / 2 and abs(v * z) <= self.target_s * th / 2) or (
                self._on_side(u, v) and self.side_m < z):
            # off the target (or the side square is nearer): the side square, else the background behind
            z = self.side_m if self._on_side(u, v) else self.bg_m
        p = math.atan2(u * z - self.head.baseline_m, z) - math.atan(u)
        for _ in range(6 if self.head.axis_m else 0):  # the slave's centre moves with its pan
            cx_, cz_ = self.head.slave_centre(p)
            p = math.atan2(u * z - cx_, z - cz_) - math.atan(u)
        return p

    def _on_side(self, u: float, v: float) -> bool:
        """Whether the master's ray (u, v) (x/z, y/z) meets the side square."""
        if self._side is None:
            return False
        tm, s, x = self._side
        half = s * tm.shape[1] / 2
        return abs(u * self.side_m - x) <= half and abs(v * self.side_m) <= half

    @property
    def one_px_rad(self) -> float:
        return math.atan(1.0 / self.focal_px)

    def error_px(self, slave_pan_rad: float, t: float = 0.0) -> float:
        """f tan(pan - truth(t)): positive when the slave has turned too far right."""
        return self.focal_px * math.tan(slave_pan_rad - self.truth_pan(t))

    def _homography(self, tex_shape, s: float, z: float, centre: tuple[float, float], pan: float,
                    x: float = 0.0) -> np.ndarray:
        th, tw = tex_shape[:2]
        u0, v0 = (tw - 1) / 2.0, (th - 1) / 2.0
        plane = np.array([[s, 0.0, x - s * u0 - centre[0]], [0.0, s, -s * v0], [0.0, 0.0, z - centre[1]]])
        return self.head.K @ rotation(pan, 0.0).T @ plane

    def _view(self, z: float, centre: tuple[float, float], pan: float, region: Region | None = None) -> np.ndarray:
        lens = self.head.lens
        if lens is not None and (region is None or not region.scale):  # (a preview stays a pinhole's)
            return self._distorted(lens, z, centre, pan, region)
        return self._pinhole(z, centre, pan, region)

    def _distorted(self, lens, z: float, centre: tuple[float, float], pan: float, region: Region | None) -> np.ndarray:
        """A distorted camera's rows (the region's band, or the whole view): the pinhole render of the part of the
        view's plane those pixels see (vergence.io.lens.distort_grid), remapped."""
        from ..io.lens import distort_grid

        y0 = 0 if region is None else region.y0
        y1 = self.size[1] if region is None else region.y0 + region.size[1]
        mx, my = distort_grid(lens, self.size, y0, y1)
        x0, x1 = int(np.floor(mx.min())) - 1, int(np.ceil(mx.max())) + 2
        r0, r1 = int(np.floor(my.min())) - 1, int(np.ceil(my.max())) + 2
        pin = self._pinhole(z, centre, pan, Region.window(x0, r0, x1, r1))
        return cv2.remap(pin, mx - np.float32(x0), my - np.float32(r0), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)

    def _pinhole(self, z: float, centre: tuple[float, float], pan: float, region: Region | None = None) -> np.ndarray:
        size = self.size if region is None else region.size
        key = (centre, pan, None if region is None else region.key)
        if (bg := self._bg.get(key)) is None:  # the background stands still: a camera that holds sees the same
            hb = self._homography(self.bg_tex.shape, self.bg_s, self.bg_m, centre, pan)
            if region is not None:
                hb = region.matrix @ hb
            bg = self._bg.keep(key, cv2.warpPerspective(self.bg_tex, hb, size, flags=cv2.INTER_LINEAR,
                                                        borderMode=cv2.BORDER_REFLECT))
        out = bg.copy()
        planes = [(z, self._tex_mask, self.target_s, 0.0)]
        if self._side is not None:
            planes.append((self.side_m, *self._side))
        for pz, tex_mask, s, x in sorted(planes, key=lambda p: -p[0]):  # far to near
            h = self._homography(tex_mask.shape, s, pz, centre, pan, x)
            if region is not None:
                h = region.matrix @ h
            c0, c1 = _columns(h, tex_mask.shape, size[0])
            if c1 <= c0:
                continue  # the plane is off these columns: nothing to blend
            # texture and mask in one warp, outside = 0: the texture channel comes out premultiplied by the mask;
            # only the columns the plane can reach (elsewhere the blend leaves `out` as it is)
            shift = np.array([[1.0, 0.0, -float(c0)], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
            tm = cv2.warpPerspective(tex_mask, shift @ h, (c1 - c0, size[1]), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0))  # (4 channels)
            a = tm[..., 1].astype(np.float32) * np.float32(1 / 255)
            out[:, c0:c1] = np.rint(out[:, c0:c1] * (1 - a) + tm[..., 0]).astype(np.uint8)
        return out

    def master_view(self, t: float = 0.0, region: Region | None = None) -> np.ndarray:
        """The master's view of the scene at time t, without sensor noise; region: that part of it."""
        if not math.isfinite(t):
            raise ValueError(f"time {t} is not finite")
        return self._view(self.motion.z(t), (0.0, 0.0), 0.0, region)

    def slave_view(self, slave_pan_rad: float, t: float = 0.0, region: Region | None = None) -> np.ndarray:
        """The slave's view at time t, panned to slave_pan_rad, without sensor noise; region: that part of it."""
        if not (math.isfinite(slave_pan_rad) and math.isfinite(t)):
            raise ValueError(f"slave pan {slave_pan_rad} or time {t} is not finite")
        return self._view(self.motion.z(t), self.head.slave_centre(slave_pan_rad), slave_pan_rad, region)

    def noisy(self, img: np.ndarray, camera: int, y0: int = 0) -> np.ndarray:
        """img with this camera's sensor noise; img is the view's rows from y0 on (a band)."""
        return self.noise(img, camera, self.size, y0)

    def render(self, slave_pan_rad: float, t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(master, slave) uint8 gray views at time t with sensor noise, the slave panned to slave_pan_rad."""
        master, slave = self.master_view(t), self.slave_view(slave_pan_rad, t)
        return self.noise(master, 0), self.noise(slave, 1)

    # -- construction from text ---------------------------------------------------------------------------

    KEYS = ("motion", "baseline", "focal", "size", "noise", "seed", "pan", "texture", "target", "bg", "cx", "cy", "k1",
            "k2", "axis", "side")

    @classmethod
    def from_options(cls, **items: str | None) -> "MovingRig":
        """A moving rig from keyword strings (None: default): motion=SPEC, baseline=M (0.06), focal=PX
        (0.8 x width), size=WxH (640x480), noise=SIGMA, seed=N, pan=DEG (the slave's start pan),
        texture=FILE|flat (the target's; default procedural), target=M (its width), bg=M (the background's
        distance), cx=PX, cy=PX (both cameras' principal point; default the view centre), k1=, k2= (both
        cameras' radial distortion, OpenCV's; default 0), axis=M (the slave's pan axis behind its optical centre;
        default 0), side=M (a second square standing at M right of the target; default none). A bad key or value
        raises ValueError naming it."""

        items = {k: v for k, v in items.items() if v is not None}
        unknown = sorted(set(items) - set(cls.KEYS))
        if unknown:
            raise ValueError(f"sim source: {unknown[0]}= does not go with motion=; keys: {', '.join(cls.KEYS)}")

        def num(key, conv=float, default=None):
            return option_number(items, key, conv, default)

        try:
            size = (640, 480)
            if "size" in items:
                try:
                    size = tuple(int(p) for p in items["size"].lower().split("x"))
                    assert len(size) == 2
                except (ValueError, AssertionError):
                    raise ValueError(f"size={items['size']!r} must be WxH") from None
            focal = num("focal", default=0.8 * size[0])
            head = Head(num("baseline", default=0.06), focal, size, num("cx"), num("cy"), num("k1", default=0.0),
                        num("k2", default=0.0), num("axis", default=0.0))
            tex = items.get("texture")
            if tex is not None and tex != "flat":
                tex = read_image(tex)
            return cls(items.get("motion", "still:z=0.8"), head, target_tex=tex, target_m=num("target"),
                       bg_m=num("bg"), noise=num("noise", default=0.0), start_pan_deg=num("pan", default=0.0),
                       seed=num("seed", int, 0), side_m=num("side"))
        except ValueError as e:
            msg = str(e)
            raise ValueError(msg if msg.startswith("sim source") else f"sim source: {msg}") from None

    def pan_off_truth(self, px: float, t: float = 0.0) -> float:
        """truth(t) + atan(px / f): the slave pan px pixels past the converged one."""
        return self.truth_pan(t) + math.atan(px / self.focal_px)


def _with_mask(tex: np.ndarray) -> np.ndarray:
    """A texture and its mask (255) in one 4-channel image, the last two unused: OpenCV warps 1, 3 and 4 channels
    with vectorised code exact to rounding, 2 with plain code on a 1/32 px grid (OpenCV 5.1; the target's band 190 us
    against 35-60)."""
    zero = np.zeros(tex.shape, np.uint8)
    return np.ascontiguousarray(np.dstack([tex, np.full(tex.shape, 255, np.uint8), zero, zero]))


def _columns(h: np.ndarray, tex_shape, width: int) -> tuple[int, int]:
    """The output columns c0..c1-1 (of `width`) where the plane of a texture of tex_shape, seen through the homography
    h (texel -> pixel), can leave anything: its texels and their one-texel border (INTER_LINEAR mixes a border
    texel with the outside), two pixels more each side. The whole width where the plane reaches behind the camera."""
    th, tw = tex_shape[:2]
    corners = np.array([[-1.0, -1.0, tw, tw], [-1.0, th, -1.0, th], [1.0, 1.0, 1.0, 1.0]])
    p = h @ corners
    if not np.all(p[2] > 0):
        return 0, width
    xs = p[0] / p[2]
    return max(0, int(math.floor(xs.min())) - 2), min(width, int(math.ceil(xs.max())) + 3)
