"""`vergence ros2`, the bridge, as a real process between a real Zenoh router and the test's own real rclpy node:
every topic's values, stamps, type names and hashes; look_at to a Fixate; bad look_at points and bad Zenoh
messages counted, never a Fixate. (The conversions alone: tests/vergence/test_ros2.py.)"""

from __future__ import annotations

import functools
import json
import math
import re
import threading
import time

import cv2
import numpy as np
import pytest

import rosnode
from procs import Procs, free_port, run, wait_for
from vergence.wire import keys
from vergence.stages.frames import make_frame
from vergence.wire.messages import Fixate, MotorState, Preview, Profile, Decision
from vergence.network.params import Params

pytestmark = [pytest.mark.slow, pytest.mark.alone]  # (alone: tests/split.py)

# RIHS01 hashes as rclpy 7.1.6 (Jazzy) reports them (../shared/docs/ROS2.md), for the types that table names
HASHES = {"sensor_msgs/msg/JointState": "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e",
          "geometry_msgs/msg/PointStamped":
              "RIHS01_4c0296af86e01e562e9e0405d138a01537247580076c58ea38d7923ac1045897"}
W, H, F = 320, 240, 400.0


def frame_bytes(rig: str) -> bytes:
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (H, W), np.uint8)
    return make_frame(img, img, rig=rig, frame=1, pan_rad=0.0, focal_px=F, params=Params(),
                      plan=[["w", 0, W - 15 + 1]]).to_bytes()


def verdict(rig: str, frame: int, converged: bool, x=200, y=100, depth=0.8, sigma=0.01, t=None) -> Decision:
    return Decision(rig=rig, frame=frame, t_capture_ns=t or time.time_ns(), t_reduced_ns=time.time_ns(), window=15,
                   k=150, k_sub=150.2, v_shift=0, k_centre=150, direction=0, magnitude=0, offset_px=0.2,
                   confidence=0.9, confident=True, texture=1.0, pan_rad=0.05, x=x, y=y, converged=converged,
                   depth_m=depth if converged else math.nan, depth_sigma_m=sigma if converged else math.nan)


def put_until(s, key: str, payload: bytes, done, timeout: float = 10.0, what: str = "an answer", logs=None):
    """Put payload on key every 0.1 s until done() (the subscriptions of a process just started route late)."""
    def cond():
        s.put(key, payload() if callable(payload) else payload)
        time.sleep(0.05)  # the answer's own time to come back; polled again by wait_for
        return done()

    return wait_for(cond, timeout, what, interval=0.05, logs=logs)


class Bridged:
    """A running `vergence ros2` and the test's ends: a Zenoh session, an rclpy node collecting every topic."""

    def __init__(self, P, t, domain: int):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float32MultiArray

        self.P, self.t, self.domain = P, t, domain
        P.router()
        self.bridge = P.start("ros2", "ros2")
        self.ns = ns = f"/vergence/{P.rig}"
        self.joints = t.collect(JointState, f"{ns}/joint_states")
        self.fixes = t.collect(PointStamped, f"{ns}/fixation")
        self.covs = t.collect(PoseWithCovarianceStamped, f"{ns}/fixation/covariance")
        self.corrs = t.collect(Float32MultiArray, f"{ns}/correlation")
        self.diags = t.collect(DiagnosticArray, "/diagnostics")
        self.s = P.session()
        P.wait_alive(self.s, "ros2")
        self.fixates = P.collect(self.s, P.key("fixate"))
        self.statuses = P.collect(self.s, keys.status(P.rig, "ros2", "*"))

    def status(self, cond=lambda st: True, what: str = "the bridge's status") -> dict:
        """The bridge's latest status once cond(status) holds."""
        def latest():
            got = self.statuses.snapshot()
            st = json.loads(got[-1][1]) if got else None
            return st if st is not None and cond(st) else None

        return wait_for(latest, 10, what, logs=self.P.logs)

    def diagnostic(self, name_starts: str, level: bytes | None = None, what: str = "a DiagnosticStatus"):
        def find():
            return next((d for _, arr in self.diags for d in arr.status
                         if d.name.startswith(name_starts) and (level is None or d.level == level)), None)

        return self.t.wait_until(find, 10, what, self.P.logs)


def _joint_states(b: Bridged) -> None:
    """joint_states: the motor's own stamps; velocity from two states 10 ms apart."""
    P, s, joints = b.P, b.s, b.joints
    put_until(s, P.key("motor_state"), lambda: MotorState(rig=P.rig, t_ns=time.time_ns(), pan_rad=0.1, goal_rad=0.1,
                                                            min_rad=-0.5, max_rad=0.5, status="ok").to_bytes(),
              lambda: joints, what="a joint state", logs=P.logs)
    n, t0 = len(joints), time.time_ns()
    for dt, p in ((0, 0.1), (10_000_000, 0.12)):
        s.put(P.key("motor_state"), MotorState(rig=P.rig, t_ns=t0 + dt, pan_rad=p, goal_rad=p, min_rad=-0.5,
                                               max_rad=0.5, status="ok").to_bytes())
    js = b.t.wait_until(lambda: next((m for _, m in joints[n:] if (m.header.stamp.sec, m.header.stamp.nanosec)
                                      == divmod(t0 + 10_000_000, 10**9)), None), 10, "the second state", P.logs)
    assert list(js.name) == [f"{P.rig}_slave_pan"] and js.position[0] == pytest.approx(0.12, abs=1e-12)
    assert js.velocity[0] == pytest.approx(2.0, rel=1e-6)


def _fixation_and_correlation(b: Bridged) -> None:
    """fixation: nothing before a frame's view, nothing while not converged; then the point in the master's
    optical frame, stamped with the frame's capture time; its covariance; correlation: layer 4 as float32."""
    P, s, t = b.P, b.s, b.t
    put_until(s, P.key("frame"), frame_bytes(P.rig), lambda: any(json.loads(p)["counters"].get("frames") for _, p, _
                                                                 in b.statuses.snapshot()), what="a frame counted")
    s.put(P.key("decision"), verdict(P.rig, 2, False).to_bytes())
    tc = time.time_ns()
    s.put(P.key("decision"), verdict(P.rig, 3, True, t=tc).to_bytes())
    _, fx = t.wait(b.fixes, 1, 10, "fixations", P.logs)[0]
    assert (fx.point.x, fx.point.y, fx.point.z) == pytest.approx((40 * 0.8 / F, -20 * 0.8 / F, 0.8), abs=1e-12)
    assert fx.header.frame_id == f"{P.rig}_master_optical_frame"
    assert (fx.header.stamp.sec, fx.header.stamp.nanosec) == divmod(tc, 10**9)
    _, cv = t.wait(b.covs, 1, 10, "covariances", P.logs)[0]
    c = np.array(cv.pose.covariance).reshape(6, 6)
    ray = np.array([0.08, -0.04, 0.8]) / np.linalg.norm([0.08, -0.04, 0.8])
    assert ray @ c[:3, :3] @ ray == pytest.approx((0.01 * np.linalg.norm([0.08, -0.04, 0.8]) / 0.8) ** 2)
    assert len(b.fixes) == 1  # the unconverged decision published nothing

    scores = np.arange(13 * 306, dtype="<f8").reshape(13, 306) / 7.0
    pr = Profile(**{f: getattr(verdict(P.rig, 4, True), f) for f in Decision.__struct_fields__},
                 width=W, rows=13, scores=scores.tobytes())
    # the bridge follows the profiles once it sees our subscription to correlation (within a second)
    put_until(s, P.key("profile"), pr.to_bytes(), lambda: b.corrs, what="a correlation", logs=P.logs)
    _, cm = b.corrs[0]
    assert "correlation: a ROS 2 subscriber: following the profiles" in b.bridge.text()
    assert [(d.label, d.size, d.stride) for d in cm.layout.dim] == [("v", 13, 13 * 306), ("k", 306, 306)]
    assert np.array_equal(np.asarray(cm.data, np.float32), scores.astype(np.float32).ravel())


