"""Shared helpers for process tests: a real Zenoh router on 127.0.0.1, real `vergence ...` processes in their
own process groups with their output in log files, bounded waits, and a teardown that leaves nothing behind.

    from procs import Procs                # tests/ has no __init__.py: pytest puts tests/ on sys.path

    def test_something(tmp_path):
        with Procs(tmp_path) as P:
            P.router()                      # a router on a free port; P.endpoint is its tcp/127.0.0.1:PORT
            P.start("worker", "worker")     # `vergence worker --connect <router> --rig <P.rig>`
            with P.session() as s:          # a zenoh client session of the test itself
                got = P.wait_key(s, "vergence/%s/command" % P.rig, timeout=10)
        # leaving the block kills every process group started (SIGINT, then SIGKILL after a grace time)

Every wait has a timeout and raises TimeoutError (with the tail of the process logs) when it expires.
Processes, ports and waits are services/ops/launch.py's, the same as `vergence up`'s and the benchmark's.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import zygote
from vergence.wire import keys
from services.ops.launch import Proc, free_port, wait_for, wait_listening

VERGENCE = str(Path(sys.executable).with_name("vergence"))  # the installed command itself

__all__ = ["free_port", "Proc", "Procs", "wait_for", "VERGENCE", "run", "gives_up_without_a_router"]


def run(*args: str, timeout: float = 60, fresh: bool = False) -> subprocess.CompletedProcess:
    """`vergence ARGS...` run to its end (at most timeout s: subprocess.TimeoutExpired, the command killed), its
    stdout and stderr captured as text. Forked by the tests' zygote (tests/zygote.py) unless `fresh` (a new
    interpreter: what the user's shell starts) or the zygote would not fork it."""
    argv = [sys.executable, "-m", "services.ops.cli", *args]
    z = None if fresh else zygote.get()
    if z is None or not z.fits(argv, dict(os.environ, PYTHONUNBUFFERED="1")):
        return subprocess.run(argv, capture_output=True, text=True, timeout=timeout)
    import tempfile

    with tempfile.TemporaryDirectory(prefix="vergence-run-") as d:
        out, err = Path(d) / "out", Path(d) / "err"
        child = z.spawn(argv, out, dict(os.environ, PYTHONUNBUFFERED="1"), err=err)
        try:
            code = child.wait(timeout)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(child.pid, 9)
            child.wait(10)
            raise subprocess.TimeoutExpired(argv, timeout, out.read_bytes(), err.read_bytes()) from None
        return subprocess.CompletedProcess(argv, code, out.read_text(errors="replace"),
                                           err.read_text(errors="replace"))


