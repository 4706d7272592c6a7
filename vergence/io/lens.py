"""The camera's own geometry (issue #36): its intrinsics and lens distortion (Lens, from a ROS 2 camera_info or
vergence's pinhole), the distortion removed from the rows a frame reads (Undistorter: maps built once per
camera_info, only the band's rows remapped per frame), and the same model the other way for the simulator
(distort_grid: the maps that turn a pinhole render into a distorted camera's rows; distort_point, undistort_point
for single pixels).

The model is OpenCV's (that of ROS's camera_calibration): with x = (u - cx) / fx, y = (v - cy) / fy, r2 = x^2 + y^2,
x' = x (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3) + 2 p1 x y + p2 (r2 + 2 x^2), y' alike
(p1 (r2 + 2 y^2) + 2 p2 x y), u' = fx x' + cx: a pinhole pixel (u, v) is seen at the distorted pixel (u', v').
"plumb_bob" is k1, k2, p1, p2, k3; "rational_polynomial" adds k4, k5, k6; "none" has no distortion. The undistorted
image keeps the camera's own K (newCameraMatrix = K): a pinhole camera with the same fx, fy, cx, cy, so the
network, the focal length and the fixation point mean what they meant. Pixel (0, 0)'s centre is (0, 0), as in
OpenCV and ROS."""

from __future__ import annotations

import functools
import math
import threading
from dataclasses import dataclass, fields

import cv2
import numpy as np

__all__ = ["MODELS", "COEFFICIENTS", "UNDISTORT_CRITERIA", "Lens", "Undistorter", "distort_grid", "distort_point",
           "undistort_point", "band_rows", "principal_points", "undistorters"]

MODELS = ("none", "plumb_bob", "rational_polynomial")
COEFFICIENTS = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")  # OpenCV's order, ROS's D
_COUNT = {"none": 0, "plumb_bob": 5, "rational_polynomial": 8}
_FISHEYE = ("equidistant", "fisheye", "kannala_brandt")

# cv2.undistortPoints runs a fixed 5 fixed-point iterations by default, which leaves 0.52 px at the corners of a
# 640 x 480 image for k1 = -0.25, k2 = 0.05 (f 500; 2.9 px for the rational case of the tests). With this criterion
# it iterates until the point, distorted again, lands within 1e-6 px of the pixel (15-20 iterations there, 40 for
# the rational case; 100 is the bound), at about 4-6 times the default's cost.
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-6)


