"""vergence.io.sources: each kind of source opens, reads and refuses as it says; the exposure times each gives with
its images (#25)."""

import math

import cv2
import numpy as np
import pytest

from vergence.head.control import ControlSettings
from vergence.stages.gather import Gatherer
from vergence.network.params import Params
from vergence.io.sources import FilesSource, SimSource, SourceError, open_source

from samples import textured

MS = 1_000_000


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


@pytest.mark.realtime  # times a thread or a wake-up: kept in the main process of a split run
def test_the_sim_source_renders_ahead_as_far_as_the_pan_is_known_and_reads_out_at_the_exposure():
    """Render ahead (issue #33): where the pan is known ahead (the capture's ahead_ns), the pair is exposed the
    median of the last renders later than its render starts, the slave rendered at its pan then, and read no
    earlier than that exposure (a camera's read-out is the camera's, not the host's: latency=0 is 0); where it is
    not known ahead, exposed when its render starts, as a plain pan does."""
    import time

    src = open_source("sim:motion=sine:z=0.8,amp=0.3,hz=0.2")
    src.rows = (200, 280)
    asked = []

    class Lookup:
        def __init__(self, ahead):
            self.ahead = ahead

        def ahead_ns(self):
            return self.ahead

        def __call__(self, t_ns):
            asked.append(t_ns)
            return 0.01

    for ahead in (10**9, 0, 10**9):
        leads, outs = [], []
        for _ in range(8):
            before = time.time_ns()
            expected = sorted(src.render_ns)[len(src.render_ns) // 2] if src.render_ns else 0
            src.read(Lookup(ahead))
            after = time.time_ns()
            t_master, t_slave = src.exposure_ns
            leads.append((t_master - before, min(expected, ahead)))
            outs.append(after - t_master)
            assert asked[-1] == t_slave == t_master  # the slave rendered at its pan at the exposure
        assert all(lead <= lead_ns + 5 * MS and lead >= lead_ns for lead, lead_ns in leads)
        assert all(out >= 0 for out in outs)  # never read before its exposure
        if ahead:
            assert min(lead for lead, _ in leads[1:]) > 20_000  # the moving target's band: some 0.1-0.5 ms


def test_the_sim_sources_truth_is_for_the_fovea_the_capture_sets():
    from vergence.sim.fixation import truth_at, truth_pan_at

    still = open_source("sim")
    still.read(still.start_pan_rad)
    centre = still.truth_pan_rad
    assert centre == still.rig.truth_pan_rad
    still.fovea = (440, 240)  # where `vergence fixate` moved it
    still.read(centre)
    assert still.truth_pan_rad == truth_at(still.rig, 440, 240)[0] and abs(still.truth_pan_rad - centre) > 0.01
    still.fovea = (320, 240)
    still.read(centre)
    assert still.truth_pan_rad == centre
    # the moving target: the truth at the master's exposure, for the fovea (here off the target: the background)
    moving = open_source("sim:motion=sine:z=0.8,amp=0.3,hz=0.2")
    moving.fovea = (610, 240)
    moving.read(0.0)
    t = (moving.exposure_ns[0] - moving.t0) / 1e9
    assert moving.truth_pan_rad == truth_pan_at(moving.rig, 610, 240, t)
    assert abs(moving.truth_pan_rad - moving.rig.truth_pan(t)) > math.radians(3)


@pytest.mark.parametrize("spec,says", [("sim:latency=x", "latency='x' is not a number"),
                                       ("sim:latency=2", r"sim source: latency: must be from 0 to 1 .*got 2\.0"),
                                       ("sim:stamps=maybe", "stamps='maybe'"),
                                       ("sim:skew=-0.9", r"skew: must be from -0.5 to 0.5 .*got -0\.9"),
                                       ("sim:axis=0.03", r"axis= is the physical rig's: give motion= with it \(e\.g\. "
                                                         r"sim:motion=still:z=0\.8:axis=0\.03\)"),
                                       ("sim:cx=330", "cx= is the physical rig's"),
                                       ("sim:motion=still:z=0.8:axis=0.7", "axis=0.7: the pan axis within 0.5 m")])
def test_a_bad_timing_key_is_refused_naming_it(spec, says):
    with pytest.raises(SourceError, match=says):
        open_source(spec)




def clipping_pair():
    """A textured pair whose slave is at gain 1.6, +40: a quarter of its band saturates (clip_master clips)."""
    m, s = textured()
    return m, np.clip(s * 1.6 + 40, 0, 255).astype(np.uint8)


def gather(params=Params(max_window=0), deadline=0.05):
    return Gatherer(params, ControlSettings(), deadline)


def test_files_source(tmp_path):
    m, s = textured()
    cv2.imwrite(str(tmp_path / "l.png"), m)
    cv2.imwrite(str(tmp_path / "r.png"), s)
    src = open_source(f"files:{tmp_path / 'l.png'},{tmp_path / 'r.png'}")
    a, b = src.read(0.3)
    assert isinstance(src, FilesSource) and src.size == (200, 120)
    assert np.array_equal(a, m) and np.array_equal(b, s)
    assert not src.follows_pan and src.start_pan_rad == 0.0  # taken at pan 0, whatever the motor does
    a, b = open_source(f"files:{tmp_path / 'l.png'},{tmp_path / 'r.png'}", master="right").read()
    assert np.array_equal(a, s)


@pytest.mark.parametrize("spec,msg", [
    ("files:/nonexistent/l.png,/nonexistent/r.png", "/nonexistent/l.png"),
    ("files:onlyone", "LEFT,RIGHT"),
    ("video:/nonexistent/a.avi,/nonexistent/b.avi", "no such file"),
    ("camera:97,98", "camera '97'"),
    ("nope:1", "unknown source"),
    ("sim:bogus=1", "bogus"),
], ids=["missing-file", "one-file", "missing-video", "no-camera", "unknown", "bad-sim-key"])
def test_source_errors_name_the_problem(spec, msg):
    with pytest.raises(SourceError, match=msg):
        open_source(spec)


def test_video_source(tmp_path):
    m, s = textured()
    for name, img in (("l.avi", m), ("r.avi", s)):
        vw = cv2.VideoWriter(str(tmp_path / name), cv2.VideoWriter_fourcc(*"MJPG"), 10, (200, 120))
        if not vw.isOpened():
            pytest.skip("no MJPG writer in this OpenCV")
        for _ in range(2):
            vw.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
        vw.release()
    src = open_source(f"video:{tmp_path / 'l.avi'},{tmp_path / 'r.avi'}")
    assert not src.follows_pan and src.start_pan_rad == 0.0
    for _ in range(5):  # rewinds at the end
        a, b = src.read()
        assert a.shape == (120, 200) and a.dtype == np.uint8
        assert np.abs(a.astype(int) - m).mean() < 4
    src.close()


def test_sim_source_renders_at_the_given_pan():
    src = open_source("sim:size=160x120:focal=128")
    assert isinstance(src, SimSource) and src.size == (160, 120) and src.focal_px == 128.0 and src.follows_pan
    a0, b0 = src.read(0.0)
    a1, b1 = src.read(0.05)
    assert a0.shape == (120, 160) and np.array_equal(a0, a1) and not np.array_equal(b0, b1)


def test_every_source_is_a_source_and_says_which_master_it_cannot_take():
    """Source is an abstract base class (issue #34): every source subclasses it, the ROS 2 one too (its master
    check and ordering are the base's); a source without read() cannot be made; the simulator, whose master is
    its left camera, refuses master 'right' instead of ignoring it."""
    import inspect

    from vergence.io import sources
    from vergence.ros2.source import Ros2Source

    kinds = [c for _, c in inspect.getmembers(sources, inspect.isclass) if c.__module__ == sources.__name__
             and c.__name__.endswith("Source") and c is not sources.Source]
    assert {c.__name__ for c in kinds} == {"FilesSource", "VideoSource", "CameraSource", "SimSource"}
    assert all(issubclass(c, sources.Source) for c in kinds + [Ros2Source])
    with pytest.raises(TypeError, match="abstract"):
        sources.Source()
    with pytest.raises(SourceError, match="capture.master must be 'left' or 'right', got 'up'"):
        Ros2Source("/l,/r", master="up")
    with pytest.raises(SourceError, match="the simulator's master is its left camera"):
        open_source("sim", master="right")