def _point(x, y, z, frame=""):
    from geometry_msgs.msg import PointStamped

    m = PointStamped()
    m.header.frame_id = frame
    m.point.x, m.point.y, m.point.z = x, y, z
    return m


def _look_at(b: Bridged) -> None:
    """look_at: a good point -> a Fixate at its pixel; six bad ones, a publisher of another type and a flood:
    counted, nothing sent for them, a WARN of the bridge on /diagnostics."""
    from geometry_msgs.msg import PointStamped
    from std_msgs.msg import String

    P, ns = b.P, b.ns
    look = b.t.publisher(PointStamped, f"{ns}/look_at", logs=P.logs)
    for bad in (_point(0.0, 0.0, -1.0), _point(math.nan, 0, 1), _point(1.0, 0.0, 0.1), _point(0, 0, math.inf),
                _point(0, 0, 1, frame="base_link"), _point(0.39, 0.0, 1.0)):
        look.publish(bad)
    look.publish(_point(-0.1, 0.05, 1.0))  # pixel (160 - 40, 120 + 20)
    req = Fixate.from_bytes(b.fixates.wait(1, 10)[0][1])
    assert (req.x, req.y, req.source) == (120.0, 140.0, "ros2 look_at") and len(b.fixates) == 1
    own = b.status(lambda st: st["counters"].get("look_at", 0) >= 7)
    assert own["counters"]["look_at_refused"] == 6 and own["counters"]["look_at_sent"] == 1
    d = b.diagnostic(f"vergence/{P.rig}/ros2/", b"\x01", "a WARN of the bridge")
    assert d.message.startswith("look_at refused: point (0.39, 0, 1) at pixel (316, 120): ")

    with rosnode.TestNode(b.domain, "wrong_type") as other:  # (one participant cannot have both types on a topic)
        other.node.create_publisher(String, f"{ns}/look_at", 10).publish(String(data="look at me"))
        own = b.status(lambda st: st["counters"].get("look_at_wrong_type"), "the wrong type counted")
    assert own["counters"]["look_at_wrong_type"] == 1 and own["counters"]["look_at_sent"] == 1
    assert f"publishes std_msgs/msg/String on {ns}/look_at" in (b.P.dir / "ros2.log").read_text()

    for i in range(60):  # a flood, 60 in 0.3 s: at most LOOK_AT_HZ (20) a second go on as Fixates
        look.publish(_point(-0.1, 0.05 + i * 1e-4, 1.0))
        time.sleep(0.005)  # (the publishing rate under test: 200 Hz)
    own = b.status(lambda st: st["counters"]["look_at"] >= 67, "the flood counted")
    assert own["counters"]["look_at_sent"] - 1 <= 20 and own["counters"]["look_at_flood"] >= 40
    wait_for(lambda: len(b.fixates) == own["counters"]["look_at_sent"], 5, "the Fixates", logs=P.logs)


def _diagnostics_and_bad_zenoh(b: Bridged) -> None:
    """/diagnostics: a process's status becomes one DiagnosticStatus, a growing bad count a WARN, the motor OK
    then STALE; bad Zenoh messages: counted, nothing published."""
    P, s = b.P, b.s
    cap = {"role": "capture", "id": "c-1", "counters": {"frames": 7}, "bad": {"fixate": 1}, "window": 15}
    s.put(keys.status(P.rig, "capture", "c-1"), json.dumps(cap))
    s.put(keys.status(P.rig, "capture", "c-1"), json.dumps(dict(cap, bad={"fixate": 2})))
    d = b.diagnostic(f"vergence/{P.rig}/capture/c-1", what="the capture's DiagnosticStatus")
    assert d.level == b"\x01" and d.hardware_id == P.rig and d.message == "bad messages: fixate 2"
    assert {kv.key: kv.value for kv in d.values} == {"frames": "7", "bad.fixate": "2", "window": "15"}
    motor = [d for _, a in b.diags for d in a.status if d.name == f"vergence/{P.rig}/motor"]
    assert motor[0].level == b"\x00" and {kv.key: kv.value for kv in motor[0].values}["pan_rad"] in ("0.1", "0.12")
    b.diagnostic(f"vergence/{P.rig}/motor", b"\x03", "the motor STALE (no motor state for 3 s)")

    before = (len(b.joints), len(b.fixes), len(b.corrs))
    for key in ("motor_state", "decision", "profile", "frame"):
        s.put(P.key(key), b"\xc1 garbage")
    s.put(P.key("motor_state"), MotorState(rig=P.rig, t_ns=-5, pan_rad=0.0, goal_rad=0.0, min_rad=-1,
                                           max_rad=1, status="ok").to_bytes())  # a time before the epoch
    s.put(keys.status(P.rig, "worker", "x"), b"[1, 2")
    want = {"motor_state": 2, "decision": 1, "profile": 1, "frame": 1, "status": 1}
    # the keys arrive on separate subscribers in no set order: wait until every count has reached its figure
    own = b.status(lambda st: all(st.get("bad", {}).get(k, 0) >= n for k, n in want.items()), "bad messages counted")
    assert own["bad"] == want
    assert (len(b.joints), len(b.fixes), len(b.corrs)) == before


