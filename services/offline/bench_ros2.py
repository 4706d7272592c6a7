"""`vergence bench ros2 [--seconds S] [--size WxH] [--json]`: the latency the ROS 2 parts add, on this machine.

Real processes on 127.0.0.1 (a router, `vergence ros2`, one worker, a capture) and the benchmark's own rclpy
node, on a ROS domain of its own with localhost-only discovery:
- the bridge: a MotorState (t_ns = now) put on Zenoh every 10 ms reaches the benchmark's node as a JointState
  on /vergence/<rig>/joint_states; the same message's arrival at a plain Zenoh subscriber of the benchmark is
  the baseline, so bridge_added_ms = the two medians' difference (what rclpy, DDS and the bridge's Python
  add). The same for a converged decision -> fixation, and look_at -> Fixate (ROS publish -> Zenoh arrival).
- the ros2 source: a stereo pair (WxH, mono8) stamped now, published every 33 ms by the benchmark's node, to
  the frame on Zenoh (its arrival minus the newest stamp at or before the frame's capture time), against the
  sim source of the same size (the frame's arrival minus its capture time, right after the render): source
  added_ms = the two medians' difference (DDS transport of two images, their decoding and the pairing).
Each figure: p50 and p99 in ms.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np

from services.runtime.args import number
from services.ops.launch import Proc, free_port, stop_all, vergence, wait_for, wait_listening


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=number(0, 3600, lo_open=True), default=5.0,
                   help="length of each measurement (default 5 s)")
    p.add_argument("--size", default="640x480", metavar="WxH", help="the stereo pair's size (default 640x480)")
    p.add_argument("--json", action="store_true", help="one JSON object per figure")


def _ms(xs) -> dict:
    a = np.asarray(xs, dtype=np.float64) / 1e6
    if not a.size:
        return {"n": 0, "p50_ms": math.nan, "p99_ms": math.nan}
    return {"n": int(a.size), "p50_ms": float(np.percentile(a, 50)), "p99_ms": float(np.percentile(a, 99))}


class Bench:
    """The processes, the benchmark's Zenoh session and rclpy node."""

    def __init__(self, workdir: Path):
        import zenoh

        from vergence.ros2.node import RosNode

        from services.runtime import session

        self.dir, self.rig = workdir, f"b{uuid.uuid4().hex[:8]}"
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.procs: list[Proc] = []
        self.statuses: list = []  # the captures' status messages (vergence.wire.status.Status)
        router = self.spawn("router", ["router", "--listen", self.endpoint])
        wait_listening(self.endpoint, 30, router, logs=self.logs)
        self.z = zenoh.open(session.zenoh_config("client", [self.endpoint]))
        self.ros = RosNode(f"vergence_bench_{random.randint(0, 10**6)}")

    def spawn(self, name: str, args: list[str], member: bool = False) -> Proc:
        argv = vergence(*args) + (["--connect", self.endpoint, "--rig", self.rig] if member else [])
        p = Proc(name, argv, log=self.dir / f"{name}.log", append=True)
        self.procs.append(p)
        return p

    def logs(self) -> str:
        return "\n".join(p.tail(10) for p in self.procs)

    def key(self, suffix: str) -> str:
        from vergence.wire import keys

        return keys.prefix(self.rig) + suffix

    def close(self) -> None:
        self.ros.close()
        self.z.close()
        stop_all(self.procs[::-1])


def _bridge(b: Bench, seconds: float) -> list[dict]:
    """Zenoh -> ROS 2 (joint_states, fixation) and ROS 2 -> Zenoh (look_at), against plain Zenoh."""
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import JointState

    from vergence.wire.messages import Frame, MotorState, Decision

    lat: dict[str, list[int]] = {k: [] for k in ("zenoh", "joint_states", "fixation", "look_at")}
    stamp = lambda m: m.header.stamp.sec * 10**9 + m.header.stamp.nanosec  # noqa: E731
    n = b.ros.node
    n.create_subscription(JointState, f"/vergence/{b.rig}/joint_states",
                          lambda m: lat["joint_states"].append(time.time_ns() - stamp(m)), 100)
    n.create_subscription(PointStamped, f"/vergence/{b.rig}/fixation",
                          lambda m: lat["fixation"].append(time.time_ns() - stamp(m)), 100)
    look = n.create_publisher(PointStamped, f"/vergence/{b.rig}/look_at", 10)
    sub = b.z.declare_subscriber(b.key("motor_state"), lambda s: lat["zenoh"].append(
        time.time_ns() - MotorState.from_bytes(s.payload.to_bytes()).t_ns))
    sent = [0]
    sub_fix = b.z.declare_subscriber(b.key("fixate"), lambda s: lat["look_at"].append(time.time_ns() - sent[0]))
    bridge = b.spawn("ros2", ["ros2"], member=True)
    wait_for(lambda: look.get_subscription_count() > 0 and bridge.poll() is None, 60, "the bridge", logs=b.logs)
    frame = Frame(rig=b.rig, frame=1, t_capture_ns=time.time_ns(), pan_rad=0.0, width=64, height=48, x=32, y=24,
                  window=15, vsearch=0, focal_px=50.0, fovea=bytes(17 * 17), band=bytes(17 * 66)).to_bytes()
    end = time.monotonic() + seconds
    i = 0
    while time.monotonic() < end:
        b.z.put(b.key("frame"), frame)  # the master's view, for the fixation (the bridge keeps the latest)
        now = time.time_ns()
        b.z.put(b.key("motor_state"), MotorState(rig=b.rig, t_ns=now, pan_rad=0.0, goal_rad=0.0, min_rad=-1.0,
                                                  max_rad=1.0, status="ok").to_bytes())
        b.z.put(b.key("decision"), Decision(rig=b.rig, frame=i, t_capture_ns=now, t_reduced_ns=now, window=15, k=10,
                                           k_sub=10.0, v_shift=0, k_centre=10, direction=0, magnitude=0,
                                           offset_px=0.0, confidence=1.0, confident=True, texture=1.0,
                                           pan_rad=0.0, x=32, y=24, converged=True, depth_m=1.0,
                                           depth_sigma_m=0.01).to_bytes())
        if i % 10 == 0:  # look_at at 10 Hz (the bridge passes 20 a second)
            m = PointStamped()
            m.point.z = 1.0
            sent[0] = time.time_ns()
            look.publish(m)
        i += 1
        time.sleep(0.01)  # (the rate of the measurement: 100 Hz)
    time.sleep(0.2)  # (the last ones in flight)
    sub.undeclare()
    sub_fix.undeclare()
    base = _ms(lat["zenoh"])
    out = [dict(figure="zenoh MotorState (baseline)", **base)]
    for k in ("joint_states", "fixation"):
        r = _ms(lat[k])
        out.append(dict(figure=f"bridge {k}", **r, added_ms=r["p50_ms"] - base["p50_ms"]))
    out.append(dict(figure="bridge look_at -> Fixate", **_ms(lat["look_at"])))
    return out


