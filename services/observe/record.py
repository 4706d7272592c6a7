"""`vergence record FILE [--duration S] [--queue-mb MB]`: every vergence/<rig>/** message, with its key and
arrival time, into a msgpack stream (the format of vergence.io.recording); FILE.mcap: a ROS 2 MCAP file
(vergence.io.mcap_file: the rig's messages as the standard ROS 2 messages of `vergence ros2`, and every sample raw
for `vergence replay`).

A zenoh callback stamps each sample (time.time_ns()) and hands it to a queue; one writer thread appends
the records, so the network threads never wait on the disk. The queue is bounded (--queue-mb of payload,
32 MB): what arrives while it is full is dropped, counted and reported at the end, so a slow disk never
grows the recorder's memory. Liveliness tokens vergence/<rig>/alive/** are recorded too, as "alive"/"dead"
events (empty payload). Note that subscribing to vergence/<rig>/** also subscribes to the profiles, so the
reducer publishes them while the recorder runs. Stops after --duration seconds, or on SIGINT/SIGTERM; the
file is complete either way (a killed recorder leaves at worst a truncated last record, which readers skip).

The file is created once a router answered: with none within --wait (default session.CLIENT_WAIT_S) or
--duration, whichever is shorter, it exits 1 with one line and writes no file (an existing one stays as it
was). --duration counts from the start, the wait for the router included.

A write that fails (a full disk, an I/O error) or a file removed or replaced under the recorder stops it at
once: one line names the file and the error, the exit status is 1, and the file ends with the last record
flushed whole (it replays up to the failure). The writer flushes at least every FLUSH_S and checks the file
is still there every CHECK_S.
"""

from __future__ import annotations

import argparse
import collections
import logging
import sys
import threading
import time

import zenoh

from vergence.wire import keys
from vergence.config import load
from vergence.io.mcap_file import McapWriter, is_mcap
from vergence.io.recording import RecordingError, Writer

from services.runtime import session
from services.runtime.args import number
from services.runtime.node import Node

log = logging.getLogger("vergence.record")
QUEUE_MB = 32.0  # the default bound of the queue between the subscribers and the writer, in MB of payload
FLUSH_S = 0.25  # the writer flushes at least this often (what a failure can lose)
CHECK_S = 0.5  # ... and checks that its file is still there this often


def configure(p: argparse.ArgumentParser) -> None:
    session.add_options(p)
    p.add_argument("file", metavar="FILE", help="the recording to write (overwritten)")
    p.add_argument("--duration", type=number(0, None, lo_open=True), default=None, metavar="S",
                   help="stop S seconds after the start, the wait for a router included (default: Ctrl-C)")
    session.add_wait(p)
    p.add_argument("--queue-mb", type=number(0, 100_000, lo_open=True), default=QUEUE_MB, metavar="MB",
                   help=f"the most payload waiting for the disk; more is dropped and counted (default {QUEUE_MB:g})")


class Bounded:
    """A FIFO of (key, t_ns, payload, event) holding at most `limit` bytes of payload: put() drops (and counts)
    what does not fit; get() waits up to a timeout."""

    def __init__(self, limit: int):
        self.limit = limit
        self.items: collections.deque = collections.deque()
        self.size = 0
        self.dropped = 0
        self.dropped_bytes = 0
        self.cond = threading.Condition()

    def put(self, item) -> None:
        n = len(item[2]) + len(item[0])
        with self.cond:
            if self.items and self.size + n > self.limit:
                self.dropped += 1
                self.dropped_bytes += n
                return
            self.items.append(item)
            self.size += n
            self.cond.notify()

    def get(self, timeout: float):
        """The oldest item, or None after `timeout` s."""
        with self.cond:
            if not self.items and not self.cond.wait(timeout):
                return None
            if not self.items:
                return None
            item = self.items.popleft()
            self.size -= len(item[2]) + len(item[0])
            return item


