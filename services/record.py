"""`vergence record FILE [--duration S]`: every vergence/<rig>/** message, with its key and arrival time, into a
msgpack stream (the format of vergence.recording); FILE.mcap: a ROS 2 MCAP file (vergence.mcap_file: the
rig's messages as the standard ROS 2 messages of `vergence ros2`, and every sample raw for `vergence replay`).

A zenoh callback stamps each sample (time.time_ns()) and hands it to a queue; one writer thread appends
the records, so the network threads never wait on the disk. Liveliness tokens vergence/<rig>/alive/** are
recorded too, as "alive"/"dead" events (empty payload). Note that subscribing to vergence/<rig>/** also
subscribes to the profiles, so the reducer publishes them while the recorder runs. Stops after --duration
seconds, or on SIGINT/SIGTERM; the file is complete either way (a killed recorder leaves at worst a
truncated last record, which readers skip).
"""

from __future__ import annotations

import argparse
import logging
import queue
import sys
import threading
import time

import zenoh

from vergence import keys
from vergence.config import load
from vergence.mcap_file import McapWriter, is_mcap
from vergence.recording import RecordingError, Writer

from . import session

log = logging.getLogger("vergence.record")


def configure(p: argparse.ArgumentParser) -> None:
    session.add_options(p)
    p.add_argument("file", metavar="FILE", help="the recording to write (overwritten)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds (default: Ctrl-C)")


def main(rig: str, conf: zenoh.Config, stop: session.Stop, path: str, duration: float | None = None) -> int:
    try:  # FILE.mcap: a ROS 2 MCAP file (vergence.mcap_file; the [ros2] extra), else vergence's own format
        writer = McapWriter(path, rig=rig) if is_mcap(path) else Writer(path, rig=rig)
    except RecordingError as e:
        print(f"vergence record: {e}", file=sys.stderr)
        return 2
    q: queue.SimpleQueue = queue.SimpleQueue()
    done = object()

    def on_sample(sample) -> None:
        event = "put" if sample.kind == zenoh.SampleKind.PUT else "delete"
        q.put((str(sample.key_expr), time.time_ns(), sample.payload.to_bytes(), event))

    def on_alive(sample) -> None:
        event = "alive" if sample.kind == zenoh.SampleKind.PUT else "dead"
        q.put((str(sample.key_expr), time.time_ns(), b"", event))

    def write_loop() -> None:
        while True:
            item = q.get()
            if item is done:
                return
            writer.write(*item)

    th = threading.Thread(target=write_loop, name="record-writer", daemon=True)
    th.start()
    t0 = time.monotonic()
    key = keys.everything(rig)
    try:
        with session.open_session(conf) as s:
            subs = [s.declare_subscriber(key, on_sample),
                    s.liveliness().declare_subscriber(keys.alives(rig), on_alive, history=True)]
            # a token says the recorder listens (tests and tools wait for it before starting a capture)
            token = s.liveliness().declare_token(session.alive_key(rig, "record"))
            log.info("recording %s into %s", key, path)
            stop.wait(duration)
            token.undeclare()
            for sub in subs:
                sub.undeclare()
    finally:
        q.put(done)
        th.join(10.0)
        writer.close()
    secs = time.monotonic() - t0
    print(f"vergence record: {writer.count} messages, {writer.bytes / 1e6:.1f} MB in {secs:.1f} s into {path}",
          file=sys.stderr)
    return 0


def run(args: argparse.Namespace) -> int:
    settings = load(args.config)
    stop = session.Stop()
    return main(args.rig or settings.rig, session.config_from_args(args), stop, args.file, args.duration)