def _finite(value, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: {value!r} is not a number") from None
    if not math.isfinite(v):
        raise ValueError(f"{name}: {v} is not finite")
    return v


def _size(size) -> tuple[int, int]:
    try:
        w, h = (int(s) for s in size)
    except (TypeError, ValueError):
        raise ValueError(f"size: {size!r} is not (width, height)") from None
    if w < 1 or h < 1:
        raise ValueError(f"size: {w} x {h} is not a positive (width, height)")
    return w, h


@dataclass(frozen=True)
class Lens:
    """A camera's intrinsics and lens distortion. focal_px is fx (px), fy defaults to fx; (cx, cy) the principal
    point (px); k1..k6, p1, p2 OpenCV's coefficients; model one of MODELS (None: the smallest that holds the
    coefficients). ValueError naming the field for a non-finite value, a focal length <= 0, or coefficients the
    model does not have (k4..k6 with plumb_bob, any with none)."""

    focal_px: float
    cx: float
    cy: float
    fy: float | None = None
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    k5: float = 0.0
    k6: float = 0.0
    model: str | None = None

    def __post_init__(self):
        for f in fields(self):
            if f.name != "model" and not (f.name == "fy" and self.fy is None):
                object.__setattr__(self, f.name, _finite(getattr(self, f.name), f.name))
        if self.fy is None:
            object.__setattr__(self, "fy", self.focal_px)
        for name in ("focal_px", "fy"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name}: {getattr(self, name)} px is not a focal length (> 0)")
        coeffs = self.coefficients
        if self.model is None:
            model = "none" if not any(coeffs) else "plumb_bob" if not any(coeffs[5:]) else "rational_polynomial"
            object.__setattr__(self, "model", model)
        if self.model not in MODELS:
            raise ValueError(f"model: {self.model!r} is not one of {', '.join(MODELS)}")
        n = _COUNT[self.model]
        extra = [name for name, v in zip(COEFFICIENTS[n:], coeffs[n:]) if v]
        if extra:
            raise ValueError(f"{', '.join(extra)}: model {self.model!r} has no such coefficient")

    @classmethod
    def pinhole(cls, f: float, size: tuple[int, int]) -> "Lens":
        """vergence's camera until now: focal length f, principal point at the view centre (W // 2, H // 2)."""
        w, h = _size(size)
        return cls(f, float(w // 2), float(h // 2), model="none")

    @classmethod
    def from_camera_info(cls, k, d, model: str, size: tuple[int, int]) -> "Lens":
        """The lens of a ROS 2 sensor_msgs/CameraInfo: k its K (9 numbers, row-major), d its D, model its
        distortion_model, size its (width, height). An empty D, or all zeros, is no distortion (model "none"); so
        is an empty distortion_model with no D. ValueError naming the field (k[i], d[i], distortion_model) for a
        non-finite value, fx or fy <= 0 (an all-zero K: an uncalibrated camera), a skew or a K whose last row is
        not (0, 0, 1), a principal point outside the image, more coefficients than the model has, and a model
        other than plumb_bob and rational_polynomial (equidistant, the fisheye model, is refused: OpenCV's
        cv2.fisheye would need maps and points of its own). The binning and the ROI of camera_info are not read:
        K must be that of the images received."""
        w, h = _size(size)
        k = list(k)
        if len(k) != 9:
            raise ValueError(f"camera_info k: {len(k)} numbers, K is 9 (row-major 3 x 3)")
        names = ["k[0] (fx)", "k[1] (skew)", "k[2] (cx)", "k[3]", "k[4] (fy)", "k[5] (cy)", "k[6]", "k[7]", "k[8]"]
        kv = [_finite(v, f"camera_info {n}") for v, n in zip(k, names)]
        for i in (0, 4):
            if kv[i] <= 0:
                raise ValueError(f"camera_info {names[i]}: {kv[i]} px is not a focal length (> 0; an all-zero K is "
                                 "an uncalibrated camera)")
        for i, want in ((1, 0.0), (3, 0.0), (6, 0.0), (7, 0.0), (8, 1.0)):
            if kv[i] != want:
                raise ValueError(f"camera_info {names[i]}: {kv[i]}, expected {want:g} (K = [fx 0 cx; 0 fy cy; 0 0 1]"
                                 f"{'; a skewed pixel is not modelled' if i == 1 else ''})")
        for i, n in ((2, w), (5, h)):
            if not 0 <= kv[i] < n:
                raise ValueError(f"camera_info {names[i]}: {kv[i]} px, the principal point is outside the "
                                 f"{w} x {h} image")
        dv = [_finite(v, f"camera_info d[{i}] ({COEFFICIENTS[i] if i < 8 else 'beyond k6'})")
              for i, v in enumerate(d)]
        m = (model or "").strip().lower()
        if m in _FISHEYE:
            raise ValueError(f"camera_info distortion_model: {model!r} (the fisheye model) is not supported: only "
                             "plumb_bob and rational_polynomial (or none)")
        if m not in ("", *MODELS):
            raise ValueError(f"camera_info distortion_model: {model!r} is not one of plumb_bob, "
                             "rational_polynomial (or none, or empty with no d)")
        n = _COUNT.get(m, 0)
        beyond = [i for i, v in enumerate(dv) if v and i >= n]
        if beyond:
            i = beyond[0]
            what = COEFFICIENTS[i] if i < 8 else "a thin-prism or tilt coefficient, not modelled"
            raise ValueError(f"camera_info d[{i}] ({what}): {dv[i]}, but distortion_model {model!r} has "
                             f"{n} coefficients")
        coeffs = dict(zip(COEFFICIENTS, dv[:n]))
        return cls(kv[0], kv[2], kv[5], fy=kv[4], model=m if any(dv) else "none", **coeffs)

    @property
    def coefficients(self) -> tuple[float, ...]:
        """(k1, k2, p1, p2, k3, k4, k5, k6), OpenCV's order."""
        return tuple(getattr(self, n) for n in COEFFICIENTS)

    @property
    def is_pinhole(self) -> bool:
        """No distortion: every coefficient zero."""
        return not any(self.coefficients)

    def matrix(self) -> np.ndarray:
        """K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (float64)."""
        return np.array([[self.focal_px, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def distortion(self) -> np.ndarray:
        """OpenCV's distCoeffs: 5 numbers (plumb_bob and none: zeros), 8 for rational_polynomial."""
        return np.array(self.coefficients[: max(5, _COUNT[self.model])], np.float64)


def band_rows(y: int, window: int, vsearch: int, height: int) -> tuple[int, int]:
    """The rows y0..y1-1 a frame reads of each image around the fovea row y (vergence.stages.frames.make_frame,
    through vergence.network.retina.band_strip): the band y - w//2 - R .. y + w//2 + R with the Sobel kernels'
    one-row margin above and below, window + 2 vsearch + 2 rows, clipped to the image (retina mirrors the margin
    at the image's edge). The fovea's rows, and the master band's (lr_check), lie inside."""
    half = window // 2 + vsearch
    return max(0, y - half - 1), min(height, y + half + 2)


class Undistorter:
    """The distortion removed from rows of a camera's images: cv2.initUndistortRectifyMap's maps (newCameraMatrix
    = K, no rotation), built once for a lens and a (width, height), then `rows` remaps only the rows asked for.

    The maps are float32 (x and y); fixed=True converts them to OpenCV's fixed-point CV_16SC2 + interpolation
    table, which measured no faster for a band (vergence.tools.bench_lens, OpenCV 5.1: from as fast to 1.7 x
    slower across runs) and differs by 1 gray level on a few percent of the pixels (the rounding of the sub-pixel
    weights). The interpolation is bilinear; the border is
    replicated: where an undistorted pixel falls outside the distorted image (a pincushion lens's corners, the
    edges of a strong barrel), it takes the nearest edge pixel, smooth across, where a constant black border would
    draw a strong edge at the same image position in both cameras, one the correlation could lock on (a false
    match at the disparity of the two borders). A pinhole lens has no maps: `rows` is the slice itself."""

    def __init__(self, lens: Lens, size: tuple[int, int], fixed: bool = False):
        self.lens = lens
        self.size = _size(size)
        self.fixed = fixed
        w, h = self.size
        if lens.is_pinhole:
            self.maps = None
            self.lo = np.arange(h)
            self.hi = np.arange(1, h + 1)
            return
        mx, my = cv2.initUndistortRectifyMap(lens.matrix(), lens.distortion(), None, lens.matrix(), self.size,
                                             cv2.CV_32FC1)
        # the distorted rows each output row reads: bilinear reads floor(y) and floor(y) + 1 (OpenCV rounds y to
        # 1/32 px first, so y just below an integer may read the row above it with a zero weight: covered too)
        self.lo = np.clip(np.floor(my.min(axis=1)).astype(np.int64), 0, h - 1)
        self.hi = np.clip(np.floor(my.max(axis=1)).astype(np.int64) + 2, 1, h)
        self.maps = cv2.convertMaps(mx, my, cv2.CV_16SC2) if fixed else (mx, my)

    def _check(self, y0: int, y1: int) -> None:
        if not 0 <= y0 < y1 <= self.size[1]:
            raise ValueError(f"rows {y0}..{y1 - 1}: not inside the {self.size[0]} x {self.size[1]} image")

    def source_rows(self, y0: int, y1: int) -> tuple[int, int]:
        """(a, b): the distorted rows a..b-1 that the undistorted rows y0..y1-1 read (clipped to the image). The
        simulator renders only a band: it renders these rows, and passes them to `rows` with top=a."""
        self._check(y0, y1)
        return int(self.lo[y0:y1].min()), int(self.hi[y0:y1].max())

    def rows(self, image: np.ndarray, y0: int, y1: int, top: int = 0) -> np.ndarray:
        """The undistorted rows y0..y1-1 (full width) of a distorted image (gray or colour): the whole image, or
        with top = a only its rows a.. (at least source_rows(y0, y1)). For a pinhole lens the slice itself (a
        view, no copy)."""
        self._check(y0, y1)
        w, h = self.size
        if image.shape[1] != w or not (0 <= top and top + image.shape[0] <= h):
            raise ValueError(f"image of {image.shape[1]} x {image.shape[0]} from row {top}: not rows of the "
                             f"{w} x {h} image")
        if self.maps is None:
            if not (top <= y0 and y1 <= top + image.shape[0]):
                raise ValueError(f"rows {y0}..{y1 - 1} are not in the image's rows {top}..{top + image.shape[0] - 1}")
            return image[y0 - top : y1 - top]
        if top:
            a, b = self.source_rows(y0, y1)
            if not (top <= a and b <= top + image.shape[0]):
                raise ValueError(f"rows {y0}..{y1 - 1} read the distorted rows {a}..{b - 1}, not all in the image's "
                                 f"rows {top}..{top + image.shape[0] - 1}")
            m1, m2 = self.maps[0][y0:y1], self.maps[1][y0:y1]
            if self.fixed:  # (x, y) pairs of int16
                m1 = m1 - np.array([0, top], np.int16)
            else:
                m2 = m2 - np.float32(top)
            return cv2.remap(image, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return cv2.remap(image, self.maps[0][y0:y1], self.maps[1][y0:y1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)


def _points(x, y) -> tuple[np.ndarray, bool]:
    scalar = np.ndim(x) == 0 and np.ndim(y) == 0
    xs, ys = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
    return np.stack([xs.ravel(), ys.ravel()], axis=-1), scalar


def _undistort(lens: Lens, pts: np.ndarray) -> np.ndarray:
    """Distorted pixels (n, 2) -> pinhole pixels (n, 2), float64, iterated to UNDISTORT_CRITERIA (OpenCV 4's
    undistortPointsIter, OpenCV 5's undistortPoints with criteria)."""
    if lens.is_pinhole or not len(pts):
        return pts.astype(np.float64, copy=True)
    k = lens.matrix()
    src = np.ascontiguousarray(pts, np.float64).reshape(-1, 1, 2)
    if hasattr(cv2, "undistortPointsIter"):
        out = cv2.undistortPointsIter(src, k, lens.distortion(), None, k, UNDISTORT_CRITERIA)
    else:
        out = cv2.undistortPoints(src, k, lens.distortion(), R=None, P=k, criteria=UNDISTORT_CRITERIA)
    return out.reshape(-1, 2)


def undistort_point(lens: Lens, x, y):
    """The pinhole pixel that the distorted pixel (x, y) sees (numbers or arrays alike: floats or arrays back),
    through cv2.undistortPoints iterated to UNDISTORT_CRITERIA (distorted again, within 1e-6 px)."""
    pts, scalar = _points(x, y)
    out = _undistort(lens, pts)
    if scalar:
        return float(out[0, 0]), float(out[0, 1])
    shape = np.broadcast_shapes(np.shape(x), np.shape(y))
    return out[:, 0].reshape(shape), out[:, 1].reshape(shape)


def distort_point(lens: Lens, x, y):
    """Where the distorted camera sees the pinhole pixel (x, y): the model in closed form (numbers or arrays)."""
    xn = (np.asarray(x, np.float64) - lens.cx) / lens.focal_px
    yn = (np.asarray(y, np.float64) - lens.cy) / lens.fy
    k1, k2, p1, p2, k3, k4, k5, k6 = lens.coefficients
    r2 = xn * xn + yn * yn
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
    u, v = lens.focal_px * xd + lens.cx, lens.fy * yd + lens.cy
    if np.ndim(u) == 0:
        return float(u), float(v)
    return u, v


class _Grid:
    """distort_grid's maps of one lens and size, filled a row span at a time as bands ask for them (each row
    undistorted once, ever); the rows handed out are never written again."""

    def __init__(self, lens: Lens, size: tuple[int, int]):
        self.lens, self.size = lens, size
        w, h = size
        self.mx = np.empty((h, w), np.float32)
        self.my = np.empty((h, w), np.float32)
        self.done = np.zeros(h, bool)
        self.lock = threading.Lock()

    def band(self, y0: int, y1: int) -> tuple[np.ndarray, np.ndarray]:
        with self.lock:
            todo = np.flatnonzero(~self.done[y0:y1])
            if len(todo):
                a, b = y0 + int(todo[0]), y0 + int(todo[-1]) + 1
                ys, xs = np.mgrid[a:b, 0 : self.size[0]].astype(np.float64)
                out = _undistort(self.lens, np.stack([xs.ravel(), ys.ravel()], axis=-1))
                self.mx[a:b] = out[:, 0].reshape(b - a, -1)
                self.my[a:b] = out[:, 1].reshape(b - a, -1)
                self.done[a:b] = True
        mx, my = self.mx[y0:y1], self.my[y0:y1]
        mx.flags.writeable = my.flags.writeable = False
        return mx, my


@functools.lru_cache(maxsize=8)
def _grid(lens: Lens, size: tuple[int, int]) -> _Grid:
    return _Grid(lens, size)


def distort_grid(lens: Lens, size: tuple[int, int], y0: int, y1: int) -> tuple[np.ndarray, np.ndarray]:
    """For the simulator: float32 maps (mapx, mapy), (y1 - y0) x width, such that cv2.remap(pinhole, mapx, mapy,
    cv2.INTER_LINEAR) is the distorted camera's rows y0..y1-1, pinhole being the pinhole render (same K) of the
    whole view: for each distorted pixel, the pinhole pixel it sees (undistort_point's, iterated to
    UNDISTORT_CRITERIA). Coordinates may fall outside the pinhole view (a barrel lens's corners see past its
    edges): a render of rows a..b-1 and columns c..d-1 takes maps minus (c, a), its span from the maps' min and
    max. Cached (read-only arrays): each row of a lens and size is computed once, when a band first asks for it
    (about 5-10 ms per 640 x 29 band, 0.1-0.2 s for a whole 640 x 480 view, on one core)."""
    w, h = _size(size)
    if not 0 <= y0 < y1 <= h:
        raise ValueError(f"rows {y0}..{y1 - 1}: not inside the {w} x {h} image")
    return _grid(lens, (w, h)).band(y0, y1)


# -- the capture's cameras ---------------------------------------------------------------------------------------

def principal_points(cam, source_says, size: tuple[int, int]) -> tuple:
    """For the capture (cam: the settings' [camera], vergence.config.CameraSettings): (master's, slave's) principal
    point (cx, cy) for the frames: [camera] cx, cy, slave_cx, slave_cy where set, else the source's (a
    camera_info's, the simulator's), else -1 (the image centre). ValueError naming the setting that lies outside
    the image."""
    said = source_says or ((-1.0, -1.0), (-1.0, -1.0))
    out = []
    for i, (kx, ky) in enumerate((("cx", "cy"), ("slave_cx", "slave_cy"))):
        pt = []
        for j, (key, most) in enumerate(((kx, size[0]), (ky, size[1]))):
            v = getattr(cam, key)
            if v >= 0 and v > most:
                raise ValueError(f"[camera] {key} = {v:g}: outside the {size[0]} x {size[1]} image (0..{most})")
            pt.append(float(v if v >= 0 else said[i][j]))
        out.append(tuple(pt))
    return tuple(out)


def undistorters(cam, source_lenses, focal: float, principal: tuple, size: tuple[int, int]) -> tuple:
    """For the capture: (master's, slave's) Undistorter, or None for a pinhole camera: [camera] k1.. where set (at
    the frames' focal length and each camera's principal point), else the source's lenses (a camera_info's, the
    simulator's). ValueError naming what is wrong."""
    if cam.distortion:
        lenses = tuple(Lens(focal, pt[0] if pt[0] >= 0 else size[0] // 2, pt[1] if pt[1] >= 0 else size[1] // 2,
                            **cam.distortion) for pt in principal)
    else:
        lenses = source_lenses or (None, None)
    return tuple(Undistorter(ln, size) if ln is not None and not ln.is_pinhole else None for ln in lenses)
