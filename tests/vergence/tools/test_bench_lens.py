"""vergence.tools.bench_lens: its rows, small (one size, one repetition), are the bands a frame reads, with every
figure and ratio present (the timings themselves are not asserted: a shared machine's)."""

from __future__ import annotations

from vergence.io.lens import Undistorter
from vergence.network.params import Params
from vergence.tools.bench_lens import barrel, bench_lens


def test_bench_lens_rows():
    seen = []
    rows = bench_lens(sizes=((320, 240),), repeats=1, min_time=0.0, progress=seen.append)
    assert rows == seen and [r["window"] for r in rows] == [15, 47]
    p = Params()
    for r in rows:
        assert (r["width"], r["height"], r["vsearch"]) == (320, 240, p.vsearch)
        assert r["band_rows"] == r["window"] + 2 * p.vsearch + 2 == r["y1"] - r["y0"]
        assert r["source_rows"] == list(Undistorter(barrel((320, 240)), (320, 240)).source_rows(r["y0"], r["y1"]))
        for k in ("rows_us", "rows_fixed_us", "full_us", "copy_us", "full_vs_rows", "rows_vs_copy", "fixed_vs_float",
                  "build_ms", "grid_band_ms"):
            assert r[k] > 0, k
    assert barrel((1280, 720)).focal_px == 1000 and barrel((640, 480)).cy == 228
