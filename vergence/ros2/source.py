"""The capture's ROS 2 source: `ros2:LEFT_TOPIC,RIGHT_TOPIC[:slop=S][:wait=S][:skew=S]`.

An rclpy node (vergence.ros2.node) subscribes to the two image topics, sensor_msgs/msg/Image (mono8, bgr8,
rgb8, bgra8, rgba8, mono16) or sensor_msgs/msg/CompressedImage (jpeg, png), whichever each topic carries
(looked up in the ROS graph; a name ending in /compressed is taken as compressed while it is not there yet), with
sensor-data QoS (best effort: matches reliable and best-effort publishers). Images are paired by header.stamp
within `slop` seconds (default 0.005; vergence.ros2.convert.Pairer) and the stamps, the exposure times, are the pair's
`exposure_ns` (t_master_ns, t_slave_ns). The camera_info beside each image topic (<topic's namespace>/camera_info)
gives the focal length (k[0], fx) when it comes within `wait` s of the first pair, and each camera's principal point
(k[2], k[5]: `principal`, the frames carry it; issue #36); one outside the image is not taken (logged); and
each camera's lens distortion (d, distortion_model: `lenses`, vergence.io.lens; the capture removes it from the
rows a frame reads).

The master image's header.frame_id, the camera's name of its optical frame, is `frame_id` after each read (the
capture puts it in the Frame, the ROS 2 bridge publishes the fixation in it); one that is too long or not
printable ASCII without spaces is not taken (counted: bad_frame_id, and logged once; the image is used).

Refused images are counted (`counters`) and logged once per kind: an encoding it cannot use, undecodable
data, a stamp of 0 or more than `skew` s (default 2) off this machine's clock, a size other than the first
pair's (the message says the stream changed size: restart the capture to take the new size). A topic with
no publisher after `wait` s (default 10) at start is a SourceError naming it and the image topics the graph has.
read() hands out each pair once: it waits for a newer one up to STALL_S, then raises SourceStall (the capture
counts it and goes on), so a camera that stops does not stop the capture.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time

from . import convert as conv
from ..io.images import Source, SourceError
from ..spec import Key, SpecError, parse

__all__ = ["SourceStall", "Ros2Source", "parse_spec"]

log = logging.getLogger("vergence.ros2_source")
STALL_S = 1.0  # read() waits this long for a new pair, then SourceStall
QOS_DEPTH = 20  # images kept per topic until the node takes them
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"


class SourceStall(SourceError):
    """No new pair yet: not fatal (transient), the capture tries again."""

    transient = True


def parse_spec(rest: str) -> tuple[str, str, dict[str, float]]:
    """'LEFT,RIGHT[:key=value...]' -> (left topic, right topic, options); SourceError naming what is wrong."""
    topics, *opts = rest.split(":")
    parts = [p.strip() for p in topics.split(",")]
    if len(parts) != 2 or not all(parts):
        raise SourceError(f"source ros2:{rest!r}: want ros2:LEFT_TOPIC,RIGHT_TOPIC[:slop=S][:wait=S][:skew=S]")
    keys = [Key("slop", default=0.005, lo=0.0, unit="s"), Key("wait", default=10.0, lo=0.0, unit="s"),
            Key("skew", default=2.0, lo=0.0, unit="s")]
    try:
        out = parse(":".join(opts), keys, "source ros2")
    except SpecError as e:
        raise SourceError(str(e)) from None
    return parts[0], parts[1], out


def _info_topic(image_topic: str) -> str:
    base = image_topic.rstrip("/")
    if base.endswith("/compressed"):
        base = base[: -len("/compressed")]
    return base.rpartition("/")[0] + "/camera_info"


class Ros2Source(Source):
    """Stereo pairs from two ROS 2 image topics (see the module's docstring)."""

    follows_pan = True
    truth_pan_rad = None
    start_pan_rad = 0.0

    def __init__(self, rest: str, master: str = "left"):
        from .node import RosNode, RosUnavailable

        super().__init__(master)
        *self.topics, self.opts = parse_spec(rest)
        self.size: tuple[int, int] = (0, 0)
        self.focal_px = 0.0
        self.principal: tuple = ((-1.0, -1.0), (-1.0, -1.0))  # (master's, slave's) (cx, cy); -1: the centre
        self.exposure_ns: tuple[int, int] = (0, 0)
        self.frame_id = ""  # the master image's header.frame_id, once checked (conv.frame_id_problem); "": none
        self._frame_ids = ["", ""]  # the latest checked frame id of each topic
        self._raw_ids: list[str | None] = [None, None]  # the latest header.frame_id of each topic, as it came
        self.counters: dict[str, int] = {}
        self._logged: set[str] = set()
        self.cond = threading.Condition()
        self.pairer = conv.Pairer(int(self.opts["slop"] * conv.NS_PER_S))
        self.latest = None  # (t_left, left, t_right, right)
        self.served = -1  # the left stamp of the pair read() handed out last
        self.info: list = [None, None]
        self.ages: collections.deque = collections.deque(maxlen=300)  # ms from the later stamp to the pair
        try:
            self.ros = RosNode("vergence_source")
        except RosUnavailable as e:
            raise SourceError(f"ros2 source: {e}") from None
        try:
            self._subscribe()
            self._first_pair()
        except BaseException:
            self.ros.close()
            raise

    # -- setup -----------------------------------------------------------------------------------------------------

    def _types(self) -> dict[str, list[str]]:
        return dict(self.ros.node.get_topic_names_and_types())

    def _subscribe(self) -> None:
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image

        end = time.monotonic() + self.opts["wait"]
        kinds = [None, None]
        while None in kinds:
            graph = self._types()
            for i, topic in enumerate(self.topics):
                tps = graph.get(topic, [])
                if IMAGE in tps or COMPRESSED in tps:
                    kinds[i] = COMPRESSED if COMPRESSED in tps else IMAGE
                elif tps:
                    raise SourceError(f"ros2 source: topic {topic} carries {', '.join(tps)}, not {IMAGE} or "
                                      f"{COMPRESSED}")
            if None in kinds and time.monotonic() > end:
                missing = [t for t, k in zip(self.topics, kinds) if k is None]
                images = sorted(t for t, tps in graph.items() if IMAGE in tps or COMPRESSED in tps)
                raise SourceError(f"ros2 source: no publisher on {', '.join(missing)} after {self.opts['wait']:g} s "
                                  f"(image topics seen: {', '.join(images) or 'none'}; is the camera driver running, "
                                  "on this ROS_DOMAIN_ID?)")
            time.sleep(0.05)
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        n = self.ros.node
        # best effort (it matches reliable publishers too) with room for a burst: a capture starved of CPU for a
        # few frames still finds both images of a pair
        qos = QoSProfile(depth=QOS_DEPTH, reliability=ReliabilityPolicy.BEST_EFFORT)
        for i, (topic, kind) in enumerate(zip(self.topics, kinds)):
            tp = CompressedImage if kind == COMPRESSED else Image
            n.create_subscription(tp, topic, lambda m, i=i: self._on_image(i, m), qos)
            n.create_subscription(CameraInfo, _info_topic(topic), lambda m, i=i: self._on_info(i, m),
                                  self.ros.sensor_qos)
        log.info("ros2 source: %s (%s) and %s (%s), paired within %g s", self.topics[0], kinds[0], self.topics[1],
                 kinds[1], self.opts["slop"])

    def _first_pair(self) -> None:
        end = time.monotonic() + self.opts["wait"]
        with self.cond:
            if not self.cond.wait_for(lambda: self.latest is not None, self.opts["wait"]):
                raise SourceError(f"ros2 source: no pair of images within {self.opts['wait']:g} s from "
                                  f"{', '.join(self.topics)} (counted: {self.counters or 'nothing'})")
            self.cond.wait_for(lambda: all(self.info), max(0.0, min(1.0, end - time.monotonic())))
        # the master's camera_info first (the focal length of the frames is the master's), else the slave's
        usable = [i for i in (self.info[::-1] if self.swap else self.info)
                  if i is not None and math.isfinite(i.k[0]) and 0 < i.k[0] < 1e6]
        if usable:
            self.focal_px = float(usable[0].k[0])
            ordered = list(zip(self.info[::-1] if self.swap else self.info, ("master", "slave")))
            self.principal = tuple(self._principal(i, which) for i, which in ordered)
            lenses = tuple(self._lens(i, which) for i, which in ordered)
            self.lenses = lenses if any(ln is not None for ln in lenses) else None
        elif any(self.info):
            log.warning("ros2 source: camera_info without a usable focal length (k[0] = %s): the focal length comes "
                        "from the settings", [float(i.k[0]) for i in self.info if i is not None])
        else:
            log.info("ros2 source: no camera_info beside the image topics: the focal length comes from the settings")

    def _principal(self, info, which: str) -> tuple[float, float]:
        """(cx, cy) of a camera_info (k[2], k[5]), or (-1, -1) (the image centre) where there is none or it lies
        outside the image (logged)."""
        if info is None:
            return -1.0, -1.0
        cx, cy = float(info.k[2]), float(info.k[5])
        if not (0 <= cx <= self.size[0] and 0 <= cy <= self.size[1]):
            log.warning("ros2 source: the %s's camera_info has its principal point (%s, %s) outside the %d x %d "
                        "image: the image centre is taken", which, cx, cy, *self.size)
            return -1.0, -1.0
        return cx, cy

    def _lens(self, info, which: str):
        """The camera's vergence.io.lens.Lens of a camera_info with a distortion (None: none, or one that cannot be
        used: logged, and the images are taken as they are)."""
        from ..io.lens import Lens

        if info is None:
            return None
        try:
            lens = Lens.from_camera_info(info.k, info.d, info.distortion_model, self.size)
        except ValueError as e:
            log.warning("ros2 source: the %s's camera_info: %s; its images are taken as they are (no undistortion)",
                        which, e)
            return None
        return None if lens.is_pinhole else lens

    # -- callbacks (the rclpy thread) -------------------------------------------------------------------------------

    def _count(self, name: str) -> None:
        self.counters[name] = self.counters.get(name, 0) + 1

    def _reject(self, kind: str, why: str) -> None:
        self._count(f"bad_{kind}")
        if self.on_reject is not None:
            self.on_reject()
        if kind not in self._logged:
            self._logged.add(kind)
            log.warning("ros2 source: image refused (%s; further ones are only counted): %s", kind, why)

    def _on_info(self, i: int, msg) -> None:
        with self.cond:
            self.info[i] = msg
            self.cond.notify_all()

    def _on_image(self, i: int, msg) -> None:
        self._count("images")
        st = msg.header.stamp
        why = conv.stamp_problem(st.sec, st.nanosec, time.time_ns(), self.opts["skew"])
        if why is not None:
            return self._reject("stamp", f"{self.topics[i]}: {why}")
        try:
            if hasattr(msg, "encoding"):
                img = conv.image_gray(msg.encoding, msg.width, msg.height, msg.step, msg.data, msg.is_bigendian)
            else:
                img = conv.compressed_gray(msg.format, msg.data)
        except conv.ImageError as e:
            return self._reject("image", f"{self.topics[i]}: {e}")
        size = (img.shape[1], img.shape[0])
        fid = msg.header.frame_id
        if fid != self._raw_ids[i]:  # a camera names its frame once: checked when it changes
            self._raw_ids[i] = fid
            why = conv.frame_id_problem(fid) if fid else None
            if why is not None:
                self._count("bad_frame_id")
                if "frame_id" not in self._logged:
                    self._logged.add("frame_id")
                    log.warning("ros2 source: %s: the image's %s is not taken (the image is; further ones are only "
                                "counted): the bridge names the optical frame itself", self.topics[i], why)
            self._frame_ids[i] = "" if why else fid
        elif fid and not self._frame_ids[i]:
            self._count("bad_frame_id")  # the same refused frame id again: counted per image
        with self.cond:
            if self.size != (0, 0) and size != self.size:
                return self._reject("size", f"{self.topics[i]}: the stream changed size from {self.size[0]} x "
                                            f"{self.size[1]} to {size[0]} x {size[1]}; restart the capture to use it")
            got = self.pairer.add(i, conv.from_stamp(st.sec, st.nanosec), img)
            self.counters["unmatched"] = self.pairer.unmatched
            if got is None:
                return
            if got[1].shape != got[3].shape:
                return self._reject("size", f"left is {got[1].shape[1]} x {got[1].shape[0]}, right is "
                                            f"{got[3].shape[1]} x {got[3].shape[0]}")
            if self.size == (0, 0):
                self.size = size
            self.ages.append((time.time_ns() - max(got[0], got[2])) / 1e6)
            self.latest = got
            self._count("pairs")
            self.cond.notify_all()

    # -- the Source interface -----------------------------------------------------------------------------------

    def read(self, pan_rad: float = 0.0):
        """The newest pair not handed out yet (master, slave), its stamps in exposure_ns; SourceStall after STALL_S
        without one."""
        with self.cond:
            if not self.cond.wait_for(lambda: self.latest is not None and self.latest[0] != self.served, STALL_S):
                self._count("stalls")
                raise SourceStall(f"ros2 source: no new pair from {', '.join(self.topics)} in {STALL_S:g} s")
            tl, left, tr, right = self.latest
            self.served = tl
            self.frame_id = self._frame_ids[1 if self.swap else 0]
        self.exposure_ns = self._order(tl, tr)
        return self._order(left, right)

    def status(self) -> dict:
        """Counters for the capture's status: images, pairs, unmatched, stalls, bad_stamp, bad_image, bad_size,
        bad_frame_id (the image was used, its frame id not);
        pair_age_ms: the median and largest time from a pair's later exposure stamp to its pairing here (the
        camera driver's and the transport's latency) over the latest 300 pairs."""
        with self.cond:
            out = dict(self.counters)
            if self.ages:
                a = sorted(self.ages)
                out["pair_age_ms"] = {"p50": round(a[len(a) // 2], 3), "max": round(a[-1], 3)}
            return out

    def close(self) -> None:
        ros, self.ros = getattr(self, "ros", None), None
        if ros is not None:
            ros.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
