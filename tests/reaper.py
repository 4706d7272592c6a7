"""The test run's reaper: a killed run leaves no process behind (issue #33).

A test's processes run in process groups and sessions of their own (services/ops/launch.py's Proc), so a signal
to pytest, or to its process group, does not reach them: on SIGTERM or SIGINT the reaper kills every process the
run started (each live Proc's group, every descendant of pytest, and what tests registered with `at_reap`, such
as a tmux session) and then lets the signal do what it does (SIGTERM: pytest dies of it; SIGINT: a
KeyboardInterrupt, pytest's own summary). At the end of the session it kills what a test left running, saying
what. tests/conftest.py installs it (its pytest_* hooks below); a conftest of a test run made by a test can import
them the same way.

A signal handler runs in the main thread, between two bytecodes: a run blocked in a call without a timeout would
not run it (the tests' waits all have one). A SIGKILLed pytest runs nothing: its children stay (`.ci/run` kills
its own process group, which holds pytest and its direct children, but not the Procs' groups)."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import time

import psutil

from services.ops import launch

SIGNALS = (signal.SIGTERM, signal.SIGINT)
TERM_S = 1.0  # after SIGTERM, the time the processes have to exit before SIGKILL
REAP_S = 3.0  # the longest the reaper spends in all

_at_reap: dict[object, object] = {}  # key -> a callable that ends something not a descendant (a tmux session)
_previous: dict[int, object] = {}  # the handlers replaced (SIGINT: pytest's KeyboardInterrupt)
_config = None  # pytest's, to say what was reaped past its output capture


def at_reap(key, fn) -> None:
    """Call fn() when the run is reaped (a signal, or the session's end), unless forget(key) came first."""
    _at_reap[key] = fn


def forget(key) -> None:
    _at_reap.pop(key, None)


def _targets() -> tuple[list[launch.Proc], list[psutil.Process]]:
    """The live Procs (their groups) and every descendant of this process."""
    procs = launch.live()
    try:
        tree = psutil.Process().children(recursive=True)
    except psutil.Error:
        tree = []
    zygote = sys.modules.get("zygote")  # the tests' zygote (tests/zygote.py) is the run's, not a test's: its
    if zygote is not None:  # children are reaped, it stays to tell their exit codes; it dies with pytest
        tree = [ps for ps in tree if ps.pid not in zygote.pids()]
    return procs, tree


def _send(procs: list[launch.Proc], tree: list[psutil.Process], sig: int) -> None:
    for p in procs:
        if p.returncode is None:  # not reaped: its pid (and its group's id) is still this run's
            p.signal_group(sig)
    for ps in tree:
        with contextlib.suppress(psutil.Error):  # psutil checks the pid is still that process (its start time)
            ps.send_signal(sig)


def reap(why: str = "", term_s: float = TERM_S, within: float = REAP_S) -> list[str]:
    """End every process this run started: SIGTERM (and SIGCONT, for a stopped one) to each live Proc's process
    group and to every descendant, SIGKILL after `term_s` to what is left (looked for again: a supervisor may
    have started another meanwhile), for at most `within` s; then the at_reap callables. What was found
    running, as "name (pid N)" lines."""
    end = time.monotonic() + within
    procs, tree = _targets()
    found = [f"{p.name} (pid {p.pid})" for p in procs if p.returncode is None]
    found += [f"{' '.join(_cmdline(ps))[:120]} (pid {ps.pid})" for ps in tree
              if ps.pid not in {p.pid for p in procs}]
    if procs or tree:
        _send(procs, tree, signal.SIGTERM)
        _send(procs, tree, signal.SIGCONT)
        term_end = min(end, time.monotonic() + term_s)
        while time.monotonic() < term_end and any(_running(ps) for ps in tree):
            time.sleep(0.02)
        while True:
            procs, tree = _targets()
            _send(procs, tree, signal.SIGKILL)
            for p in procs:
                with contextlib.suppress(Exception):
                    p.p.wait(0.2)  # reaped (the leader's pid is free again only now)
                launch.forget(p)
            tree = [ps for ps in tree if _running(ps)]
            if not tree or time.monotonic() > end:
                break
            time.sleep(0.02)
    for key, fn in list(_at_reap.items()):
        with contextlib.suppress(Exception):
            fn()
        _at_reap.pop(key, None)
    if found and why:
        _say(f"\nreaper ({why}): ended {len(found)} process(es):\n  " + "\n  ".join(found))
    return found


def _say(text: str) -> None:
    """A line on the run's stderr, also while pytest captures a test's output."""
    capman = _config.pluginmanager.getplugin("capturemanager") if _config is not None else None
    with capman.global_and_fixture_disabled() if capman is not None else contextlib.nullcontext():
        print(text, file=sys.stderr, flush=True)


def _cmdline(ps: psutil.Process) -> list[str]:
    try:
        return ps.cmdline() or [ps.name()]
    except psutil.Error:
        return ["?"]


def _running(ps: psutil.Process) -> bool:
    try:
        return ps.is_running() and ps.status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def _on_signal(signum, frame) -> None:
    for sig in SIGNALS:  # a second signal meanwhile: the default (end now)
        signal.signal(sig, signal.SIG_DFL)
    try:
        reap(f"{signal.Signals(signum).name}")
    finally:
        if signum == signal.SIGINT:
            install()
            raise KeyboardInterrupt
        os.kill(os.getpid(), signum)  # die of it, as without the reaper
        time.sleep(5)  # (the signal is delivered on return from the kill)
        os._exit(128 + signum)


def install() -> None:
    """Our handler for SIGTERM and SIGINT (the main thread only; again before each test: a test that runs a
    service's main in process may have installed that service's)."""
    for sig in SIGNALS:
        current = signal.getsignal(sig)
        if current is not _on_signal:
            _previous.setdefault(sig, current)
            signal.signal(sig, _on_signal)


# -- the pytest hooks (tests/conftest.py imports them) --------------------------------------------------------------

def pytest_configure(config) -> None:
    global _config
    _config = config
    install()


def pytest_runtest_setup(item) -> None:
    install()


def pytest_unconfigure(config) -> None:
    zygote = sys.modules.get("zygote")  # the tests' zygote (tests/zygote.py) is no test's leftover
    if zygote is not None:
        zygote.close()
    found = reap("the session's end: left running by a test")
    for sig, h in _previous.items():
        with contextlib.suppress(Exception):
            signal.signal(sig, h)
    _previous.clear()
    if found:
        _say(f"reaper: {len(found)} process(es) were still running at the session's end (a test's teardown "
             "missed them)")
