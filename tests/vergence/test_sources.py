"""vergence.sources: the exposure times each source gives with its images (#25)."""

import cv2
import numpy as np
import pytest

from vergence.sources import SourceError, open_source


def _video(path, n=6, fps=25):
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (64, 48))
    for i in range(n):
        w.write(np.full((48, 64, 3), 20 * i, np.uint8))
    w.release()


def test_a_video_gives_its_frame_times_anchored_at_the_first_read(tmp_path):
    for side in ("l", "r"):
        _video(tmp_path / f"{side}.avi")
    src = open_source(f"video:{tmp_path / 'l.avi'},{tmp_path / 'r.avi'}")
    stamps = []
    for _ in range(6):
        src.read()
        stamps.append(src.exposure_ns)
    masters = [s[0] for s in stamps]
    assert [b - a for a, b in zip(masters, masters[1:])] == [40_000_000] * 5  # 25 fps: the video's own times
    assert all(m == s for m, s in stamps)
    src.read()  # the end: rewound, anchored again at this read
    assert src.exposure_ns[0] > masters[-1] - 40_000_000 * 5


def test_the_sim_source_stamps_its_exposures_as_its_timing_says():
    src = open_source("sim:latency=0.05:skew=0.004:size=160x120")
    src.read(0.0)
    tm, ts = src.exposure_ns
    assert ts - tm == 4_000_000
    assert open_source("sim:latency=0.05:stamps=no:size=160x120").read(0.0) is not None
    src = open_source("sim:latency=0.05:stamps=no:size=160x120")
    src.read(0.0)
    assert src.exposure_ns is None


def test_the_sim_source_renders_the_slave_at_the_pan_of_its_exposure():
    asked = []
    src = open_source("sim:latency=0.03:exposure=0.004:size=160x120")

    def pan_at(t_ns):
        asked.append(t_ns)
        return -0.05

    src.read(pan_at)
    tm, ts = src.exposure_ns
    assert len(asked) == 2 and all(abs(t - ts) <= 1_000_001 for t in asked)  # two sub-views, +-1 ms


@pytest.mark.parametrize("spec,says", [("sim:latency=x", "latency='x' is not a number"),
                                       ("sim:latency=2", "latency_s=2.0"), ("sim:stamps=maybe", "stamps='maybe'"),
                                       ("sim:skew=-0.9", "skew_s=-0.9")])
def test_a_bad_timing_key_is_refused_naming_it(spec, says):
    with pytest.raises(SourceError, match=says):
        open_source(spec)