def _frames_as_the_camera_names_them(b: Bridged) -> None:
    """A frame whose master image names its optical frame (the ros2 source's header.frame_id): the fixation is
    published in that name, and a look_at in it is taken; a frame_id that is no plausible name (a space) is
    ignored and counted, and the fixation is back in <rig>_master_optical_frame."""
    from geometry_msgs.msg import PointStamped

    P, s, t = b.P, b.s, b.t
    frame = make_frame(np.random.default_rng(1).integers(0, 256, (H, W), np.uint8),
                       np.zeros((H, W), np.uint8), rig=P.rig, frame=1, pan_rad=0.0, focal_px=F, params=Params(),
                       plan=[["w", 0, W - 15 + 1]])

    def fixation_in(name: str, fid: str):
        """Put the frame (named fid) and a converged decision until a fixation in `name` comes (the frame and the
        decision arrive on subscribers of their own, in no set order)."""
        frame.frame_id = fid
        n = len(b.fixes)

        def got():
            s.put(P.key("frame"), frame.to_bytes())
            s.put(P.key("decision"), verdict(P.rig, 9, True).to_bytes())
            return next((m for _, m in b.fixes[n:] if m.header.frame_id == name), None)

        return wait_for(got, 10, f"a fixation in {name}", interval=0.1, logs=P.logs)

    fx = fixation_in("cam_left_optical", "cam_left_optical")
    assert (fx.point.x, fx.point.y, fx.point.z) == pytest.approx((40 * 0.8 / F, -20 * 0.8 / F, 0.8), abs=1e-12)
    _, cov = t.wait_until(lambda: [c for c in b.covs if c[1].header.frame_id == "cam_left_optical"][:1], 5,
                          "its covariance in cam_left_optical", P.logs)[0]
    look = t.publisher(PointStamped, f"{b.ns}/look_at", logs=P.logs)
    sent, n = b.status()["counters"]["look_at_sent"], len(b.fixates)
    look.publish(_point(-0.1, 0.05, 1.0, frame="cam_left_optical"))  # the image's own name: taken
    own = b.status(lambda st: st["counters"]["look_at_sent"] > sent, "the look_at in the image's frame sent")
    req = Fixate.from_bytes(b.fixates.wait(n + 1, 10)[-1][1])
    assert (req.x, req.y) == (120.0, 140.0) and own["counters"]["look_at_sent"] == sent + 1

    fixation_in(f"{P.rig}_master_optical_frame", "cam left\n")
    own = b.status(lambda st: st["counters"].get("frame_id_ignored"), "the bad frame_id counted")
    assert own["counters"]["frame_id_ignored"] >= 1 and own["counters"]["look_at_sent"] == sent + 1
    assert "not printable ASCII without spaces: not taken as the optical frame's name" in b.bridge.text()


