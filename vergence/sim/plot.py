"""PNGs of closed-loop runs, drawn with OpenCV: the pan trajectory and the layer-4 profiles of the first
and the last frame (the paper's figure 5); for a moving target, truth and pan over time and the error."""

from __future__ import annotations

import math

import cv2
import numpy as np

from ..decide import centre_offset
from .loop import Step

__all__ = ["plot_run", "plot_tracking", "draw_axes_plot"]

WHITE, BLACK, GREY = (255, 255, 255), (0, 0, 0), (170, 170, 170)
BLUE, RED, GREEN, ORANGE = (200, 80, 20), (40, 40, 220), (40, 150, 40), (0, 140, 255)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def _ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    span = hi - lo
    if span <= 0:
        return [lo]
    raw = span / n
    mag = 10 ** math.floor(math.log10(raw))
    step = min((m * mag for m in (1, 2, 5, 10) if m * mag >= raw), default=10 * mag)
    first = math.ceil(lo / step) * step
    return [first + i * step for i in range(int((hi - first) / step) + 1)]


def draw_axes_plot(img: np.ndarray, box: tuple[int, int, int, int], series: list[tuple[np.ndarray, np.ndarray, tuple,
                   str]], title: str, xlabel: str, ylabel: str, hlines: list[tuple[float, tuple]] = (),
                   vlines: list[tuple[float, tuple, str]] = ()) -> None:
    """Line plots of (x, y, colour, legend) in box = (x0, y0, x1, y1) of img, with ticks and labels."""
    x0, y0, x1, y1 = box
    left, bottom, top, right = x0 + 70, y1 - 45, y0 + 30, x1 - 15
    xs = np.concatenate([s[0] for s in series])
    ys = np.concatenate([s[1] for s in series] + [np.array([h for h, _ in hlines])])
    ys = ys[np.isfinite(ys)]
    xlo, xhi = float(xs.min()), float(xs.max())
    ylo, yhi = (float(ys.min()), float(ys.max())) if ys.size else (0.0, 1.0)
    if xhi == xlo:
        xhi = xlo + 1
    pad = (yhi - ylo) * 0.08 or 1.0
    ylo, yhi = ylo - pad, yhi + pad

    def px(x, y):
        return (int(round(left + (x - xlo) / (xhi - xlo) * (right - left))),
                int(round(bottom - (y - ylo) / (yhi - ylo) * (bottom - top))))

    cv2.rectangle(img, (left, top), (right, bottom), BLACK, 1)
    for t in _ticks(xlo, xhi):
        p = px(t, ylo)
        cv2.line(img, (p[0], bottom), (p[0], bottom + 5), BLACK, 1)
        cv2.putText(img, f"{t:g}", (p[0] - 12, bottom + 20), FONT, 0.4, BLACK, 1, cv2.LINE_AA)
    for t in _ticks(ylo, yhi):
        p = px(xlo, t)
        cv2.line(img, (left - 5, p[1]), (left, p[1]), BLACK, 1)
        cv2.putText(img, f"{t:.4g}", (x0 + 2, p[1] + 4), FONT, 0.4, BLACK, 1, cv2.LINE_AA)
    for h, colour in hlines:
        cv2.line(img, px(xlo, h), px(xhi, h), colour, 1, cv2.LINE_AA)
    for i, (v, colour, label) in enumerate(vlines):
        a, b = px(v, ylo), px(v, yhi)
        cv2.line(img, a, b, colour, 1, cv2.LINE_AA)
        cv2.putText(img, label, (b[0] + 3, b[1] + 12 + 14 * i), FONT, 0.4, colour, 1, cv2.LINE_AA)
    for i, (x, y, colour, legend) in enumerate(series):
        pts = np.array([px(a, b) for a, b in zip(x, y) if math.isfinite(b)], np.int32)
        if len(pts) > 1:
            cv2.polylines(img, [pts], False, colour, 2 if len(pts) < 60 else 1, cv2.LINE_AA)
        for p in pts if len(pts) < 60 else []:
            cv2.circle(img, tuple(int(c) for c in p), 3, colour, -1, cv2.LINE_AA)
        cv2.putText(img, legend, (right - 230, top + 18 + 16 * i), FONT, 0.45, colour, 1, cv2.LINE_AA)
    cv2.putText(img, title, (left, y0 + 20), FONT, 0.55, BLACK, 1, cv2.LINE_AA)
    cv2.putText(img, xlabel, ((left + right) // 2 - 40, y1 - 8), FONT, 0.45, BLACK, 1, cv2.LINE_AA)
    cv2.putText(img, ylabel, (x0 + 2, top - 8), FONT, 0.45, BLACK, 1, cv2.LINE_AA)


def plot_run(steps: list[Step], path: str, one_px_deg: float, width: int = 900,
             height: int = 760) -> np.ndarray:
    """Write the PNG (and return the image): pan trajectory on top, first and last profile below."""
    img = np.full((height, width, 3), 255, np.uint8)
    frames = np.array([s.frame for s in steps], float)
    pans = np.array([s.pan_deg for s in steps])
    truth = steps[0].truth_pan_deg
    hl = [] if not math.isfinite(truth) else [(truth, GREEN), (truth + one_px_deg, GREY),
                                              (truth - one_px_deg, GREY)]
    draw_axes_plot(img, (0, 0, width, height // 2), [(frames, pans, BLUE, "slave pan")],
                   "Slave pan (green: converged pan, grey: +-1 px)", "frame", "pan (deg)", hlines=hl)
    first, last = steps[0], steps[-1]
    k = np.arange(first.scores.size, dtype=float)
    series = [(k, first.scores, ORANGE, f"frame {first.frame}: k*={first.k}"),
              (np.arange(last.scores.size, dtype=float), last.scores, BLUE,
               f"frame {last.frame}: k*={last.k}")]
    kc = centre_offset(first.scores.size + first.window - 1, first.window)
    draw_axes_plot(img, (0, height // 2, width, height), series, "Layer 4: y(k), first and last frame",
                   "k (offset of the slave window)", "y(k)",
                   vlines=[(first.k, ORANGE, "k* first"), (last.k, BLUE, "k* last"), (kc, RED, "k_c")])
    if not cv2.imwrite(path, img):
        raise OSError(f"cannot write {path}")
    return img


def plot_tracking(steps: list[Step], path: str, title: str = "", first: int = 0, width: int = 900,
                  height: int = 700) -> np.ndarray:
    """Write the PNG (and return the image) of a tracking run: the converged pan (truth) and the slave's
    pan over time on top, the error in pixels below from frame `first` on (grey: +-1 px)."""
    from .loop import tracking_error

    img = np.full((height, width, 3), 255, np.uint8)
    t = np.array([s.t_s for s in steps])
    pans = np.array([s.pan_deg for s in steps])
    truth = np.array([s.truth_pan_deg for s in steps])
    err = np.array([s.error_px for s in steps])
    draw_axes_plot(img, (0, 0, width, height // 2), [(t, truth, GREEN, "truth (converged pan)"),
                                                      (t, pans, BLUE, "slave pan")],
                   f"Slave pan and truth: {title}", "time (s)", "pan (deg)")
    e = tracking_error(steps, first)
    t0 = steps[first].t_s if first < len(steps) else 0.0
    draw_axes_plot(img, (0, height // 2, width, height), [(t[first:], err[first:], RED, "error (px)")],
                   f"Error f tan(pan - truth): from {t0:g} s, RMS {e['rms_px']:.2f} px, max {e['max_px']:.2f} px",
                   "time (s)", "error (px)", hlines=[(1.0, GREY), (-1.0, GREY), (0.0, BLACK)])
    if not cv2.imwrite(path, img):
        raise OSError(f"cannot write {path}")
    return img
