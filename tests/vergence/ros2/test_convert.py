"""vergence.ros2.convert, the ROS 2 conversions without ROS: stamps, the master's view, the fixated point and its
covariance, look_at's projection and refusals, the image's own frame_id, the bridge's [ros2] settings as applied,
diagnostics, image decoding, stamp pairing."""

from __future__ import annotations

import math

import cv2
import msgspec
import numpy as np
import pytest

from vergence.ros2 import convert as conv
from vergence.wire.messages import Frame
from vergence.stages.frames import make_frame
from vergence.network.params import Params
from vergence.sim.optics import rotation


def test_stamps_round_trip_and_refuse_what_is_not_a_time():
    t = 1_764_600_000_123_456_789
    assert conv.stamp(t) == (1_764_600_000, 123_456_789) and conv.from_stamp(*conv.stamp(t)) == t
    assert conv.stamp(0) == (0, 0)
    for bad in (-1, 2**31 * 10**9, 2**64):
        with pytest.raises(ValueError):
            conv.stamp(bad)
    now = t
    assert conv.stamp_problem(*conv.stamp(now - 10**8), now, 2.0) is None
    assert "stamp 0" in conv.stamp_problem(0, 0, now, 2.0)
    assert "out of range" in conv.stamp_problem(5, 10**9, now, 2.0)
    assert "+3 s off" in conv.stamp_problem(*conv.stamp(now + 3 * 10**9), now, 2.0)
    assert conv.ros_name("head") == "head" and conv.ros_name("my-rig.2") == "my_rig_2"
    assert conv.ros_name("2heads") == "_2heads"


def test_view_of_a_real_frame_and_garbage():
    img = np.random.default_rng(0).integers(0, 256, (240, 320), np.uint8)
    f = make_frame(img, img, rig="r", frame=1, pan_rad=0.0, focal_px=400.0, params=Params(), plan=[["w", 0, 306]])
    f.master_pan_rad, f.tilt_rad = 0.1, -0.05
    assert conv.view_of_frame(f.to_bytes(), "fick") == conv.View(320, 240, 400.0, 0.1, -0.05, "fick")
    for bad in (b"\xc1", b"", f.to_bytes()[:20]):
        with pytest.raises(ValueError):
            conv.view_of_frame(bad)


def test_view_takes_the_frames_frame_id_when_plausible():
    """The master image's frame_id in the Frame is a claim: taken when printable ASCII without spaces and at most
    MAX_FRAME_ID long; else the view has none and says why. An old Frame without the field decodes, without one."""
    img = np.random.default_rng(0).integers(0, 256, (240, 320), np.uint8)
    f = make_frame(img, img, rig="r", frame=1, pan_rad=0.0, focal_px=400.0, params=Params(), plan=[["w", 0, 306]])
    assert (conv.view_of_frame(f.to_bytes()).frame_id, conv.view_of_frame(f.to_bytes()).bad_frame_id) == ("", "")
    f.frame_id = "left_optical_frame"
    assert conv.view_of_frame(f.to_bytes()).frame_id == "left_optical_frame"
    assert Frame.from_bytes(f.to_bytes()).frame_id == "left_optical_frame"
    for bad, says in (("x" * (conv.MAX_FRAME_ID + 1), "of 129 characters (at most 128)"),
                      ("left optical", "not printable ASCII without spaces"), ("cam\x1b[2J", "not printable"),
                      ("kamera_ø", "not printable")):
        f.frame_id = bad
        v = conv.view_of_frame(f.to_bytes())
        assert v.frame_id == "" and says in v.bad_frame_id, (bad, v)
    assert conv.frame_id_problem("x" * conv.MAX_FRAME_ID) is None and conv.frame_id_problem("/a/b-c.1") is None
    old = msgspec.msgpack.decode(f.to_bytes())
    del old["frame_id"]
    assert Frame.from_bytes(msgspec.msgpack.encode(old)).frame_id == ""