def _type_hashes(b: Bridged) -> None:
    """Type names and hashes as rclpy reports them, equal to rosbags' (an independent computation)."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    for topic, tp in ((f"{b.ns}/joint_states", "sensor_msgs/msg/JointState"),
                      (f"{b.ns}/fixation", "geometry_msgs/msg/PointStamped"),
                      (f"{b.ns}/fixation/covariance", "geometry_msgs/msg/PoseWithCovarianceStamped"),
                      (f"{b.ns}/correlation", "std_msgs/msg/Float32MultiArray"),
                      ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")):
        infos = list(b.t.node.get_publishers_info_by_topic(topic))
        assert [i.topic_type for i in infos] == [tp]
        assert str(infos[0].topic_type_hash) == store.hash_rihs01(tp) == HASHES.get(tp, store.hash_rihs01(tp))


def test_bridge_topics_values_stamps_hashes_and_look_at(tmp_path, monkeypatch):
    """`vergence ros2` between a real router and the test's rclpy node: each topic's values and stamps, look_at
    and its refusals, /diagnostics, bad Zenoh messages, the type names and hashes, a clean exit on SIGINT."""
    rosnode.require()
    domain = rosnode.ros_env(monkeypatch)
    with Procs(tmp_path) as P, rosnode.TestNode(domain) as t:
        b = Bridged(P, t, domain)
        _joint_states(b)
        _fixation_and_correlation(b)
        _look_at(b)
        _diagnostics_and_bad_zenoh(b)
        _frames_as_the_camera_names_them(b)
        _type_hashes(b)
        assert "ros2 bridge: look_at on (no deployed ACL (the Zenoh session is not authenticated)), discovery " \
               "localhost (this host only)" in b.bridge.text()
        own = b.status()
        assert (own["look_at"], own["discovery"]) == ("on", "localhost")
        assert b.bridge.stop() == 0 and f"ros2 {own['id']} exits" in b.bridge.text()


def test_bridge_under_the_deployed_acl_look_at_off_unless_turned_on(tmp_path, monkeypatch):
    """Under the deployed ACL (deploy/router-tcp.json5 and make-certs.sh's client configs): a bridge with the
    monitor's identity and no [ros2] look_at has look_at off: a look_at moves nothing (no Fixate) and is named in
    its log; one with the ros2 role's identity and `look_at = true` passes a look_at on as a Fixate, through the
    router's rules, and its status gets through."""
    rosnode.require()
    from deploy_helpers import client_config_file, client_session, make_secrets, router_config, start_router
    from geometry_msgs.msg import PointStamped
    from procs import VERGENCE

    domain = rosnode.ros_env(monkeypatch)
    secrets = make_secrets(tmp_path / "secrets", "localhost", "127.0.0.1")
    conf, endpoint = router_config("tcp", secrets, tmp_path / "router.json5")
    on = tmp_path / "on.toml"
    on.write_text("[ros2]\nlook_at = true\n")
    with Procs(tmp_path) as P, rosnode.TestNode(domain) as t:
        start_router(P, conf, endpoint)

        def bridge(name: str, role: str, ns: str, *extra: str):
            c = client_config_file(secrets, role, "tcp", endpoint, tmp_path / f"{name}.json5")
            return P.spawn(name, [VERGENCE, "ros2", "--rig", P.rig, "--namespace", ns, "--zenoh-config", str(c),
                                  *extra])

        b_on = bridge("ros2on", "ros2", "/acl_on", "--config", str(on))
        b_off = bridge("ros2off", "monitor", "/acl_off")
        watch = client_session(secrets, "monitor", "tcp", endpoint)
        cap = client_session(secrets, "capture", "tcp", endpoint)
        try:
            fixates = P.collect(watch, P.key("fixate"))
            statuses = P.collect(watch, keys.status(P.rig, "ros2", "*"))
            put_until(cap, P.key("frame"), frame_bytes(P.rig), lambda: any(
                json.loads(b)["counters"].get("frames") for _, b, _ in statuses.snapshot()), 30,
                "the ros2 role's bridge counting a frame", P.logs)
            point = _point(-0.1, 0.05, 1.0)  # pixel (120, 140)
            look_off = t.publisher(PointStamped, "/acl_off/look_at", logs=P.logs)
            look_off.publish(point)
            wait_for(lambda: "look_at is off, the fovea stays" in b_off.text(), 10, "the refusal logged",
                     logs=P.logs)
            assert "ros2 bridge: look_at off (a deployed ACL (the Zenoh session authenticates as user 'monitor'); " \
                   "[ros2] look_at = true, with the ros2 role's client config, turns it on)" in b_off.text()
            t.publisher(PointStamped, "/acl_on/look_at", logs=P.logs).publish(point)
            req = Fixate.from_bytes(fixates.wait(1, 10)[0][1])
            assert (req.x, req.y) == (120.0, 140.0)
            own = json.loads(wait_for(lambda: next((b for _, b, _ in reversed(statuses.snapshot())
                                                    if json.loads(b)["counters"].get("look_at_sent")), None), 10,
                                      "the look_at counted", logs=P.logs))
            assert own["look_at"] == "on" and own["counters"]["look_at_sent"] == 1
            assert "ros2 bridge: look_at on ([ros2] look_at = true)" in b_on.text()
            assert len(fixates) == 1  # the look_at while off sent nothing
        finally:
            watch.close()
            cap.close()


def _verdicts(c, after_ns: int = 0) -> list[tuple[int, Decision]]:
    return [(t, Decision.from_bytes(b)) for t, b, _ in c.snapshot() if t >= after_ns]


def _converges_within_3_s(P, t, decisions, fixes, t_first: int, error_px, z_true: float) -> int:
    """Five decisions in a row within 1 px and the slave within 1 px of the truth (error_px()) no later than 3 s
    after the first decision; then the next 5 fixations at the depth z_true (their median within 2 %): the first
    returned."""

    def converged():
        v = _verdicts(decisions, t_first)
        if len(v) >= 5 and all(abs(d.offset_px) <= 1 for _, d in v[-5:]) and abs(error_px()) <= 1:
            return v[-1][0]
        return None

    t_conv = wait_for(converged, 10, "converged decisions and joint states", interval=0.01, logs=P.logs)
    took = (t_conv - t_first) / 1e9
    print(f"converged {took:.2f} s after the first decision")
    assert took <= 3.0
    # the fixations of the 5 frames after it, their median at the depth (one frame's alone may be off: the test's
    # camera node renders at the joint states it heard, which a loaded CI once delivered late: 0.766 m of 0.8)
    def five():
        after = [f for f in fixes if f[0] > t_conv]
        return after[:5] if len(after) >= 5 else None

    got = t.wait_until(five, 5, "5 fixations", P.logs)
    if z_true is not None:
        assert float(np.median([f.point.z for _, f in got])) == pytest.approx(z_true, rel=0.02)
    return got[0][1]


def _look_at_through_the_loop(P, t, decisions, fixes, z_true: float) -> None:
    """look_at another point of the target (pixel (90, 150), in the master's optical frame as the camera names it,
    left_optical_frame): the next decisions are there, and once the loop has converged there `fixation` says that
    point; one behind the camera moves nothing."""
    from geometry_msgs.msg import PointStamped

    look = t.publisher(PointStamped, f"/vergence/{P.rig}/look_at", logs=P.logs)
    target = _point((90 - 160) * 0.8 / 256, (150 - 120) * 0.8 / 256, 0.8, frame="left_optical_frame")  # the camera's
    t_look = time.time_ns()
    look.publish(target)
    wait_for(lambda: [v for _, v in _verdicts(decisions, t_look) if (v.x, v.y) == (90, 150)], 5,
             "a decision at (90, 150)", logs=P.logs)
    there = t.wait_until(lambda: (lambda f: f if len(f) >= 10 else None)(
        [m for a, m in fixes if a > t_look and abs(256 * m.point.x / m.point.z + 160 - 90) < 0.01]), 10,
        "10 fixations there", P.logs)
    assert all(256 * m.point.y / m.point.z + 120 == pytest.approx(150, abs=0.01) for m in there)
    assert np.median([m.point.z for m in there]) == pytest.approx(z_true, rel=0.02)
    t_bad = time.time_ns()
    target.point.z = -1.0
    look.publish(target)
    wait_for(lambda: len(_verdicts(decisions, t_bad)) >= 20, 10, "more decisions", logs=P.logs)
    assert {(v.x, v.y) for _, v in _verdicts(decisions, t_bad)} == {(90, 150)}


def test_up_with_a_ros2_stereo_camera_converges_and_fixation_depth(tmp_path, monkeypatch):
    """The Must of issue #27: the test's own ROS 2 node plays a stereo camera at 30 Hz (vergence.sim.moving's
    head, f = 256 px, b = 0.06 m, a textured target 0.8 m ahead), its slave view rendered at the pan it reads
    from /vergence/<rig>/joint_states at the exposure (interpolated between two joint states; the images come
    out 30 ms after it); `vergence up --source ros2:LEFT,RIGHT --ros2` (the sim actuator) converges within 1 px
    within 3 s of its first decision (measured: 0.23-0.30 s in 12 runs), and `fixation` says z within 2 % of
    0.8 m, in the camera's own frame (left_optical_frame). A look_at point in it moves the fovea (the next
    decisions, then `fixation`, there); a bad one nothing; one to a second bridge with look_at off nothing (issue
    #36's Must), counted and named."""
    rosnode.require()
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import JointState
    from vergence.sim.moving import Head, MovingRig

    domain = rosnode.ros_env(monkeypatch)
    z_true = 0.8
    rig = MovingRig("still:z=0.8", Head(0.06, 256.0, (320, 240)))
    with Procs(tmp_path) as P, rosnode.TestNode(domain) as t:
        P.endpoint = f"tcp/127.0.0.1:{free_port()}"
        joints = t.collect(JointState, f"/vergence/{P.rig}/joint_states")
        fixes = t.collect(PointStamped, f"/vergence/{P.rig}/fixation")

        def pan() -> float:
            return float(joints[-1][1].position[0]) if joints else 0.0

        def pan_at(t_ns: int) -> float | None:
            """The slave's pan at t_ns, from the joint states received (interpolated between two); None before
            the first of them."""
            from vergence.ros2.convert import pan_at as interpolate

            with t.cond:
                states = [(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, m.position[0]) for _, m in joints[-20:]]
            if not states or t_ns < states[0][0]:
                return None
            return interpolate(states, t_ns, 0.0)

        diags = t.collect(DiagnosticArray, "/diagnostics")
        cam = rosnode.StereoCamera(t, lambda p: rig.render(p, 0.0), pan_at, 256.0, hz=30.0)
        off = tmp_path / "off.toml"
        off.write_text("[ros2]\nlook_at = false\n")
        try:
            P.start("up", "up", "--listen", P.endpoint, "--source", f"ros2:{cam.LEFT},{cam.RIGHT}:wait=60", "--ros2",
                    "--workers", "2", "--rate", "0", "--no-standby", connect=False)
            # a second bridge, look_at off, started meanwhile (it waits for up's router)
            P.start("ros2off", "ros2", "--namespace", "/vergence_off", "--config", str(off))
            s = P.session(60)
            decisions = P.collect(s, P.key("decision"))
            t_first = decisions.wait(1, 90)[0][0]

            fx = _converges_within_3_s(P, t, decisions, fixes, t_first, lambda: rig.error_px(pan()), z_true)
            assert (fx.point.x, fx.point.y) == pytest.approx((0.0, 0.0), abs=0.005)  # the fovea: the view centre
            assert fx.header.frame_id == "left_optical_frame"  # the master image's own, without configuration
            # the fixation is stamped with a pair's exposure (the camera's stamps), never later than it arrived
            stamp = fx.header.stamp.sec * 10**9 + fx.header.stamp.nanosec
            assert min(abs(stamp - ts) for ts, _ in cam.sent) < 50_000_000

            _look_at_through_the_loop(P, t, decisions, fixes, z_true)
            _look_at_off_moves_nothing(P, t, s, decisions, diags)
        finally:
            cam.close()


def _look_at_off_moves_nothing(P, t, s, decisions, diags) -> None:
    """A second bridge on the same rig, `[ros2] look_at = false`, under the namespace /vergence_off: a look_at to
    another pixel (200, 100) there moves nothing (the next 20 decisions stay at (90, 150), where the first
    bridge's look_at put the fovea), is counted (look_at_off) and named: the log, a WARN on /diagnostics saying
    what to set."""
    from geometry_msgs.msg import PointStamped

    statuses = P.collect(s, keys.status(P.rig, "ros2", "*"))
    off = wait_for(lambda: next((json.loads(b) for _, b, _ in reversed(statuses.snapshot())
                                 if json.loads(b).get("look_at") == "off"), None), 60, "the second bridge's status",
                   logs=P.logs)
    look = t.publisher(PointStamped, "/vergence_off/look_at", logs=P.logs)
    t_look = time.time_ns()
    look.publish(_point((200 - 160) * 0.8 / 256, (100 - 120) * 0.8 / 256, 0.8, frame="left_optical_frame"))
    counted = wait_for(lambda: next((st for st in (json.loads(b) for _, b, _ in statuses.snapshot())
                                     if st["id"] == off["id"] and st["counters"].get("look_at_off")), None), 10,
                       "look_at_off counted", logs=P.logs)
    assert counted["counters"]["look_at_off"] == 1 and "look_at_sent" not in counted["counters"]
    wait_for(lambda: len(_verdicts(decisions, t_look)) >= 20, 10, "more decisions", logs=P.logs)
    assert {(v.x, v.y) for _, v in _verdicts(decisions, t_look)} == {(90, 150)}
    d = t.wait_until(lambda: next((d for _, a in diags for d in a.status
                                   if d.name == f"vergence/{P.rig}/ros2/{off['id']}" and d.level == b"\x01"), None),
                     10, "the second bridge's WARN", P.logs)
    assert d.message.startswith("look_at is off: set [ros2] look_at = true")
    text = (P.dir / "ros2off.log").read_text()
    assert "ros2 bridge: look_at off ([ros2] look_at = false), discovery localhost (this host only)" in text
    assert "look_at is off, the fovea stays" in text


def _image(t: "rosnode.TestNode", img, t_ns: int, encoding: str = "mono8"):
    from sensor_msgs.msg import Image

    m = Image()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(t_ns, 10**9)
    m.height, m.width = img.shape[:2]
    m.encoding, m.step = encoding, img.shape[1] * (img.shape[2] if img.ndim == 3 else 1)
    m.data = img.tobytes()
    return m


def _source_counters(statuses, cond):
    """A wait_for condition: the `source` counters of the capture's latest status once cond(them) holds."""
    def f():
        for _, b, _ in reversed(statuses.snapshot()):
            src = json.loads(b).get("source", {})
            return src if cond(src) else None
        return None
    return f


def _send_bad_images(t, right, gray, source, logs) -> dict[str, int]:
    """An unknown encoding, a frame_id with a space (the image is used, its frame_id not), stamps of 0 and 1 h ahead,
    another size: each counted before the next, each sent
    again every 0.5 s until counted (best effort: one may be dropped while the feeder's pairs come). How many of
    each were sent."""
    def named(fid: str):
        m = _image(t, np.dstack([gray] * 3), time.time_ns(), "bgr8")
        m.header.frame_id = fid
        return m

    sent = {"bad_image": 0, "bad_stamp": 0, "bad_size": 0, "bad_frame_id": 0}
    for kind, n, make in (("bad_image", 1, lambda: _image(t, gray, time.time_ns(), "yuv422")),
                          ("bad_frame_id", 1, lambda: named("right camera")),
                          ("bad_stamp", 1, lambda: _image(t, gray, 0)),
                          ("bad_stamp", 2, lambda: _image(t, gray, time.time_ns() + 3600 * 10**9)),
                          ("bad_size", 1, lambda: _image(t, np.zeros((60, 80, 3), np.uint8), time.time_ns(), "bgr8"))):
        due = [0.0]

        def counted(kind=kind, n=n, make=make, due=due):
            if (source(lambda c: True)() or {}).get(kind, 0) >= n:
                return True
            if time.monotonic() >= due[0]:  # (again) once every 0.5 s
                right.publish(make())
                sent[kind] += 1
                due[0] = time.monotonic() + 0.5
            return False

        wait_for(counted, 20, f"{kind} {n} counted", logs=logs)
    return sent


def _topics_refused(P, t) -> None:
    """A topic nobody publishes, and one of another type: the capture exits 2 naming it."""
    from std_msgs.msg import String

    r = P.start("capture2", "capture", "--source", "ros2:/nobody/left,/cam/right/image_raw:wait=1")
    wait_for(lambda: r.poll() is not None, 30, "the capture to exit", logs=P.logs)
    assert r.returncode == 2
    text = (P.dir / "capture2.log").read_text()  # (the right topic too, when discovery took over 1 s)
    assert re.search(r"no publisher on /nobody/left(, /cam/right/image_raw)? after 1 s", text), text
    t.node.create_publisher(String, "/cam/words", 10)
    r = P.start("capture3", "capture", "--source", "ros2:/cam/words,/cam/right/image_raw:wait=10")
    wait_for(lambda: r.poll() is not None, 30, "the capture to exit", logs=P.logs)
    assert r.returncode == 2
    assert "topic /cam/words carries std_msgs/msg/String, not sensor_msgs/msg/Image" in (
        P.dir / "capture3.log").read_text()


def test_ros2_source_counts_bad_images_and_goes_on(tmp_path, monkeypatch):
    """`vergence capture --source ros2:...` fed by the test's node: compressed PNG on the left and raw bgr8 on the
    right pair by stamp; an encoding it cannot use, stamps of 0 and 1 h ahead, an image of another size, right
    images no left matches and a flood of 600 images in a burst are counted in the capture's status, and the
    capture goes on pairing. A topic nobody publishes: exit 2 naming it."""
    rosnode.require()
    from sensor_msgs.msg import CameraInfo, CompressedImage, Image

    domain = rosnode.ros_env(monkeypatch)
    rng = np.random.default_rng(2)
    gray = rng.integers(0, 256, (120, 160), np.uint8)
    bgr = np.dstack([gray] * 3)
    png = cv2.imencode(".png", gray)[1].tobytes()
    with Procs(tmp_path) as P, rosnode.TestNode(domain) as t:
        P.router()
        left = t.node.create_publisher(CompressedImage, "/cam/left/image_raw/compressed", 10)
        right = t.node.create_publisher(Image, "/cam/right/image_raw", 10)
        info = t.node.create_publisher(CameraInfo, "/cam/left/camera_info", 10)  # a garbage focal length

        def pair(t_ns=None, dt=0):
            t_ns = t_ns or time.time_ns()
            info.publish(CameraInfo(k=[math.inf, 0.0, 80.0, 0.0, math.inf, 60.0, 0.0, 0.0, 1.0]))
            c = CompressedImage(format="png", data=png)
            c.header.stamp.sec, c.header.stamp.nanosec = divmod(t_ns, 10**9)
            left.publish(c)
            right.publish(_image(t, bgr, t_ns + dt, "bgr8"))

        stop = threading.Event()
        feeder = threading.Thread(target=lambda: [pair() for _ in iter(lambda: stop.wait(0.05), True)],
                                                daemon=True)
        feeder.start()
        try:
            cap = P.start("capture", "capture", "--source",
                          "ros2:/cam/left/image_raw/compressed,/cam/right/image_raw:slop=0.002")
            s = P.session()
            statuses = P.collect(s, P.key("status/capture/*"))

            source = functools.partial(_source_counters, statuses)
            first = wait_for(source(lambda c: c.get("pairs", 0) >= 5), 30, "pairs counted", logs=P.logs)
            assert not any(k.startswith("bad") for k in first)
            sent = _send_bad_images(t, right, gray, source, P.logs)
            unmatched = first.get("unmatched", 0)
            for _ in range(3):  # no left image half a second on: pushed out unpaired
                right.publish(_image(t, bgr, time.time_ns() + 10**9 // 2, "bgr8"))
                time.sleep(0.05)  # one at a time (see above)
            wait_for(source(lambda c: c.get("unmatched", 0) >= unmatched + 3), 20, "unmatched counted", logs=P.logs)
            for _ in range(600):  # a flood: the newest are taken, the capture goes on
                right.publish(_image(t, bgr, time.time_ns(), "bgr8"))
            now = wait_for(source(lambda c: c), 5, "a status", logs=P.logs)
            got = wait_for(source(lambda c: c["pairs"] >= now["pairs"] + 10), 20, "more pairs", logs=P.logs)
            assert 1 <= got["bad_image"] <= sent["bad_image"] and 2 <= got["bad_stamp"] <= sent["bad_stamp"]
            assert 1 <= got["bad_size"] <= sent["bad_size"] and 1 <= got["bad_frame_id"] <= sent["bad_frame_id"]
            assert cap.poll() is None
            text = (tmp_path / "capture.log").read_text()
            assert "encoding 'yuv422' is not one vergence reads" in text and "stamp 0" in text
            assert "the stream changed size from 160 x 120 to 80 x 60" in text
            assert ("/cam/right/image_raw: the image's frame_id 'right camera': not printable ASCII without spaces is "
                    "not taken (the image is;") in text
            assert "camera_info without a usable focal length (k[0] = [inf])" in text and "f=128.0 px" in text
        finally:
            stop.set()
            feeder.join(2)
        _topics_refused(P, t)


GARBAGE = b"\xc1 garbage"


def _read_mcap(path, ns: str) -> dict[str, list]:
    """The file's ros2 profile, ros2msg schemas and CDR channels checked; its messages by topic, decoded by
    mcap-ros2-support from the schema text in the file, each also decoded by rclpy as the type it names, and
    the same counts from rosbags' rosbag2 reader."""
    import importlib

    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rclpy.serialization import deserialize_message
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with open(path, "rb") as fh:
        r = make_reader(fh)
        assert r.get_header().profile == "ros2"
        summary = r.get_summary()
        topics = {ch.topic: (summary.schemas[ch.schema_id].name, summary.schemas[ch.schema_id].encoding,
                             ch.message_encoding) for ch in summary.channels.values()}
    assert {(e, m) for _, e, m in topics.values()} == {("ros2msg", "cdr")}
    for topic, tp in (("joint_states", "sensor_msgs/msg/JointState"), ("fixation", "geometry_msgs/msg/PointStamped"),
                      ("fixation/covariance", "geometry_msgs/msg/PoseWithCovarianceStamped"),
                      ("correlation", "std_msgs/msg/Float32MultiArray"), ("preview/master", "sensor_msgs/msg/Image"),
                      ("zenoh/frame", "std_msgs/msg/UInt8MultiArray")):
        assert topics[f"{ns}/{topic}"][0] == tp
    assert topics["/diagnostics"][0] == "diagnostic_msgs/msg/DiagnosticArray"
    by_topic: dict[str, list] = {}
    with open(path, "rb") as fh:
        for schema, channel, message, decoded in make_reader(
                fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            by_topic.setdefault(channel.topic, []).append(decoded)
            pkg, _, name = schema.name.partition("/msg/")
            cls = getattr(importlib.import_module(f"{pkg}.msg"), name)  # rclpy's own type, by the file's name
            assert type(deserialize_message(message.data, cls)) is cls
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as bag:
        assert {c.topic: c.msgcount for c in bag.connections} == {k: len(v) for k, v in by_topic.items()}
    return by_topic


def _check_against_raw(by_topic: dict, ns: str, P) -> dict[str, list[bytes]]:
    """The ROS 2 messages say what the raw Zenoh samples of the same file say: pans and stamps, the fixated
    depth, the preview's pixels; the garbage made none. The raw payloads by key."""
    from vergence.sim import Rig
    from vergence.sim.optics import rotation

    raw: dict[str, list[bytes]] = {}
    for kind in ("motor_state", "decision", "preview"):
        for m in by_topic[f"{ns}/zenoh/{kind}"]:
            raw.setdefault(m.layout.dim[0].label, []).append(bytes(m.data))
    assert GARBAGE in raw[P.key("motor_state")] and GARBAGE in raw[P.key("decision")]
    states = [MotorState.from_bytes(b) for b in raw[P.key("motor_state")] if b != GARBAGE]
    joints = by_topic[f"{ns}/joint_states"]
    assert len(joints) == len(states) >= 50  # 4 s at 50 Hz, less start-up; the garbage made no joint state
    for st, js in zip(states, joints):
        assert js.position[0] == st.pan_rad and js.header.stamp.sec * 10**9 + js.header.stamp.nanosec == st.t_ns
    converged = [v for v in (Decision.from_bytes(b) for b in raw[P.key("decision")] if b != GARBAGE) if v.converged]
    fixes = by_topic[f"{ns}/fixation"]
    assert 10 <= len(fixes) <= len(converged)
    depth = {v.t_capture_ns: v.depth_m for v in converged}
    sim = Rig.from_spec("")  # the master is aimed: its optical frame turned into the head's gives the depth
    for m in fixes:
        head = rotation(sim.master_pan_rad, sim.tilt_rad) @ np.array([m.point.x, m.point.y, m.point.z])
        assert head[2] == pytest.approx(depth[m.header.stamp.sec * 10**9 + m.header.stamp.nanosec], rel=1e-9)
    first = Preview.from_bytes(next(b for b in raw[P.key("preview")] if b != GARBAGE))
    img = by_topic[f"{ns}/preview/master"][0]
    assert (img.width, img.height, img.encoding) == (first.width, first.height, "mono8")
    assert bytes(img.data) == first.master
    return raw


def test_record_mcap_opens_in_independent_readers_and_replays(tmp_path):
    """`vergence record FILE.mcap` of a running `vergence up` (the simulated rig), read by three readers this
    project did not write (_read_mcap), its messages checked against the raw samples in the same file
    (_check_against_raw); garbage published meanwhile is recorded raw and nothing else; `vergence replay
    FILE.mcap` publishes the recorded decisions again, byte for byte (whatever was recorded: the garbage too)."""
    rosnode.require()
    path = tmp_path / "run.mcap"
    with Procs(tmp_path) as P:
        P.endpoint = f"tcp/127.0.0.1:{free_port()}"
        P.start("up", "up", "--listen", P.endpoint, "--source", "sim", "--workers", "1", "--no-standby",
                connect=False)
        s = P.session(60)
        P.collect(s, P.key("decision")).wait(1, 90)
        rec = P.start("record", "record", str(path), "--duration", "4")
        P.wait_alive(s, "record")
        for key in ("motor_state", "decision", "profile", "preview", "status/capture/x"):
            s.put(P.key(key), GARBAGE)
        wait_for(lambda: rec.poll() is not None, 30, "the recorder to finish", logs=P.logs)
        assert rec.returncode == 0
        raw = _check_against_raw(_read_mcap(path, f"/vergence/{P.rig}"), f"/vergence/{P.rig}", P)

        again = P.collect(s, keys.decision("replay27"))
        rp = P.start("replay", "replay", str(path), "--rig", "replay27", "--only", "decision", "--speed", "0",
                     rig=False)
        wait_for(lambda: rp.poll() is not None, 60, "the replay to finish", logs=P.logs)
        assert rp.returncode == 0
        recorded = set(raw[P.key("decision")])  # the garbage too: a replay sends what was recorded
        got = [b for _, b, _ in again.snapshot()]
        assert len(got) >= len(recorded) - 5 and set(got) <= recorded  # (the first ones may precede the routes)
        assert "replayed" in rp.text() and "bad 0" in rp.text()


def _bad_and_silent_joint_states(P, t, s, ctl, states, decisions) -> None:
    """Bad joint states: counted in the motor state's errors, the pan unchanged. Joint states that stop: the
    motor state says disconnected with the reason and no command goes out, whatever the decisions; back: it
    resumes."""
    def latest() -> MotorState:
        return MotorState.from_bytes(states.snapshot()[-1][1])

    errors = latest().errors
    bad_pub = t.publisher(type(ctl.state(0)), "/joint_states", logs=P.logs)  # matched by the actuator

    def counted():  # the three again every 0.5 s until counted (a best-effort subscription)
        m = latest()
        if m.errors >= errors + 3:
            return m
        for bad in (ctl.state(time.time_ns(), names=["slave_pan", "tilt"], positions=[0.5]),
                    ctl.state(time.time_ns(), positions=[math.nan]), ctl.state(0, positions=[0.4])):
            bad_pub.publish(bad)
        return None

    st = wait_for(counted, 10, "errors counted", interval=0.5, logs=P.logs)
    assert abs(st.pan_rad - ctl.position()) < math.radians(1)

    ctl.publishing.clear()
    gone = wait_for(lambda: (lambda m: m if m.status == "disconnected" else None)(latest()), 10, "disconnected",
                    logs=P.logs)
    assert "no joint state" in gone.note
    n = len(ctl.commands)
    t_fix = time.time_ns()
    s.put(P.key("fixate"), Fixate(x=100, y=120, t_ns=t_fix).to_bytes())  # a reason to move: the background
    wait_for(lambda: sum((v.x, v.y) == (100, 120) and abs(v.offset_px) > 1 for _, v in _verdicts(
        decisions, t_fix)) >= 10, 20, "decisions off the new point", logs=P.logs)  # 10 s was short once, loaded
    assert len(ctl.commands) == n
    ctl.publishing.set()
    wait_for(lambda: latest().status in ("ok", "hold"), 15, "the motor back", logs=P.logs)


def test_up_with_the_ros2_driver_against_a_forward_command_controller(tmp_path, monkeypatch):
    """The second Must of issue #27: as the stereo-camera test, with `--driver ros2` driving a forward command
    controller played by the test (a joint heading for its command at 170 deg/s, /joint_states at 100 Hz; the
    camera renders the slave at that joint's pan): converged within 1 px within 3 s of the first decision made
    once the motor is connected (its first joint state can take seconds of DDS discovery); every command inside
    the limits and steps of the Safety. Bad joint states (arrays of unequal length, NaN, stamp 0) are counted in
    the motor state's errors; joint states that stop: the motor state says disconnected with the reason and no
    command goes out; they come back: it resumes.
    Issue #36's Must through ROS 2: the cameras' camera_info says their principal point (170, 112) and barrel
    distortion (k1 -0.25), and the slave camera sits 0.5 deg further than the joint says: `vergence calibrate
    --distance 0.8 --write` measures the zero, the head restarted with the file fixates at 0.8 m within 2 %."""
    rosnode.require()
    from geometry_msgs.msg import PointStamped
    from vergence.sim.moving import Head, MovingRig

    domain = rosnode.ros_env(monkeypatch)
    zero, cx, cy = math.radians(0.5), 170, 112
    rig = MovingRig("still:z=0.8", Head(0.06, 256.0, (320, 240), cx, cy, k1=-0.25))
    truth = rig.truth_at(160, 120)  # the camera's pan that converges the fovea (the image's centre)
    cfg = tmp_path / "head.toml"
    with Procs(tmp_path) as P, rosnode.TestNode(domain) as t:
        P.endpoint = f"tcp/127.0.0.1:{free_port()}"
        fixes = t.collect(PointStamped, f"/vergence/{P.rig}/fixation")
        ctl = rosnode.ForwardController(t)
        cam = rosnode.StereoCamera(t, lambda p: rig.render(p + zero, 0.0), ctl.pan_at, 256.0, hz=30.0,
                                   principal=(cx, cy), d=[-0.25, 0.0, 0.0, 0.0, 0.0])
        args = ("--listen", P.endpoint, "--source", f"ros2:{cam.LEFT},{cam.RIGHT}", "--ros2", "--driver", "ros2",
                "--port", "forward_position_controller:joint=slave_pan", "--workers", "2", "--rate", "0",
                "--no-standby")
        try:
            up = P.start("up", "up", *args, connect=False)
            s = P.session(60)
            decisions = P.collect(s, P.key("decision"))
            states = P.collect(s, P.key("motor_state"))
            # from the first decision once the motor is connected (its first joint state can take seconds of DDS
            # discovery; commands meanwhile are not executed)
            t_ok = wait_for(lambda: next((t for t, b, _ in states.snapshot() if MotorState.from_bytes(b).status
                                          in ("ok", "hold")), None), 90, "the motor connected", logs=P.logs)
            t_first = wait_for(lambda: next((t for t, _, _ in decisions.snapshot() if t >= t_ok), None), 90,
                               "a decision", logs=P.logs)

            _converges_within_3_s(P, t, decisions, fixes, t_first,
                                  lambda: 256.0 * math.tan(ctl.position() + zero - truth), None)
            goals = [g for _, g in ctl.commands]
            assert goals and ctl.bad_commands == 0 and all(abs(g) <= math.radians(45) for g in goals)
            assert all(abs(b - a) <= math.radians(10) + 1e-9 for a, b in zip([0.0] + goals, goals))
            last = MotorState.from_bytes(states.snapshot()[-1][1])
            assert last.driver == "ros2" and last.status in ("ok", "hold")
            assert last.t_ns in ctl.stamps  # the motor state's time is the joint state's own stamp

            _bad_and_silent_joint_states(P, t, s, ctl, states, decisions)

            t_back = time.time_ns()  # the fovea back on the target, whose distance calibrate is told
            s.put(P.key("fixate"), Fixate(x=160, y=120, t_ns=t_back).to_bytes())
            wait_for(lambda: sum((v.x, v.y) == (160, 120) and v.converged for _, v in _verdicts(decisions, t_back))
                     >= 5, 20, "converged decisions at (160, 120)", logs=P.logs)
            r = run("calibrate", "--connect", P.endpoint, "--rig", P.rig, "--distance", "0.8",
                    "--write", str(cfg), timeout=60)
            assert r.returncode == 0, r.stdout + r.stderr
            print(r.stdout)
            assert float(re.search(r"pan zero: off by ([-+\d.]+) \+-", r.stdout)[1]) == pytest.approx(0.5, abs=0.03)
            up.stop()
            t_again = time.time_ns()
            P.start("up2", "up", *args, "--config", str(cfg), connect=False)
            fx = t.wait_until(lambda: [f for a, f in fixes if a > t_again][10:11], 90, "fixations after the restart",
                              P.logs)[0]
            assert fx.point.z == pytest.approx(0.8, rel=0.02)
            assert fx.header.frame_id == "left_optical_frame"  # the camera's own name for it
        finally:
            cam.close()
            ctl.close()
    # SIGINT to `up`: each child, the ROS 2 ones too, exits by itself with 0
    for log_name in ("up.log", "up2.log"):
        text = (tmp_path / log_name).read_text()
        for child in ("capture", "ros2", "actuator", "reducer"):
            assert f"{child} stopped (exit 0)" in text, text[-3000:]


def test_ros2_driver_trajectory_mode_a_joint_group_and_silence(monkeypatch):
    """The ros2 driver in this process against the test's node: mode=trajectory sends one JointTrajectory point
    (joint names, position, time_from_start = reach); joints=A,B sends the group's Float64MultiArray in the
    controller's order with the other joint at its present position; parse_port refuses bad options; joint
    states that stop make read_position raise Disconnected (the MotorLoop then says disconnected and sends
    nothing) after the watchdog time."""
    rosnode.require()
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray
    from trajectory_msgs.msg import JointTrajectory
    from vergence.motors import MotorSettings, PortError, make_driver
    from vergence.motors.base import Disconnected
    from vergence.motors.ros2 import parse_port

    for bad in ("c:mode=velocity", "c:joint=a:joints=b,c", "c:reach=-1", "c:colour=red", "c:joint"):
        with pytest.raises(PortError):
            parse_port(bad)
    domain = rosnode.ros_env(monkeypatch)
    with rosnode.TestNode(domain) as t:
        trajs = t.collect(JointTrajectory, "/head_controller/joint_trajectory")
        groups = t.collect(Float64MultiArray, "/group_controller/commands")
        pub = t.node.create_publisher(JointState, "/robot/joint_states", 10)
        alive = threading.Event()
        alive.set()
        done = threading.Event()

        def states():
            while not done.wait(0.02):
                if alive.is_set():
                    m = JointState(name=["tilt", "pan"], position=[0.2, 0.1])
                    m.header.stamp.sec, m.header.stamp.nanosec = divmod(time.time_ns(), 10**9)
                    pub.publish(m)

        th = threading.Thread(target=states, daemon=True)
        th.start()
        settings = MotorSettings(watchdog_s=0.5)
        traj = make_driver("ros2", settings, "head_controller:joint=pan:mode=trajectory:states=/robot/joint_states"
                                             ":reach=0.2")
        group = make_driver("ros2", settings, "group_controller:joint=pan:joints=tilt,pan:states=/robot/joint_states")
        try:
            assert traj.open() == pytest.approx(0.1) and group.open() == pytest.approx(0.1)
            assert traj.position_ns is not None and abs(traj.position_ns - time.time_ns()) < 10**9
            wait_for(lambda: trajs or traj.write_goal(0.15), 10, "a trajectory", interval=0.1)
            m = trajs[0][1]
            assert list(m.joint_names) == ["pan"] and list(m.points[0].positions) == [0.15]
            assert (m.points[0].time_from_start.sec, m.points[0].time_from_start.nanosec) == (0, 200_000_000)
            wait_for(lambda: groups or group.write_goal(0.3), 10, "a group command", interval=0.1)
            assert list(groups[0][1].data) == pytest.approx([0.2, 0.3])
            alive.clear()  # the joint states stop
            wait_for(lambda: _raises(traj.read_position, Disconnected), 5, "Disconnected", interval=0.05)
            with pytest.raises(Disconnected, match="no joint state on /robot/joint_states"):
                traj.read_position()
        finally:
            done.set()
            th.join(2)
            traj.shutdown()
            group.shutdown()


def _raises(f, exc) -> bool:
    try:
        f()
    except exc:
        return True
    return False