def write_loop(writer: Writer, q: Bounded, done: threading.Event, failed: list[str], stop: session.Stop) -> None:
    """Append what comes until done is set and the queue is empty; on a write error, note it and set stop."""
    flushed = checked = time.monotonic()
    try:
        while True:
            item = q.get(FLUSH_S)
            now = time.monotonic()
            if item is not None:
                writer.write(*item)
            elif done.is_set():
                return
            if now - flushed >= FLUSH_S:
                writer.flush()
                flushed = now
            if now - checked >= CHECK_S:
                writer.check()
                checked = now
    except RecordingError as e:
        failed.append(str(e))
        stop.set()


def main(rig: str, conf: zenoh.Config, stop: session.Stop, path: str, duration: float | None = None,
         queue_mb: float = QUEUE_MB, wait: float = session.CLIENT_WAIT_S) -> int:
    t0 = time.monotonic()
    end = t0 + duration if duration is not None else None
    q = Bounded(int(queue_mb * 1e6))
    failed: list[str] = []

    def on_sample(sample) -> None:
        event = "put" if sample.kind == zenoh.SampleKind.PUT else "delete"
        q.put((str(sample.key_expr), time.time_ns(), sample.payload.to_bytes(), event))

    def on_alive(sample) -> None:
        event = "alive" if sample.kind == zenoh.SampleKind.PUT else "dead"
        q.put((str(sample.key_expr), time.time_ns(), b"", event))

    key = keys.everything(rig)
    done = threading.Event()
    writer = th = None
    try:
        # the node undeclares the token, then the subscriptions, at exit; it publishes no status while recording
        # (the file would hold the recorder's own), only its last one, once the subscriptions are gone. No router
        # within the wait: session.NoRouter (one line, exit 1: services/ops/cli.py), and no file was created
        with Node("record", rig, conf, stop, log=log, timeout=wait if end is None else min(wait, duration)) as node:
            try:
                # FILE.mcap: a ROS 2 MCAP file (vergence.io.mcap_file; the [ros2] extra), else vergence's own format
                writer = McapWriter(path, rig=rig) if is_mcap(path) else Writer(path, rig=rig)
            except RecordingError as e:
                print(f"vergence record: {e}", file=sys.stderr)
                return 2
            th = threading.Thread(target=write_loop, args=(writer, q, done, failed, stop), name="record-writer",
                                  daemon=True)
            th.start()
            node.subscriber(key, on_sample)
            node.liveliness_subscriber(keys.alives(rig), on_alive, history=True)
            # a token says the recorder listens (tests and tools wait for it before starting a capture)
            node.ready()
            log.info("recording %s into %s", key, path)
            stop.wait(None if end is None else max(0.0, end - time.monotonic()))
    finally:
        if th is not None:
            done.set()
            th.join(10.0)
            if not failed:
                try:
                    writer.close()
                except RecordingError as e:
                    failed.append(str(e))
    return _report(writer, q, failed, path, time.monotonic() - t0, queue_mb)


def _report(writer, q: Bounded, failed: list[str], path: str, secs: float, queue_mb: float) -> int:
    drops = f"; {q.dropped} dropped ({q.dropped_bytes / 1e6:.1f} MB: the disk fell behind by {queue_mb:g} MB)" \
        if q.dropped else ""
    if failed:
        n, size = writer.durable
        print(f"vergence record: {failed[0]}; stopped after {secs:.1f} s, the file holds the first {n} messages "
              f"({size / 1e6:.1f} MB), whole{drops}", file=sys.stderr)
        return 1
    print(f"vergence record: {writer.count} messages, {writer.bytes / 1e6:.1f} MB in {secs:.1f} s into {path}{drops}",
          file=sys.stderr)
    return 0


def run(args: argparse.Namespace) -> int:
    settings = load(args.config)
    stop = session.Stop()
    return main(args.rig or settings.rig, session.config_from_args(args), stop, args.file, args.duration,
                args.queue_mb, args.wait)
