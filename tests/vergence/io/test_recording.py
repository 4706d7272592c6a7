"""The recording format: round trip, truncated last record, corrupt and foreign files (no Zenoh)."""

from __future__ import annotations

import errno
import os

import msgpack
import pytest

from vergence.io import recording as rec


def records(n: int = 20) -> list[rec.Record]:
    out = [rec.Record(f"vergence/head/{'frame' if i % 2 else 'profile'}", 1_000 + i, bytes([i]) * (i * 37))
           for i in range(n)]
    out.append(rec.Record("vergence/head/alive/worker/h-1", 5_000, b"", "alive"))
    out.append(rec.Record("vergence/head/alive/worker/h-1", 6_000, b"", "dead"))
    return out


def test_round_trip(tmp_path):
    path = tmp_path / "r.vrec"
    with rec.Writer(path, rig="head", t_start_ns=42, flush_every=3) as w:
        for r in records():
            w.write(r.key, r.t_ns, r.payload, r.event)
    assert w.count == 22 and w.bytes == path.stat().st_size
    header, got, truncated = rec.read(path)
    assert header == {"format": "vergence-recording", "version": 1, "rig": "head", "t_start_ns": 42}
    assert got == records() and not truncated
    assert path.read_bytes() == rec.dumps(records(), rig="head", t_start_ns=42)


@pytest.mark.parametrize("cut", [1, 5, 100, 700], ids=["1B", "5B", "100B", "700B"])
def test_truncated_last_record_is_skipped(tmp_path, cut):
    data = rec.dumps(records(), "head")
    last = len(records()[-1].pack())
    path = tmp_path / "cut.vrec"
    # cut inside the last records: every complete record is still read
    path.write_bytes(data[:-cut])
    header, got, truncated = rec.read(path)
    assert truncated
    whole = records()
    assert got == whole[:len(got)]
    assert len(got) == (21 if cut < last else len(got))
    assert len(got) >= 18


def test_not_a_recording(tmp_path):
    p = tmp_path / "x.bin"
    p.write_bytes(msgpack.packb({"hello": 1}))
    with pytest.raises(rec.RecordingError, match="not a vergence recording"):
        rec.read(p)
    p.write_bytes(b"")
    with pytest.raises(rec.RecordingError, match="empty or truncated"):
        rec.read(p)
    p.write_bytes(msgpack.packb({"format": "vergence-recording", "version": 9}))
    with pytest.raises(rec.RecordingError, match="version 9"):
        rec.read(p)
    with pytest.raises(rec.RecordingError, match="cannot read recording"):
        rec.read(tmp_path / "missing.vrec")
    with pytest.raises(rec.RecordingError, match="cannot write recording"):
        rec.Writer(tmp_path / "no" / "dir.vrec")


def test_corrupt_record_names_offset(tmp_path):
    good = rec.dumps(records(2), "head")
    p = tmp_path / "bad.vrec"
    p.write_bytes(good + msgpack.packb(["vergence/head/frame", "not a time", b""]) + good[-20:])
    with pytest.raises(rec.RecordingError, match=f"record at byte {len(good)}"):
        rec.read(p)


def test_a_failed_write_names_the_file_and_the_error_and_stops_the_writer():
    """/dev/full: every write fails with ENOSPC, as on a full disk (issue #29)."""
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full on this system")
    with pytest.raises(rec.RecordingError, match=r"cannot write recording '/dev/full': No space left on device "
                                                 r"\(ENOSPC\)"):
        rec.Writer("/dev/full", rig="head")  # its header is flushed at once


def test_a_failed_write_cuts_the_file_after_its_last_whole_flush(tmp_path, monkeypatch):
    """The bytes after the last flush are a correlation tail: the file is cut to the last whole record, and
    replays without a truncated end."""
    p = tmp_path / "cut.vrec"
    w = rec.Writer(p, rig="head", flush_every=1000)
    for i in range(5):
        w.write("vergence/head/frame", i, b"y" * 10)
    w.flush()
    assert w.durable == (5, p.stat().st_size)
    w.write("vergence/head/frame", 5, b"z" * 5000)
    real = w._f

    class Full:  # the file as on a full disk: a write reaches it in part, then ENOSPC
        closed = False

        def write(self, data):
            real.write(data[: len(data) // 2])
            real.flush()
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        flush = close = lambda self: None

        def fileno(self):
            return real.fileno()

    w._f = Full()
    with pytest.raises(rec.RecordingError, match="No space left on device"):
        w.write("vergence/head/frame", 6, b"w" * 9000)
    real.close()
    header, got, truncated = rec.read(p)
    assert [r.t_ns for r in got] == [0, 1, 2, 3, 4] and not truncated


def test_a_removed_file_is_a_failure(tmp_path):
    p = tmp_path / "gone.vrec"
    w = rec.Writer(p, rig="head")
    w.check()
    p.unlink()
    with pytest.raises(rec.RecordingError, match=f"cannot write recording '{p}': it was removed or replaced"):
        w.check()
