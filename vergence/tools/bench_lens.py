"""What removing the lens distortion costs a frame (issue #36): vergence.io.lens.Undistorter.rows on the band a
frame reads of the master and of the slave (two calls), against the whole image's remap (what undistorting every
image would cost) and the band's plain slice copy (the least a frame's rows cost), interleaved in the same run so
the ratios hold on a shared machine; and the one-off costs (the maps per camera_info, the simulator's distort_grid
of a band). `python -m vergence.tools.bench_lens` prints the table."""

from __future__ import annotations

import time

import cv2
import numpy as np

from ..io.lens import Lens, Undistorter, band_rows, distort_grid
from ..network.params import Params

__all__ = ["SIZES", "barrel", "bench_lens", "main"]

SIZES = ((640, 480), (1280, 720))


def barrel(size: tuple[int, int]) -> Lens:
    """The tests' barrel (k1 -0.25, k2 0.05, f 500 px at 640 wide, the principal point 15 px right of and 12 px
    above the centre), its focal length in proportion with the width (the same field of view)."""
    w, h = size
    return Lens(500.0 * w / 640, w / 2 + 15, h / 2 - 12, k1=-0.25, k2=0.05)


def _images(size, seed: int = 0):
    rng = np.random.default_rng(seed)
    return [cv2.GaussianBlur(rng.integers(0, 256, (size[1], size[0]), dtype=np.uint8), (0, 0), 1.5)
            for _ in range(2)]


def _time(fns: dict, repeats: int, min_time: float) -> dict:
    """Median seconds per call of each fn, interleaved (A B C A B C ...), each turn at least min_time long."""
    times: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            n, t0 = 0, time.perf_counter()
            while True:
                fn()
                n += 1
                el = time.perf_counter() - t0
                if el >= min_time:
                    break
            times[name].append(el / n)
    return {k: float(np.median(v)) for k, v in times.items()}


def _once(fn, repeats: int = 3) -> float:
    t = []
    for i in range(repeats):
        t0 = time.perf_counter()
        fn(i)
        t.append(time.perf_counter() - t0)
    return float(np.median(t))


def bench_lens(sizes=SIZES, params: Params | None = None, repeats: int = 31, min_time: float = 0.005,
               progress=None) -> list[dict]:
    """One row per image size and band (the band make_frame reads at params' window, and at its max_window: the
    dynamic window's largest), the fovea at the centre row: the per-frame cost in us of the band's rows() for
    master and slave (float32 maps; rows_fixed_us with the CV_16SC2 ones), of the whole images' remap and of the
    band's slice copy, their ratios; the maps' build (ms, once per camera_info) and a band's distort_grid (ms, the
    first time only: cached). OpenCV runs with its default threads (opencv_threads)."""
    p = params or Params()
    rows = []
    for size in sizes:
        w, h = size
        lens = barrel(size)
        master, slave = _images(size)
        build_ms = _once(lambda i: Undistorter(lens, size)) * 1e3
        u, uf = Undistorter(lens, size), Undistorter(lens, size, fixed=True)
        for window in sorted({p.window, max(p.windows())}):
            y0, y1 = band_rows(h // 2, window, p.vsearch, h)
            fns = {"rows": lambda: (u.rows(master, y0, y1), u.rows(slave, y0, y1)),
                   "rows_fixed": lambda: (uf.rows(master, y0, y1), uf.rows(slave, y0, y1)),
                   "full": lambda: (u.rows(master, 0, h), u.rows(slave, 0, h)),
                   "copy": lambda: (master[y0:y1].copy(), slave[y0:y1].copy())}
            for fn in fns.values():
                fn()
            t = _time(fns, repeats, min_time)
            # a new lens each time (distort_grid caches per lens): k2 nudged by 1e-9
            grid_ms = _once(lambda i: distort_grid(Lens(lens.focal_px, lens.cx, lens.cy, k1=lens.k1,
                                                        k2=lens.k2 + 1e-9 * (i + 1 + 10 * window)), size, y0, y1)) * 1e3
            row = {"width": w, "height": h, "window": window, "vsearch": p.vsearch, "band_rows": y1 - y0,
                   "y0": y0, "y1": y1, "source_rows": list(u.source_rows(y0, y1)),
                   **{f"{k}_us": v * 1e6 for k, v in t.items()},
                   "full_vs_rows": t["full"] / t["rows"], "rows_vs_copy": t["rows"] / t["copy"],
                   "fixed_vs_float": t["rows_fixed"] / t["rows"], "build_ms": build_ms, "grid_band_ms": grid_ms,
                   "opencv_threads": cv2.getNumThreads()}
            rows.append(row)
            if progress:
                progress(row)
    return rows


def main() -> None:
    print("per frame, master + slave (two calls each), medians; k1 -0.25, k2 0.05, f 500 px per 640 wide")
    print(f"{'image':>10s} {'w':>3s} {'band':>4s} {'source':>9s} {'rows us':>8s} {'fixed us':>8s} {'full us':>8s} "
          f"{'copy us':>8s} {'full/rows':>9s} {'rows/copy':>9s} {'maps ms':>7s} {'grid ms':>7s}")

    def show(r):
        print(f"{r['width']:>5d}x{r['height']:<4d} {r['window']:3d} {r['band_rows']:4d} {r['source_rows'][0]:4d}.."
              f"{r['source_rows'][1] - 1:<3d} {r['rows_us']:8.1f} {r['rows_fixed_us']:8.1f} {r['full_us']:8.1f} "
              f"{r['copy_us']:8.1f} {r['full_vs_rows']:9.1f} {r['rows_vs_copy']:9.1f} {r['build_ms']:7.1f} "
              f"{r['grid_band_ms']:7.1f}", flush=True)

    bench_lens(progress=show)
    print(f"OpenCV {cv2.__version__}, {cv2.getNumThreads()} threads")


if __name__ == "__main__":
    main()
