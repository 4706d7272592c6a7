"""Child processes, the one way `vergence up`, `vergence bench pipeline` and the tests (tests/procs.py) start
and stop them.

    p = Proc("worker", vergence("worker", "--connect", endpoint), log=Path("worker.log"))
    wait_for(lambda: "worker" in p.text(), 10, "the worker's first line", logs=p.tail)
    p.stop()        # SIGINT to its group; SIGTERM after `grace` s; SIGKILL after `term_grace` s more

Each child runs in a process group of its own (a Ctrl-C in the terminal reaches the parent only, which stops
its children in order; a stop reaches whatever the child started); optionally it gets SIGTERM when its
parent dies (Linux; when the thread that started it ends, in fact: PR_SET_PDEATHSIG). Its stdout and stderr go
to a log file, or to the parent's. CPU time and memory come from psutil. Every wait has a deadline.

Every Proc a process starts is in `live()` until it is stopped or found exited: a parent that is killed can end
them all (tests/reaper.py does, for a killed test run), since a signal to the parent's process group does not
reach their groups.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import psutil

__all__ = ["GRACE_S", "TERM_GRACE_S", "Proc", "accepts", "forget", "free_port", "live", "stop_all", "vergence",
           "wait_for", "wait_listening"]

GRACE_S = 5.0  # after SIGINT, the time a child has to exit by itself ...
TERM_GRACE_S = 2.0  # ... then after SIGTERM, before SIGKILL
SETTLE_S = 0.3  # wait_listening on a transport it cannot probe: the time the listener has to start

_LIVE: set[Proc] = set()  # the Procs this process started, until stopped or seen exited (no lock: a signal
#                           handler reads it in the thread it may interrupt; list(set) is atomic under the GIL)


def live() -> list[Proc]:
    """The Procs this process started that were not stopped, nor seen to have exited (poll, wait), yet."""
    return [p for p in list(_LIVE) if p.returncode is None]


def forget(p: Proc) -> None:
    """Take p out of live() (it has been stopped, or reaped by someone else)."""
    _LIVE.discard(p)


def vergence(*args: str) -> list[str]:
    """The argv of `vergence ARGS...` run by this interpreter (the command's own code, whatever PATH says)."""
    return [sys.executable, "-m", "services.ops.cli", *args]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nobody listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(cond, timeout: float, what: str = "condition", interval: float = 0.02, logs=None):
    """Poll cond() until it returns a true value (returned); TimeoutError after `timeout` seconds (its
    message ends with logs(), when given)."""
    end = time.monotonic() + timeout
    while True:
        v = cond()
        if v:
            return v
        if time.monotonic() > end:
            raise TimeoutError(f"timed out after {timeout} s waiting for {what}" + (f"\n{logs()}" if logs else ""))
        time.sleep(interval)


def accepts(endpoint: str) -> bool | None:
    """Whether something accepts TCP connections at a tcp/HOST:PORT endpoint (None: not a tcp endpoint)."""
    proto, _, addr = endpoint.partition("/")
    host, _, port = addr.rpartition(":")
    host = host.strip("[]")
    if proto != "tcp" or not port.isdigit():
        return None
    probe = {"0.0.0.0": "127.0.0.1", "": "127.0.0.1", "::": "::1"}.get(host, host)
    with socket.socket(socket.AF_INET6 if ":" in probe else socket.AF_INET) as sock:
        sock.settimeout(0.2)
        return sock.connect_ex((probe, int(port))) == 0


def wait_listening(endpoint: str, timeout: float, proc: Proc | None = None, interval: float = 0.05,
                   logs=None) -> None:
    """Wait until something accepts connections at a tcp endpoint (another transport: until `proc` has run
    for SETTLE_S). RuntimeError as soon as `proc` exits; TimeoutError after `timeout` s."""
    t0 = time.monotonic()

    def up():
        if proc is not None and not proc.alive():
            raise RuntimeError(f"{proc.name} (pid {proc.pid}) exited with {proc.poll()}"
                               + (f"\n{logs()}" if logs else ""))
        ok = accepts(endpoint)
        return ok if ok is not None else time.monotonic() - t0 >= SETTLE_S

    wait_for(up, timeout, f"a listener on {endpoint}", interval=interval, logs=logs)


_PRCTL = None  # libc's prctl, resolved in the parent (no dlopen between fork and exec), False where there is none


def _prctl():
    global _PRCTL
    if _PRCTL is None:
        try:
            _PRCTL = ctypes.CDLL("libc.so.6", use_errno=True).prctl
        except (OSError, AttributeError):
            _PRCTL = False
    return _PRCTL


def _die_with_parent() -> None:
    """preexec_fn: SIGTERM this child when its parent dies (Linux; when the parent's thread that started it ends,
    in fact). It runs in the child between fork and exec: only the call, prctl resolved in the parent."""
    if _PRCTL:
        _PRCTL(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class Proc:
    """One child process in a process group of its own; stdout and stderr into `log` (a file, truncated
    unless `append`) or, without one, the parent's. die_with_parent: SIGTERM when the parent (its thread that
    started it) dies. pass_fds, env: as subprocess.Popen."""

    def __init__(self, name: str, argv: list[str], log: Path | None = None, env: dict | None = None, *,
                 append: bool = False, die_with_parent: bool = False, pass_fds: tuple[int, ...] = ()):
        self.name, self.argv, self.log = name, argv, log
        if die_with_parent:
            _prctl()
        fh = open(log, "ab" if append else "wb") if log is not None else None
        try:
            self.p = subprocess.Popen(argv, stdout=fh, stderr=subprocess.STDOUT if fh else None,
                                      stdin=subprocess.DEVNULL, start_new_session=True, env=env,
                                      pass_fds=pass_fds, preexec_fn=_die_with_parent if die_with_parent else None)
        finally:
            if fh is not None:
                fh.close()  # the child has its own copy
        self.pid = self.p.pid
        self._ps: psutil.Process | None = None
        for old in [q for q in list(_LIVE) if q.returncode is not None]:  # exited and reaped: nothing to end
            _LIVE.discard(old)
        _LIVE.add(self)

    # -- state ----------------------------------------------------------------------------------------------

    def poll(self) -> int | None:
        return self.p.poll()

    @property
    def returncode(self) -> int | None:
        return self.p.returncode

    def alive(self) -> bool:
        return self.p.poll() is None

    def wait(self, timeout: float) -> int:
        """The exit code; TimeoutError when still running after `timeout` s."""
        try:
            return self.p.wait(timeout)
        except subprocess.TimeoutExpired:
            raise TimeoutError(f"{self.name} (pid {self.pid}) still running after {timeout} s\n{self.tail()}") \
                from None

    def text(self) -> str:
        """Everything it logged so far ("" without a log file)."""
        try:
            return self.log.read_text(errors="replace") if self.log is not None else ""
        except OSError:
            return ""

    def tail(self, n: int = 30) -> str:
        lines = self.text().splitlines()[-n:]
        return f"--- {self.name} (pid {self.pid}, rc {self.p.poll()}) {self.log}\n" + "\n".join(lines)

    # -- figures (psutil) -------------------------------------------------------------------------------------

    def _process(self) -> psutil.Process:
        if self._ps is None:
            self._ps = psutil.Process(self.pid)
        return self._ps

    def cpu_s(self) -> float:
        """CPU time used so far, user + system, in seconds (psutil.NoSuchProcess once it is reaped)."""
        t = self._process().cpu_times()
        return t.user + t.system

    def rss_bytes(self) -> int:
        """Resident memory now, in bytes."""
        return self._process().memory_info().rss

    # -- signals --------------------------------------------------------------------------------------------

    def signal(self, sig: int) -> None:
        """Send sig to the process only (not its group)."""
        if self.p.poll() is None:
            os.kill(self.pid, sig)

    def kill(self) -> None:
        """SIGKILL the process only (as subprocess.Popen.kill)."""
        self.signal(signal.SIGKILL)

    def signal_group(self, sig: int) -> None:
        """Send sig to its process group (also after the leader exited: what it left behind)."""
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.pid, sig)

    def stop(self, grace: float = GRACE_S, term_grace: float = TERM_GRACE_S,
             log: logging.Logger | None = None) -> int | None:
        """SIGINT to its group, SIGTERM after `grace` s, SIGKILL after `term_grace` s more (each step only if
        it still runs; `log` warns of each), then SIGKILL to what is left of the group; always reaps. Returns
        the exit code."""
        for sig, wait, then in ((signal.SIGINT, grace, "SIGTERM"), (signal.SIGTERM, term_grace, "SIGKILL")):
            if self.p.poll() is not None:
                break
            self.signal_group(sig)
            try:
                self.p.wait(wait)
            except subprocess.TimeoutExpired:
                if log is not None:
                    log.warning("%s (pid %d) did not stop in %.0f s after %s: %s", self.name, self.pid, wait,
                                signal.Signals(sig).name, then)
        self.signal_group(signal.SIGKILL)  # leftovers of the group, even after the leader exited
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.p.wait(5)
        forget(self)
        return self.p.poll()


def stop_all(procs: list[Proc], grace: float = GRACE_S, term_grace: float = TERM_GRACE_S,
             log: logging.Logger | None = None) -> None:
    """Proc.stop each, in the order given."""
    for p in procs:
        p.stop(grace, term_grace, log)
