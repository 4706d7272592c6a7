"""The recording format of `vergence record` / `vergence replay`: a msgpack stream of records.

A file is a plain concatenation of msgpack objects, so it can be appended to while it is written and read
back after a crash:

    {"format": "vergence-recording", "version": 1, "rig": "head", "t_start_ns": ...}   header, once
    [key, t_ns, payload]                 a sample put on `key`, received at t_ns (time.time_ns())
    [key, t_ns, payload, event]          anything else: event is "delete", "alive" or "dead" (liveliness)

key is the full Zenoh key (vergence/<rig>/...), payload the message bytes exactly as they travelled (a
messages.* map, or anything else: recording never decodes). The reader stops quietly at a truncated last
record (a recorder killed mid-write) and says so in Reader.truncated; a corrupt record in the middle is an
error that names the file and the byte offset.

A write that fails (a full disk, an I/O error) raises RecordingError naming the file and the error, and
leaves the file cut at the end of the last record it had flushed whole (Writer.durable): it replays up to
the failure, with no truncated tail. check() says whether the file is still the one being written (not
removed or replaced).
"""

from __future__ import annotations

import contextlib
import errno
import io
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass

import msgpack

__all__ = ["FORMAT", "VERSION", "Record", "RecordingError", "Writer", "Reader", "read", "EVENTS"]

FORMAT = "vergence-recording"
VERSION = 1
EVENTS = ("put", "delete", "alive", "dead")
MAX_RECORD = 64 * 1024 * 1024
FLUSH_BYTES = 64 * 1024  # a Writer flushes after this many bytes (or flush_every records): what a failure loses


class RecordingError(ValueError):
    """A file that is not a vergence recording, or a corrupt record; the message names file and offset."""


@dataclass(frozen=True)
class Record:
    """One recorded sample: its key, when it was received (ns since the epoch), its bytes, what it was."""

    key: str
    t_ns: int
    payload: bytes
    event: str = "put"

    def pack(self) -> bytes:
        item = [self.key, self.t_ns, self.payload]
        if self.event != "put":
            item.append(self.event)
        return msgpack.packb(item, use_bin_type=True)


class Writer:
    """Appends records to a file. Thread-compatible, not thread-safe: one writer thread (see record.py).
    count, bytes: records and bytes written (buffered included); durable: (records, bytes) flushed whole."""

    def __init__(self, path: str | os.PathLike, rig: str = "", t_start_ns: int | None = None,
                 flush_every: int = 64):
        self.path = os.fspath(path)
        try:
            self._f = open(self.path, "wb")
        except OSError as e:
            raise RecordingError(f"cannot write recording {self.path!r}: {e.strerror}; check the directory "
                                 f"exists and is writable") from None
        st = os.fstat(self._f.fileno())
        self._ident = (st.st_dev, st.st_ino)
        self.count = 0
        self.bytes = 0
        self.durable = (0, 0)
        self.error: str | None = None
        self._flush_every = max(1, flush_every)
        header = {"format": FORMAT, "version": VERSION, "rig": rig,
                  "t_start_ns": time.time_ns() if t_start_ns is None else t_start_ns}
        self._write(msgpack.packb(header, use_bin_type=True))
        self.flush()  # a failure at once still leaves a recording (an empty one)

    def _write(self, data: bytes) -> None:
        if self.error is not None:
            raise RecordingError(self.error)
        try:
            self._f.write(data)
        except OSError as e:
            self._failed(e)
        self.bytes += len(data)

    def write(self, key: str, t_ns: int, payload: bytes, event: str = "put") -> None:
        if event not in EVENTS:
            raise ValueError(f"event {event!r} is not one of {EVENTS}")
        self._write(Record(key, int(t_ns), bytes(payload), event).pack())
        self.count += 1
        if self.count % self._flush_every == 0 or self.bytes - self.durable[1] >= FLUSH_BYTES:
            self.flush()

    def flush(self) -> None:
        if self.error is not None:
            raise RecordingError(self.error)
        try:
            self._f.flush()
        except OSError as e:
            self._failed(e)
        self.durable = (self.count, self.bytes)

    def check(self) -> None:
        """RecordingError if the file was removed or replaced since it was opened (writes to it would be lost)."""
        if self.error is not None:
            raise RecordingError(self.error)
        try:
            st = os.stat(self.path)
            same = (st.st_dev, st.st_ino) == self._ident
        except OSError:
            same = False
        if not same:
            self._failed(None, "it was removed or replaced while recording")

    def _failed(self, e: OSError | None, what: str = "") -> None:
        """Stop writing for good: cut the file after its last record flushed whole, close it, raise."""
        if e is not None:
            code = errno.errorcode.get(e.errno or 0, "")
            what = f"{e.strerror or e}" + (f" ({code})" if code else "")
        self.error = f"cannot write recording {self.path!r}: {what}"
        fd = os.dup(self._f.fileno())
        try:
            with contextlib.suppress(OSError):
                self._f.close()  # tries to flush the buffer once more, and fails as the write did
            with contextlib.suppress(OSError):
                os.ftruncate(fd, self.durable[1])  # the bytes after the last whole flush: a correlation tail
        finally:
            os.close(fd)
        raise RecordingError(self.error)

    def close(self) -> None:
        if not self._f.closed:
            self.flush()
            self._f.close()

    def __enter__(self) -> "Writer":
        return self

    def __exit__(self, *exc) -> None:
        if self.error is None:
            self.close()


