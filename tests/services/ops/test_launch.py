"""services/ops/launch.py's register of live children, and what it is for (issue #33): a killed test run leaves
no process behind. A real pytest run of a tiny test file (its conftest installs tests/reaper.py, as
tests/conftest.py does) starts `vergence up` (router, actuator, worker, reducer, capture), a worker of its own
and a plain child; the test sends SIGTERM or SIGINT to that pytest, or SIGTERM to `.ci/group` running it (as
`.ci/run` does), and every process of that run is gone within 5 s. SIGKILL to pytest runs no reaper: the
processes tests/procs.py started end by their parent-death signal (up stopping its own children), the plain child
in pytest's own process group stays (a signal to the group, as .ci/group sends, ends it). Only the processes of
that run are looked at: those whose command line names its rig or its router's port."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sys
import time
from pathlib import Path

import psutil
import pytest

from procs import Proc, free_port, wait_for
from services.ops import launch

pytestmark = pytest.mark.slow  # every test here runs real processes

TESTS = Path(__file__).resolve().parents[2]
REPO = TESTS.parent

INNER_CONFTEST = f"""
import sys
sys.path.insert(0, {str(TESTS)!r})
import vergence, services  # noqa: E401,F401  (as tests/conftest.py: the real packages first)
from reaper import pytest_configure, pytest_runtest_setup, pytest_unconfigure  # noqa: F401
"""

INNER_TEST = """
import json, os, subprocess, sys
from pathlib import Path

from procs import VERGENCE, Procs, wait_for


def test_runs_until_killed(tmp_path):
    rig, endpoint, ready = os.environ["INNER_RIG"], os.environ["INNER_ENDPOINT"], Path(os.environ["INNER_READY"])
    # a plain child in pytest's own process group (as subprocess.run makes them), named by the rig
    plain = subprocess.Popen([sys.executable, "-c", "import sys, time; time.sleep(300)", rig])
    with Procs(tmp_path, rig=rig) as P:
        P.endpoint = endpoint
        up = P.start("up", "up", "--listen", endpoint, "--source", "sim", "--workers", "1", "--rate", "10",
                     connect=False)
        wait_for(lambda: "started capture" in up.text(), 120, "up's last child", logs=P.logs)
        P.start("worker", "worker", "--name", "own")  # a Proc of the test's own, a client of up's router
        ready.write_text(json.dumps({"pytest": os.getpid(), "up": up.pid, "plain": plain.pid}))
        wait_for(lambda: False, 300, "the signal that ends this run")  # the outer test kills it long before
"""


def _of_the_run(*names: str) -> list[psutil.Process]:
    """The processes whose command line holds one of names (the run's rig, its router's port)."""
    out = []
    for ps in psutil.process_iter():
        try:
            line = " ".join(ps.cmdline())
            if any(n in line for n in names) and ps.status() != psutil.STATUS_ZOMBIE and ps.pid != os.getpid():
                out.append(ps)
        except psutil.Error:
            pass
    return out


def test_live_lists_a_proc_until_it_is_stopped_or_seen_exited(tmp_path):
    a = Proc("a", [sys.executable, "-c", "import time; time.sleep(60)"], tmp_path / "a.log")
    b = Proc("b", [sys.executable, "-c", "pass"], tmp_path / "b.log")
    try:
        assert {a, b} <= set(launch.live())
        b.wait(30)
        assert b not in launch.live() and a in launch.live()
        a.stop()
        assert a not in launch.live() and a.returncode is not None
    finally:
        a.stop()
        b.stop()


@pytest.mark.parametrize("via,sig,code", [("pytest", signal.SIGTERM, -signal.SIGTERM),
                                          ("pytest", signal.SIGINT, 2),  # pytest's "interrupted"
                                          (".ci/group", signal.SIGTERM, 128 + signal.SIGTERM),
                                          ("pytest", signal.SIGKILL, -signal.SIGKILL)],
                         ids=["pytest-SIGTERM", "pytest-SIGINT", "ci-group-SIGTERM", "pytest-SIGKILL"])
def test_a_killed_test_run_leaves_no_process_behind(tmp_path, via, sig, code):
    inner = tmp_path / "inner"
    inner.mkdir()
    (inner / "conftest.py").write_text(INNER_CONFTEST)
    (inner / "test_inner.py").write_text(INNER_TEST)
    rig, endpoint = f"k{os.getpid()}x{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    ready = tmp_path / "ready.json"
    env = dict(os.environ, INNER_RIG=rig, INNER_ENDPOINT=endpoint, INNER_READY=str(ready), PYTHONUNBUFFERED="1")
    argv = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(inner / "test_inner.py")]
    if via == ".ci/group":
        argv = [str(REPO / ".ci" / "group"), *argv]
    run = Proc("inner pytest", argv, tmp_path / "inner.log", env)
    try:
        pids = wait_for(lambda: ready.is_file() and ready.read_text() and json.loads(ready.read_text()), 180,
                        "the inner run's processes", interval=0.1, logs=run.tail)
        # up's children (router, actuator, worker1, reducer, capture), the test's own worker and the plain child
        wait_for(lambda: len(_of_the_run(rig, endpoint)) >= 7, 30, "7 processes of the run", logs=run.tail)
        before = _of_the_run(rig, endpoint)
        kinds = sorted(" ".join(ps.cmdline()).split(" --")[0].rsplit(" ", 1)[-1] for ps in before)
        print(f"\n{len(before)} processes of the run before {sig.name} to {via}: {kinds}")
        assert {"router", "actuator", "worker", "reducer", "capture", "up"} <= set(kinds), kinds
        stays = {pids["plain"]} if sig == signal.SIGKILL else set()  # (see above)

        def left() -> list[psutil.Process]:
            return [ps for ps in _of_the_run(rig, endpoint) if ps.pid not in stays]

        t0 = time.monotonic()
        run.signal(sig)  # the process only, as a CI runner's cancel or kill(1) sends it
        try:
            wait_for(lambda: not left() and not run.alive(), 5.0, "every process of the run gone", interval=0.05)
        except TimeoutError:
            still = [f"{ps.pid} {' '.join(ps.cmdline())[:100]}" for ps in left()]
            raise AssertionError(f"left after 5 s: {still}; the run {'alive' if run.alive() else 'ended'}\n"
                                 f"{run.tail(40)}") from None
        took = time.monotonic() - t0
        print(f"all gone {took:.2f} s after the signal; the run exited with {run.returncode}")
        assert run.returncode == code, run.tail(40)
        assert not psutil.pid_exists(pids["up"]) or psutil.Process(pids["up"]).status() == psutil.STATUS_ZOMBIE
        if sig != signal.SIGKILL:
            assert f"reaper ({sig.name}): ended" in run.text(), run.tail(40)
    finally:
        run.stop(grace=1.0)
        for ps in _of_the_run(rig, endpoint):  # when the test failed: what the run left (its own, by name)
            with contextlib.suppress(psutil.Error):
                ps.kill()