def test_look_at_mode_and_discovery_env():
    """[ros2] look_at: explicit wins; unset: on without an authenticated session, off under a deployed ACL.
    [ros2] discovery: localhost sets LOCALHOST and drops static peers and the old ROS_LOCALHOST_ONLY; subnet sets
    SUBNET; environment changes nothing."""
    assert conv.look_at_mode(None, None)[0] is True
    on, why = conv.look_at_mode(None, "user 'monitor'")
    assert on is False and "deployed ACL" in why and "[ros2] look_at = true" in why
    assert conv.look_at_mode(True, "user 'ros2'") == (True, "[ros2] look_at = true")
    assert conv.look_at_mode(False, None) == (False, "[ros2] look_at = false")
    env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET", "ROS_STATIC_PEERS": "10.0.0.2", "ROS_LOCALHOST_ONLY": "0"}
    assert conv.discovery_env("localhost", env) == ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
                                                     "ROS_LOCALHOST_ONLY": None, "ROS_STATIC_PEERS": None},
                                                    "localhost (this host only)")
    assert conv.discovery_env("subnet", env) == (
        {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET", "ROS_LOCALHOST_ONLY": None}, "subnet, static peers 10.0.0.2")
    assert conv.discovery_env("environment", env) == ({}, "the environment's: SUBNET, static peers 10.0.0.2")
    assert conv.discovery_env("environment", {}) == ({}, "the environment's: SYSTEM_DEFAULT")


def test_fixation_point_lies_at_the_depth_on_the_fovea_ray():
    v = conv.View(640, 480, 500.0)
    # a fixed master: (x - cx) Z / f, (y - cy) Z / f, Z
    assert conv.fixation_point(420, 190, 1.25, v) == pytest.approx((100 * 1.25 / 500, -50 * 1.25 / 500, 1.25))
    assert conv.fixation_point(320, 240, math.nan, v) is None and conv.fixation_point(320, 240, -1.0, v) is None
    # an aimed master (the simulator's): the point, turned into the head's frame by the camera's rotation
    # (vergence.sim.rig.rotation, independent of vergence.ros2.convert), has the decision's depth along the head's z
    for gimbal in ("helmholtz", "fick"):
        va = conv.View(640, 480, 500.0, 0.2, -0.1, gimbal)
        p = np.array(conv.fixation_point(400, 300, 0.9, va))
        head = rotation(0.2, -0.1, gimbal) @ p
        assert head[2] == pytest.approx(0.9, rel=1e-12)
        u, w = 500 * p[0] / p[2] + 320, 500 * p[1] / p[2] + 240  # and it is on the fovea's pixel
        assert (u, w) == pytest.approx((400, 300), abs=1e-9)


def test_fixation_covariance_along_and_across_the_ray():
    v = conv.View(640, 480, 500.0)
    p = conv.fixation_point(420, 190, 1.25, v)
    c = np.array(conv.fixation_covariance(p, 0.02, v)).reshape(6, 6)
    d = np.array(p) / np.linalg.norm(p)
    assert d @ c[:3, :3] @ d == pytest.approx((0.02 * np.linalg.norm(p) / p[2]) ** 2)
    across = np.cross(d, [0, 1, 0])
    across /= np.linalg.norm(across)
    assert across @ c[:3, :3] @ across == pytest.approx((conv.PIXEL_SIGMA * 1.25 / 500) ** 2)
    assert np.allclose(c[:3, :3], c[:3, :3].T) and np.all(np.diag(c)[3:] == -1) and not c[:3, 3:].any()
    assert np.all(np.diag(np.array(conv.fixation_covariance(p, math.nan, v)).reshape(6, 6)) == -1)


def test_look_at_projects_and_refuses():
    v = conv.View(640, 480, 500.0)
    assert conv.look_at_pixel(conv.fixation_point(420, 190, 1.25, v), v, 15, 6) == (420, 190)
    assert conv.look_at_pixel((0.0, 0.0, 2.0), v, 15, 6) == (320, 240)
    refusals = {(math.nan, 0, 1): "not finite", (0, 0, math.inf): "not finite", (0, 0, -1): "not in front",
                (0, 0, 0): "not in front", (1.0, 0, 0.5): "outside the view", (0, -1.0, 1): "outside the view",
                (0.63, 0, 1): "too close to the left/right border", (0, 0.47, 1): "too close to the top/bottom"}
    for point, why in refusals.items():
        with pytest.raises(conv.Refused, match=why):
            conv.look_at_pixel(point, v, 15, 6)


def test_pan_at_interpolates_between_the_states_around_it():
    states = [(100, 0.1), (120, 0.3), (110, 0.2)]  # as they arrived
    assert conv.pan_at(states, 105, 9.0) == pytest.approx(0.15) and conv.pan_at(states, 115, 9.0) == pytest.approx(0.25)
    assert conv.pan_at(states, 130, 9.0) == 0.3 and conv.pan_at(states, 90, 9.0) == 0.1  # the latest, the earliest
    assert conv.pan_at(states, 110, 9.0) == 0.2 and conv.pan_at([], 110, 9.0) == 9.0


def test_joint_velocity_and_correlation_layout():
    assert conv.joint_velocity((0, 0.1), (20_000_000, 0.12)) == pytest.approx(1.0)
    assert math.isnan(conv.joint_velocity(None, (1, 0.0))) and math.isnan(conv.joint_velocity((5, 0.0), (5, 1.0)))
    assert conv.correlation_layout(13, 306) == [("v", 13, 3978), ("k", 306, 306)]


def test_diagnostic_levels_and_values():
    from vergence.wire.messages import MessageError
    from vergence.wire.status import status_of

    raw = {"role": "reducer", "id": "r-1", "pid": 4, "t_ns": 7, "counters": {"profiles": 10}, "bad": {"frame": 0},
           "gatherer": {"dropped": 2}, "published_hz": 29.97}
    st = status_of(raw)
    d = conv.diagnostic("head", st, 0.5, 3.0, None)
    assert (d.level, d.name, d.message, d.hardware_id) == (conv.OK, "vergence/head/reducer/r-1", "ok", "head")
    assert dict(d.values) == {"pid": "4", "t_ns": "7", "profiles": "10", "bad.frame": "0", "gatherer.dropped": "2",
                              "published_hz": "29.97"}
    assert conv.diagnostic("head", status_of(dict(raw, bad={"frame": 3})), 0.5, 3.0, 0).level == conv.WARN
    assert conv.diagnostic("head", status_of(dict(raw, bad={"frame": 3})), 0.5, 3.0, 3).level == conv.OK
    # a named fault (vergence.head.doubt) is an ERROR with what to check; a name that is no fault is not believed
    held = conv.diagnostic("head", status_of(dict(raw, fault="reversed", fault_note="reversed: flip it")), 0.5, 3.0, 0)
    assert (held.level, held.message) == (conv.ERROR, "fault reversed: reversed: flip it")
    assert conv.diagnostic("head", status_of(dict(raw, fault="gremlins")), 0.5, 3.0, 0).level == conv.OK
    assert status_of(dict(raw, fault=None)).fault() is None
    assert conv.diagnostic("head", status_of(dict(raw, exiting=True)), 0.5, 3.0, None).level == conv.ERROR
    assert conv.diagnostic("head", st, 3.5, 3.0, None).level == conv.STALE
    # a search (vergence.head.search) is a WARN that says what to check once a sweep found nothing
    lost = conv.diagnostic("head", status_of(dict(raw, searching=True, sweeps_empty=1)), 0.5, 3.0, None)
    assert (lost.level, lost.message) == (conv.WARN, "searching: no confident match at the fovea; 1 sweep of the pan "
                                          "range found nothing: is the point visible to the slave camera (hidden "
                                          "behind a nearer object, or out of its view)?")
    assert conv.diagnostic("head", status_of(dict(raw, searching=False, sweeps_empty=1)), 0.5, 3.0, None).level \
        == conv.OK
    # black or flat frames (no texture at the fovea): named at WARN, the slave holds
    blind = conv.diagnostic("head", status_of(dict(raw, no_texture=True)), 0.5, 3.0, None)
    assert blind.level == conv.WARN and blind.message.startswith("no texture at the fovea (a black or flat image")
    assert conv.diagnostic("head", status_of(dict(raw, no_texture="yes")), 0.5, 3.0, None).level == conv.OK
    with pytest.raises(MessageError, match="role"):
        status_of({"bad": "x"})


def test_images_decode_to_gray_with_step_padding_and_refuse_the_rest():
    rng = np.random.default_rng(1)
    bgr = rng.integers(0, 256, (5, 7, 3), np.uint8)
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    pad = lambda a, step: np.pad(a.reshape(a.shape[0], -1), ((0, 0), (0, step - a[0].size))).tobytes()  # noqa: E731
    assert np.array_equal(conv.image_gray("bgr8", 7, 5, 24, pad(bgr, 24)), gray)
    assert np.array_equal(conv.image_gray("rgb8", 7, 5, 21, bgr[..., ::-1].tobytes()), gray)
    assert np.array_equal(conv.image_gray("mono8", 7, 5, 8, pad(gray, 8)), gray)
    bgra = np.dstack([bgr, np.full((5, 7), 255, np.uint8)])
    assert np.array_equal(conv.image_gray("bgra8", 7, 5, 28, bgra.tobytes()), gray)
    m16 = gray.astype(np.uint16) * 256 + 77
    assert np.array_equal(conv.image_gray("mono16", 7, 5, 14, m16.astype("<u2").tobytes()), gray)
    assert np.array_equal(conv.image_gray("mono16", 7, 5, 14, m16.astype(">u2").tobytes(), 1), gray)
    for args, why in ((("yuv422", 7, 5, 14, bytes(70)), "encoding"), (("mono8", 7, 5, 6, bytes(35)), "step"),
                      (("mono8", 7, 5, 7, bytes(34)), "34 bytes"), (("mono8", 0, 5, 7, b""), "0 x 5")):
        with pytest.raises(conv.ImageError, match=why):
            conv.image_gray(*args)
    png = cv2.imencode(".png", gray)[1].tobytes()
    assert np.array_equal(conv.compressed_gray("mono8; png compressed mono8", png), gray)
    jpg = cv2.imencode(".jpg", np.tile(gray, (8, 8)), [cv2.IMWRITE_JPEG_QUALITY, 100])[1].tobytes()
    assert np.abs(conv.compressed_gray("jpeg", jpg).astype(int) - np.tile(gray, (8, 8))).max() <= 8
    for fmt, data, why in (("png", b"\x89PNG garbage", "cannot decode"), ("bmp", png, "want jpeg or png"),
                           ("16UC1; compressedDepth", png, "depth"), ("png", b"", "cannot decode")):
        with pytest.raises(conv.ImageError, match=why):
            conv.compressed_gray(fmt, data)


def test_pairer_pairs_by_stamp_within_slop_and_counts_the_rest():
    p = conv.Pairer(slop_ns=5, depth=3)
    assert p.add(0, 100, "L100") is None
    assert p.add(1, 103, "R103") == (100, "L100", 103, "R103")
    assert p.add(1, 130, "R130") is None and p.add(0, 120, "L120") is None  # 10 apart: no pair
    assert p.add(0, 131, "L131") == (131, "L131", 130, "R130") and p.unmatched == 1  # L120 left unpaired
    for t in (200, 210, 220, 230):  # a left camera alone: the oldest beyond depth go, counted
        assert p.add(0, t, t) is None
    assert p.unmatched == 2 and [t for t, _ in p.queues[0]] == [210, 220, 230]
    assert p.add(1, 222, "R") == (220, 220, 222, "R") and p.unmatched == 3 and p.pairs == 3
