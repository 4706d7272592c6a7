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

`Proc(..., fork=True)` (what `vergence up` uses for its children) forks the parent instead of starting a fresh
interpreter: a child of up then has what up loaded before it (numpy, numba and the kernels, OpenCV, zenoh's
module, the services' code) and starts in a tenth of the CPU. The argv must be a `vergence(...)` command: the child
runs services.ops.cli.main on it as the interpreter would, with the environment, the process group, the descriptors
(`pass_fds` and 0-2 only), the signals and the exit of a fresh start, and shows the argv as its command line (ps,
/proc/PID/cmdline: setproctitle). The parent must have no thread of its own (up has none; the idle pools of
numpy's BLAS and OpenCV are rebuilt in a forked child) and no Zenoh session open.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import traceback
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


class _Forked:
    """What subprocess.Popen gives of a child, for one made by os.fork: pid, poll, wait, returncode."""

    def __init__(self, pid: int):
        self.pid = pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            try:
                pid, status = os.waitpid(self.pid, os.WNOHANG)
            except ChildProcessError:  # reaped by someone else: its status is lost (as Popen, which says 0)
                self.returncode = 0
            else:
                if pid:
                    self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        end = None if timeout is None else time.monotonic() + timeout
        pause = 0.001
        while self.poll() is None:
            if end is not None and time.monotonic() >= end:
                raise subprocess.TimeoutExpired(f"pid {self.pid}", timeout)
            time.sleep(pause)
            pause = min(2 * pause, 0.02)
        return self.returncode


def _fork(argv: list[str], out: int | None, env: dict | None, die_with_parent: bool,
          pass_fds: tuple[int, ...], err: int | None = None) -> _Forked:
    """Fork this process into `argv` (a vergence(...) command) run by services.ops.cli.main: see the module's
    docstring. Its stdout and stderr go to `out` (stderr to `err` if given), else to this process's."""
    if argv[1:3] != ["-m", "services.ops.cli"]:
        raise ValueError(f"only a vergence(...) command can be forked, not {argv[:3]}")
    from setproctitle import setproctitle

    from services.ops import cli
    from services.runtime import session

    _prctl()  # resolved here, not between fork and the child's first call
    for f in (sys.stdout, sys.stderr):  # what is buffered is the parent's to write, not the child's too
        with contextlib.suppress(Exception):
            f.flush()
    parent = os.getpid()
    pid = os.fork()
    if pid:
        return _Forked(pid)
    code = 1
    try:  # the child: it never returns from here, whatever happens (os._exit below)
        # ps and /proc/PID/cmdline show the child's command, not the parent's (before the environment changes:
        # setproctitle takes the room of the parent's argv and environment strings). A title shorter than the
        # parent's argv is padded with spaces: else the kernel gives the rest of that room as empty arguments ...
        with open("/proc/self/cmdline", "rb") as fh:
            room = len(fh.read())
        setproctitle(" ".join(argv).ljust(room - 1))
        if _PRCTL:  # ... and its name (comm) what a fresh start's would be: the interpreter's file name
            _PRCTL(15, Path(argv[0]).name.encode()[:15])  # PR_SET_NAME
        os.setsid()
        if die_with_parent and _PRCTL:
            _PRCTL(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
            if os.getppid() != parent:  # the parent died before that
                raise SystemExit(1)
        null = os.open(os.devnull, os.O_RDWR)
        os.dup2(null, 0)
        if out is not None:
            os.dup2(out, 1)
            os.dup2(out if err is None else err, 2)
        keep = {0, 1, 2, *pass_fds}
        for fd in [int(f) for f in os.listdir("/proc/self/fd")]:  # the parent's other descriptors
            if fd not in keep:
                with contextlib.suppress(OSError):
                    os.close(fd)
        # a fresh interpreter's state where the parent's differs: exit handlers, signals, environment, logging,
        # the parent's children and stops, the argv
        atexit._clear()
        signal.set_wakeup_fd(-1)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1, signal.SIGUSR2, signal.SIGCHLD):
            signal.signal(sig, signal.SIG_DFL)
        if env is not None:
            os.environ.clear()
            os.environ.update(env)
        root = logging.getLogger()
        for h in list(root.handlers):
            root.removeHandler(h)
        root.setLevel(logging.WARNING)
        _LIVE.clear()
        session._stops.clear()
        sys.argv = [cli.__file__, *argv[3:]]
        code = cli.main(argv[3:])
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 0 if e.code is None else 1
        if isinstance(e.code, str):
            print(e.code, file=sys.stderr)
    except KeyboardInterrupt:
        code = 130
    except BaseException:
        traceback.print_exc()
        code = 1
    finally:
        with contextlib.suppress(BaseException):
            getattr(threading, "_shutdown", lambda: None)()  # as at an interpreter's exit: its threads end first
            atexit._run_exitfuncs()
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code & 0xFF)


class Proc:
    """One child process in a process group of its own; stdout and stderr into `log` (a file, truncated
    unless `append`) or, without one, the parent's. die_with_parent: SIGTERM when the parent (its thread that
    started it) dies. pass_fds, env: as subprocess.Popen. fork: forked from this process (see the module's
    docstring), not a fresh interpreter."""

    def __init__(self, name: str, argv: list[str], log: Path | None = None, env: dict | None = None, *,
                 append: bool = False, die_with_parent: bool = False, pass_fds: tuple[int, ...] = (),
                 fork: bool = False):
        self.name, self.argv, self.log = name, argv, log
        if die_with_parent:
            _prctl()
        fh = open(log, "ab" if append else "wb") if log is not None else None
        try:
            if fork:
                self.p = _fork(argv, fh.fileno() if fh else None, env, die_with_parent, pass_fds)
            else:
                self.p = subprocess.Popen(argv, stdout=fh, stderr=subprocess.STDOUT if fh else None,
                                          stdin=subprocess.DEVNULL, start_new_session=True, env=env,
                                          pass_fds=pass_fds,
                                          preexec_fn=_die_with_parent if die_with_parent else None)
        finally:
            if fh is not None:
                fh.close()  # the child has its own copy
        self._started()

    def _started(self) -> None:
        """Known to live() from now on (self.p is its Popen-like)."""
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