class Reader:
    """Iterates over the records of a file. header: the file's header map. truncated: True once iteration
    met an incomplete last record (it is skipped). Records are validated: a corrupt one raises
    RecordingError with its byte offset."""

    def __init__(self, path: str | os.PathLike):
        self.path = os.fspath(path)
        try:
            self._f = open(self.path, "rb")
        except OSError as e:
            raise RecordingError(f"cannot read recording {self.path!r}: {e.strerror}") from None
        self.size = os.fstat(self._f.fileno()).st_size
        self._u = msgpack.Unpacker(self._f, raw=False, strict_map_key=True, max_buffer_size=MAX_RECORD,
                                   read_size=1 << 16)
        self.truncated = False
        self.count = 0
        try:
            header = self._u.unpack()
        except msgpack.OutOfData:
            self._f.close()
            raise RecordingError(f"{self.path!r} is empty or truncated before its header: not a recording") \
                from None
        except Exception as e:
            self._f.close()
            raise RecordingError(f"{self.path!r} is not a vergence recording ({type(e).__name__})") from None
        if not isinstance(header, dict) or header.get("format") != FORMAT:
            self._f.close()
            raise RecordingError(f"{self.path!r} is not a vergence recording (no {FORMAT!r} header)")
        if header.get("version") != VERSION:
            self._f.close()
            raise RecordingError(f"{self.path!r} is recording format version {header.get('version')!r}; "
                                 f"this build reads version {VERSION}")
        self.header: dict = header

    def __iter__(self) -> Iterator[Record]:
        while True:
            offset = self._u.tell()
            try:
                item = self._u.unpack()
            except msgpack.OutOfData:
                # Clean end, or a record cut short by a recorder that was killed mid-write.
                self.truncated = offset < self.size
                return
            except Exception as e:
                raise RecordingError(f"{self.path!r}: corrupt record at byte {offset} "
                                     f"({type(e).__name__}: {e})") from None
            yield self._record(item, offset)

    def _record(self, item, offset: int) -> Record:
        ok = (isinstance(item, list) and len(item) in (3, 4) and isinstance(item[0], str)
              and isinstance(item[1], int) and not isinstance(item[1], bool)
              and isinstance(item[2], (bytes, bytearray)) and (len(item) == 3 or item[3] in EVENTS))
        if not ok:
            raise RecordingError(f"{self.path!r}: record at byte {offset} is not [key, t_ns, payload(, event)]")
        self.count += 1
        return Record(item[0], item[1], bytes(item[2]), item[3] if len(item) == 4 else "put")

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> "Reader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read(path: str | os.PathLike) -> tuple[dict, list[Record], bool]:
    """The whole file: (header, records, truncated)."""
    with Reader(path) as r:
        records = list(r)
        return r.header, records, r.truncated


def dumps(records: list[Record], rig: str = "", t_start_ns: int = 0) -> bytes:
    """A recording as bytes (for tests and tools)."""
    buf = io.BytesIO()
    buf.write(msgpack.packb({"format": FORMAT, "version": VERSION, "rig": rig, "t_start_ns": t_start_ns},
                            use_bin_type=True))
    for r in records:
        buf.write(r.pack())
    return buf.getvalue()