def _frames(b: Bench, source: list[str], seconds: float, stamps=None) -> list[int]:
    """Latency of the frames a capture publishes: arrival minus the exposure (the newest pair stamp at or before
    the frame's capture time when stamps is given, else the frame's capture time)."""
    from vergence.wire.messages import Frame
    from vergence.wire.status import decode_status

    got: list[tuple[int, int]] = []
    sub = b.z.declare_subscriber(b.key("frame"), lambda s: got.append(
        (time.time_ns(), Frame.from_bytes(s.payload.to_bytes()).t_capture_ns)))
    status = b.z.declare_subscriber(b.key("status/capture/*"), lambda s: b.statuses.append(decode_status(
        s.payload.to_bytes())))
    cap = b.spawn(f"capture-{len(b.procs)}", ["capture", "--rate", "0", "--source"] + source, member=True)
    b.last_capture = cap
    wait_for(lambda: len(got) >= 10 or cap.poll() is not None, 90, "frames", logs=b.logs)
    if cap.poll() is not None:
        raise RuntimeError(f"the capture exited with {cap.returncode}:\n{b.logs()}")
    n0 = len(got)
    time.sleep(seconds)  # (the length of the measurement)
    cap.stop()
    sub.undeclare()
    status.undeclare()
    out = []
    for arrival, t_cap in got[n0:]:
        if stamps is None:
            out.append(arrival - t_cap)
        else:
            before = [s for s in stamps[-200:] if s <= t_cap]
            if before:
                out.append(arrival - max(before))
    return out


def _source(b: Bench, seconds: float, size: tuple[int, int]) -> list[dict]:
    from sensor_msgs.msg import Image

    w, h = size
    b.spawn("worker", ["worker", "--name", "bench"], member=True)  # frames are published only with a worker
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (h, w), np.uint8).tobytes()
    pubs = [b.ros.node.create_publisher(Image, f"/bench/{side}/image_raw", 10) for side in ("left", "right")]
    stamps: list[int] = []
    stop = threading.Event()

    def camera():
        while not stop.wait(1 / 30):
            t = time.time_ns()
            for pub in pubs:
                m = Image(height=h, width=w, encoding="mono8", step=w, data=img)
                m.header.stamp.sec, m.header.stamp.nanosec = divmod(t, 10**9)
                pub.publish(m)
            stamps.append(t)

    th = threading.Thread(target=camera, daemon=True)
    th.start()
    try:
        ros = _frames(b, ["ros2:/bench/left/image_raw,/bench/right/image_raw"], seconds, stamps)
    finally:
        stop.set()
        th.join(2)
    published = len(stamps)
    sim = _frames(b, [f"sim:size={w}x{h}", "--rate", "30"], seconds)
    r, s = _ms(ros), _ms(sim)
    return [dict(figure=f"sim source, exposure -> frame on Zenoh ({w}x{h})", **s),
            dict(figure=f"ros2 source, exposure -> frame on Zenoh ({w}x{h})", **r, added_ms=r["p50_ms"] - s["p50_ms"],
                 pairs_published=published, source=next((st.get("source") for st in reversed(b.statuses)
                                                          if st.get("source") is not None), None))]


def run(args: argparse.Namespace) -> int:
    import logging

    logging.basicConfig(level=logging.WARNING)
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        print(f"vergence bench ros2: --size {args.size!r}: want WxH", flush=True)
        return 2
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    with tempfile.TemporaryDirectory(prefix="vergence-bench-ros2-") as tmp:
        b = Bench(Path(tmp))
        try:
            rows = _bridge(b, args.seconds) + _source(b, args.seconds, (w, h))
        finally:
            b.close()
    for r in rows:
        if args.json:
            print(json.dumps(r), flush=True)
        else:
            added = f"  added {r['added_ms']:+.2f} ms" if "added_ms" in r else ""
            print(f"{r['figure']:52s} n={r['n']:5d}  p50 {r['p50_ms']:7.2f} ms  p99 {r['p99_ms']:7.2f} ms{added}",
                  flush=True)
    return 0