def gives_up_without_a_router(*args: str, within: float, margin: float = 8.0) -> subprocess.CompletedProcess:
    """`vergence ARGS... --connect <a free port of 127.0.0.1 nobody listens on>` run to its end, checked as a
    client without a router must end (issue #28): exit 1, one line on stderr naming the endpoint, the wait
    (`within` s) and what to do, and no later than `within` + margin s (the interpreter's start included)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    t0 = time.monotonic()
    r = run(*args, "--connect", endpoint, timeout=within + margin + 10)
    took = time.monotonic() - t0
    assert r.returncode == 1, (r.returncode, r.stderr[-2000:])
    assert r.stderr.splitlines() == [
        f"vergence {args[0]}: no Zenoh router or peer answered at {endpoint} within {within:g} s; start one with "
        "`vergence up` (or `vergence router`), or pass --connect ENDPOINT"], r.stderr[-2000:]
    assert took < within + margin, took
    return r


def tmux(*args: str, check: bool = True) -> str:
    """`tmux ARGS...` (a terminal a test reads as a person would), its stdout; RuntimeError when it fails. A
    session it makes (new-session -s NAME) is killed by the reaper if the run is (tmux's server is no child of
    the test's); kill-session forgets it."""
    import reaper

    if args[:1] == ("new-session",) and "-s" in args:
        name = args[args.index("-s") + 1]
        reaper.at_reap(("tmux", name), lambda: subprocess.run(["tmux", "kill-session", "-t", name],
                                                              capture_output=True, timeout=5))
    elif args[:1] == ("kill-session",) and "-t" in args:
        reaper.forget(("tmux", args[args.index("-t") + 1]))
    r = subprocess.run(["tmux", *args], capture_output=True, text=True, timeout=10)
    if check and r.returncode != 0:
        raise RuntimeError(f"tmux {' '.join(args)}: {r.stderr.strip()}")
    return r.stdout


class _Forked(Proc):
    """A Proc forked by the tests' zygote (tests/zygote.py): a `vergence ...` command that starts in a fraction of a
    fresh interpreter's time; it dies with the zygote, which dies with pytest."""

    def __init__(self, name: str, argv: list[str], log: Path, env: dict, z: "zygote.Zygote"):
        self.name, self.argv, self.log = name, argv, log
        log.write_bytes(b"")
        self.p = z.spawn(argv, log, env, append=True)
        self._started()


class Procs:
    """A set of processes for one test around one router; a context manager that tears everything down."""

    def __init__(self, tmp_path: Path, rig: str | None = None):
        self.dir = Path(tmp_path)
        self.rig = rig or f"t{uuid.uuid4().hex[:8]}"
        self.procs: list[Proc] = []
        self.port: int | None = None
        self.endpoint: str | None = None
        self._sessions = []

    # -- processes -----------------------------------------------------------------------------------------

    def spawn(self, name: str, argv: list[str], env: dict | None = None) -> Proc:
        """Start any command (own process group, log in tmp_path/<name>.log). Started from pytest's main thread, it
        gets SIGTERM if pytest dies (a SIGKILLed run runs no reaper: tests/reaper.py); from another thread, not (the
        signal would come when that thread ends)."""
        e = dict(os.environ if env is None else env)
        e.setdefault("PYTHONUNBUFFERED", "1")
        cli = [sys.executable, "-m", "services.ops.cli", *argv[1:]] if argv[:1] == [VERGENCE] else argv
        z = zygote.get() if env is None else None  # (see tests/zygote.py for what it does not fork)
        if z is not None and z.fits(cli, e):
            p = _Forked(name, cli, self.dir / f"{name}.log", e, z)
        else:
            p = Proc(name, argv, self.dir / f"{name}.log", e,
                     die_with_parent=threading.current_thread() is threading.main_thread())
        self.procs.append(p)
        return p

    def start(self, name: str, *args: str, connect: bool = True, rig: bool = True) -> Proc:
        """`vergence <args>` connected to this test's router (--connect) with this test's --rig."""
        argv = [VERGENCE, *args]
        if connect:
            if self.endpoint is None:
                raise RuntimeError("start the router first (Procs.router())")
            argv += ["--connect", self.endpoint]
        if rig:
            argv += ["--rig", self.rig]
        return self.spawn(name, argv)

    def router(self, timeout: float = 15.0) -> Proc:
        """`vergence router` on a free port of 127.0.0.1; returns once it accepts TCP connections."""
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        p = self.spawn("router", [VERGENCE, "router", "--listen", self.endpoint])
        wait_listening(self.endpoint, timeout, p, interval=0.02, logs=self.logs)  # RuntimeError if it exits
        return p

    def logs(self) -> str:
        return "\n".join(p.tail() for p in self.procs)

    # -- the test's own zenoh session ------------------------------------------------------------------------

    def wait_port(self, timeout: float = 20.0) -> None:
        """Wait until something accepts TCP connections on the endpoint's port (a router started by
        another process, `vergence up` say)."""
        wait_listening(self.endpoint, timeout, interval=0.1, logs=self.logs)

    def session(self, timeout: float = 20.0):
        """A zenoh client session connected to the router (closed at teardown if not before); waits up to
        `timeout` s for the router to listen."""
        import zenoh

        self.wait_port(timeout)
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", f'["{self.endpoint}"]')
        conf.insert_json5("scouting/multicast/enabled", "false")
        # as every vergence process (services/runtime/session.py)
        conf.insert_json5("transport/shared_memory/enabled", "false")
        s = zenoh.open(conf)
        self._sessions.append(s)
        return s

    def key(self, suffix: str) -> str:
        """vergence/<rig>/<suffix> (the suffix as vergence.wire.keys names it: frame, motor_state, status/** ...)."""
        return keys.prefix(self.rig) + suffix

    def collect(self, session, key: str) -> "Collector":
        """Record every sample on key (with its arrival time) from now on."""
        return Collector(session, key, self.logs)

    def wait_key(self, session, key: str, timeout: float = 10.0):
        """The payload (bytes) of the first sample on key, within `timeout` s."""
        c = self.collect(session, key)
        try:
            return c.wait(1, timeout)[0][1]
        finally:
            c.close()

    def wait_alive(self, session, role: str, n: int = 1, timeout: float = 15.0) -> list[str]:
        """Wait until at least n liveliness tokens vergence/<rig>/alive/<role>/* exist; their ids."""
        def ids():
            got = [keys.parse(str(r.ok.key_expr)).ident
                   for r in session.liveliness().get(keys.alives(self.rig, role), timeout=1.0) if r.ok]
            return got if len(got) >= n else None

        return wait_for(ids, timeout, f"{n} {role} token(s)", interval=0.1, logs=self.logs)

    # -- teardown -------------------------------------------------------------------------------------------

    def close(self) -> None:
        for s in self._sessions:
            with contextlib.suppress(Exception):
                s.close()
        self._sessions = []
        # workers and clients first, the router last
        for p in reversed(self.procs):
            p.stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class Collector:
    """Samples of one key as (arrival time.time_ns(), payload bytes, key), appended from zenoh's thread;
    wait() wakes as they arrive."""

    def __init__(self, session, key: str, logs=None):
        self.items: list[tuple[int, bytes, str]] = []
        self._lock = threading.Condition()
        self.logs = logs
        self.sub = session.declare_subscriber(key, self._on)

    def _on(self, sample) -> None:
        item = (time.time_ns(), sample.payload.to_bytes(), str(sample.key_expr))
        with self._lock:
            self.items.append(item)
            self._lock.notify_all()

    def snapshot(self) -> list[tuple[int, bytes, str]]:
        with self._lock:
            return list(self.items)

    def __len__(self) -> int:
        return len(self.items)

    def wait(self, n: int, timeout: float) -> list[tuple[int, bytes, str]]:
        """The first n samples (waiting up to `timeout` s for them; TimeoutError with the logs)."""
        with self._lock:
            if self._lock.wait_for(lambda: len(self.items) >= n, timeout):
                return self.items[:n]
        raise TimeoutError(f"timed out after {timeout} s waiting for {n} sample(s) on {self.sub.key_expr}"
                           + (f"\n{self.logs()}" if self.logs else ""))

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.sub.undeclare()


def textured_pair(tmp_path: Path, seed: int = 3, shift: int = 12, flat: int = 0) -> str:
    """A `files:LEFT,RIGHT` source: a 320 x 120 textured pair whose slave image shows the scene `shift` px
    further right (every frame's decision: offset_px = +shift). flat: the side of a flat grey square on the
    master's centre (and where the slave sees it): with 17, the 15 px fovea abstains and 23 px decides."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.integers(0, 256, (120, 360), np.uint8), (5, 5), 1.5)
    if flat:
        base[60 - flat // 2 : 60 + flat - flat // 2, 180 - flat // 2 : 180 + flat - flat // 2] = 128
    left, right = Path(tmp_path) / "l.png", Path(tmp_path) / "r.png"
    cv2.imwrite(str(left), base[:, 20:340])
    cv2.imwrite(str(right), base[:, 20 - shift : 340 - shift])
    return f"files:{left},{right}"

