"""Record a running pipeline, then replay its frames through new workers and a new reducer: the profiles
are the recorded ones, bit for bit (real processes, a real router, bounded waits)."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import time

import pytest

from procs import Procs, gives_up_without_a_router, textured_pair, wait_for
from vergence.wire.messages import Frame, Profile
from vergence.io.recording import Writer, read

pytestmark = pytest.mark.slow  # every test here runs real processes

FRAMES = 20


@pytest.fixture
def pair(tmp_path):
    cfg = tmp_path / "settings.toml"
    cfg.write_text("[network]\nmax_window = 0\n[capture]\npreview_hz = 0\n[reducer]\ndeadline_ms = 1000\n")
    return textured_pair(tmp_path, seed=5), str(cfg)


def test_record_then_replay_gives_the_same_profiles(tmp_path, pair):
    source, cfg = pair
    path = tmp_path / "run.vrec"
    with Procs(tmp_path) as P:
        P.router()
        first = [P.start("worker-a", "worker", "--config", cfg), P.start("worker-b", "worker", "--config", cfg),
                 P.start("reducer", "reducer", "--config", cfg)]
        s = P.session()
        P.wait_alive(s, "worker", 2)
        P.wait_alive(s, "reducer", 1)
        rec = P.start("record", "record", str(path), "--duration", "30")
        P.wait_alive(s, "record", 1)
        wait_for(lambda: "recording vergence/" in rec.text(), 15, "the recorder's subscription", logs=P.logs)
        seen = P.collect(s, P.key("profile"))
        cap = P.start("capture", "capture", "--source", source, "--rate", "20", "--frames", str(FRAMES),
                      "--config", cfg)
        assert cap.wait(20) == 0, cap.tail()
        # the profiles here too (as the recorder gets them), then SIGINT ends the recording: exit 0, the file whole
        wait_for(lambda: len(seen) >= FRAMES - 2, 10, "the run's profiles", logs=P.logs)
        assert rec.stop() == 0, rec.tail()
        header, records, truncated = read(path)
        assert header["rig"] == P.rig and not truncated
        frames = [Frame.from_bytes(r.payload) for r in records if r.key == P.key("frame")]
        recorded = {p.frame: p for p in (Profile.from_bytes(r.payload) for r in records
                                         if r.key == P.key("profile"))}
        # the reducer encodes profiles only once it knows of a subscriber (the recorder): the routes can take a
        # few frames to reach it on a loaded machine
        assert len(frames) >= FRAMES - 2 and len(recorded) >= FRAMES // 2
        old_workers = {w for f in frames for w, _, _ in f.plan}
        for p in first:
            p.stop()

        # a new run: only router + workers + reducer, fed by the replay
        # three workers where two recorded: another partition of k, the same layer 4
        [P.start("worker-c", "worker", "--config", cfg), P.start("worker-d", "worker", "--config", cfg),
         P.start("worker-e", "worker", "--config", cfg), P.start("reducer2", "reducer", "--config", cfg)]
        new_workers = set(P.wait_alive(s, "worker", 3))
        assert not new_workers & old_workers
        P.wait_alive(s, "reducer", 1)
        again = P.collect(s, P.key("profile"))
        rep = P.start("replay", "replay", str(path), "--only", "frame", "--speed", "0.5")
        assert rep.wait(20) == 0, rep.tail()
        again.wait(len(recorded) - 2, 10)
        replayed = {p.frame: p for p in (Profile.from_bytes(b) for _, b, _ in again.snapshot())}
        common = sorted(set(replayed) & set(recorded))
        assert len(common) >= len(recorded) - 2
        for fid in common:
            a, b = recorded[fid], replayed[fid]
            assert a.scores == b.scores, f"frame {fid}: layer 4 differs"
            assert (a.k, a.k_sub, a.v_shift, a.direction, a.magnitude, a.confidence, a.confident) == \
                (b.k, b.k_sub, b.v_shift, b.direction, b.magnitude, b.confidence, b.confident)
            assert set(b.workers) <= new_workers and len(b.workers) == 3


PAYLOAD = bytes(50_000)  # a frame-sized message
PACE_S = 0.005  # the publisher's pace, 200 messages (10 MB) a second: what the recorder is given to write


def _publish_while(pub, cond, timeout: float) -> None:
    """Put PAYLOAD every PACE_S while cond() holds, at most timeout s (the pace is the load under test)."""
    deadline = time.monotonic() + timeout
    while cond() and time.monotonic() < deadline:
        pub.put(PAYLOAD)
        time.sleep(PACE_S)


def test_record_on_a_full_filesystem_stops_within_1_s_and_the_file_replays(tmp_path, tiny_fs):
    """`vergence record` into a 1 MiB tmpfs (issue #29): exit status 1 within 1 s of the disk filling, one
    line naming the file and the error, RSS flat meanwhile, and the file replays up to the failure (no
    truncated tail). Needs root to mount the tmpfs."""
    mnt = tiny_fs
    path = mnt / "run.vrec"
    with Procs(tmp_path) as P:
        P.router()
        s = P.session()
        rec = P.start("record", "record", str(path))
        P.wait_alive(s, "record", 1)
        pub = s.declare_publisher(P.key("frame"))
        full: list[float] = []
        rss: list[int] = []

        def running() -> bool:
            st = os.statvfs(mnt)
            if not full and st.f_bavail * st.f_frsize < 64 * 1024:
                full.append(time.monotonic())
            with contextlib.suppress(Exception):
                rss.append(rec.rss_bytes() or rss[-1])  # 0 once it exits
            return rec.alive()

        _publish_while(pub, running, 30)
        t_exit = time.monotonic()
        assert rec.wait(5) == 1, rec.tail()
        err = [line for line in rec.text().splitlines() if line.startswith("vergence record:")]
        print(err, f"; exit {t_exit - full[0]:.3f} s after the disk filled; RSS "
                   f"{min(rss) / 2**20:.1f}..{max(rss) / 2**20:.1f} MB")
        assert len(err) == 1 and f"cannot write recording '{path}': No space left on device (ENOSPC)" in err[0]
        assert t_exit - full[0] < 1.0
        assert max(rss) - min(rss) < 20 * 2**20
        n = int(re.search(r"the file holds the first (\d+) messages", err[0])[1])
        header, records, truncated = read(path)
        assert len(records) == n > 5 and not truncated
        assert all(r.payload == PAYLOAD for r in records if r.key.endswith("/frame"))


def test_record_into_a_slow_disk_drops_what_does_not_fit_and_stays_bounded(tmp_path):
    """A FIFO that the test does not read for 3 s is a disk that stops: the writer blocks, the queue holds at
    most --queue-mb (4 MB), the rest is dropped and counted; RSS flat; once the FIFO is read again the
    recording completes with every message it kept."""
    fifo = tmp_path / "slow.vrec"
    os.mkfifo(fifo)
    rfd = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)  # a reader exists: the recorder's open does not block
    with Procs(tmp_path) as P:
        P.router()
        s = P.session()
        rec = P.start("record", "record", str(fifo), "--queue-mb", "4")
        P.wait_alive(s, "record", 1)
        pub = s.declare_publisher(P.key("frame"))
        rss: list[int] = []
        t_end = time.monotonic() + 3.0
        _publish_while(pub, lambda: rss.append(rec.rss_bytes()) or time.monotonic() < t_end, 10)
        rec.signal(signal.SIGINT)
        got = bytearray()
        os.set_blocking(rfd, True)
        while chunk := os.read(rfd, 1 << 20):  # the disk is back: read all of it, to the recorder's close
            got += chunk
        os.close(rfd)
        assert rec.wait(20) == 0, rec.tail()
        line = [x for x in rec.text().splitlines() if x.startswith("vergence record:")][-1]
        print(line, f"; RSS {min(rss) / 2**20:.1f}..{max(rss) / 2**20:.1f} MB")
        m = re.search(r"(\d+) messages, .*; (\d+) dropped \(([\d.]+) MB: the disk fell behind by 4 MB\)", line)
        assert m, line
        kept, dropped = int(m[1]), int(m[2])
        assert dropped > 200 and kept < 600 - dropped + 50  # ~600 sent in 3 s: most could not wait
        assert max(rss) - min(rss) < 30 * 2**20  # the 4 MB queue, not the 30 MB sent
        out = tmp_path / "copy.vrec"
        out.write_bytes(bytes(got))
        header, records, truncated = read(out)
        assert len(records) == kept and not truncated


def test_replay_without_a_router_gives_up_within_its_wait(tmp_path):
    """Issue #28: it kept trying forever; now --wait (default 5 s) bounds the wait for a router."""
    path = tmp_path / "empty.vrec"
    Writer(path, rig="head").close()
    gives_up_without_a_router("replay", str(path), "--wait", "1", within=1)
