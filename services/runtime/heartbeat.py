"""Liveness by heartbeat: how `vergence up` tells a hung child from a busy one (issue #29).

Every child of `vergence up` gets the write end of a pipe (ENV = "FD,STALL_S"); `services.ops.cli`
starts beat() first thing, before any heavy import: a daemon thread that writes one byte every BEAT_S. It
does nothing else, so no work of the process starves it: a long numba compile at start, a heavy frame or a
slow disk leave it beating (Python switches threads every 5 ms, and numba's compiler, like every C call
through ctypes, releases the GIL). What stops it is what stops the whole process: SIGSTOP, a debugger, a
machine out of memory swapping it out; up takes a silence longer than [supervise] heartbeat_s for death
(services/ops/up.py).

A process whose status loop (Node.status, the actuator's serve loop) stopped turning while the process
itself runs (a deadlock, a blocking call that never returns) is hung too: once the loop has called
progress() a first time, the thread beats only while the latest call is younger than STALL_S (0: never
checked). Before the first call (imports, compiling, connecting, a standby waiting its turn) it beats
unconditionally: that is the start-up, which [supervise] start_grace_s bounds only until the first beat.

Nothing here imports more than the standard library's basics: it runs before everything else.
"""

from __future__ import annotations

import os
import threading
import time

ENV = "VERGENCE_HEARTBEAT"
BEAT_S = 0.1  # one byte this often (a pipe holds 64 KiB: 1.8 h of beats up does not read)

_last = [0.0]  # time.monotonic() of the latest progress(); 0: none yet


def progress() -> None:
    """The process's own loop turned: keep beating (a no-op outside `vergence up`)."""
    _last[0] = time.monotonic()


def beating(stall_s: float, now: float) -> bool:
    """Whether to beat now: always before the first progress(), else while it is younger than stall_s."""
    return stall_s <= 0 or _last[0] == 0.0 or now - _last[0] < stall_s


def _run(fd: int, stall_s: float) -> None:
    wait = threading.Event().wait
    while True:
        if beating(stall_s, time.monotonic()):
            try:
                os.write(fd, b"h")
            except BlockingIOError:  # up does not read (it is busy or hung itself): the beat is dropped
                pass
            except OSError:  # up is gone
                os.close(fd)
                return
        wait(BEAT_S)


def start() -> bool:
    """Start beating if ENV says where (and take it out of the environment: what this process starts is
    not up's child). False outside `vergence up`."""
    spec = os.environ.pop(ENV, None)
    if not spec:
        return False
    fd_text, _, stall_text = spec.partition(",")
    fd = int(fd_text)
    os.set_inheritable(fd, False)
    os.set_blocking(fd, False)
    threading.Thread(target=_run, args=(fd, float(stall_text or 0)), name="heartbeat", daemon=True).start()
    return True
