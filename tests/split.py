"""The whole suite in two processes at once (issue #33: CI under 10 minutes on 2 cores).

The slow tier (real processes: routers, services, ROS 2 nodes) mostly waits on real time: the machine is 40-45 %
busy while it runs. The rest (what runs in the test's own process and times nothing, `-m "not slow and not realtime"`:
CPU, no waiting; a `realtime` test, in-process but timing something, a thread's wake-up say, stays here) runs beside it,
in a pytest of its own at idle priority (SCHED_IDLE: it runs only on a core nothing else wants, so the timings under
test are not disturbed, as tests/background.py's sweeps are not), and its outcome joins this run's: its summary line,
its failures in full, and this run's exit status (1 when it failed). Measured on this machine (2026-12-06, a fresh
clone's `.ci/run`): 455 s of pytest, the 988 tests beside it done in 219 s at idle priority, against 534-549 s for
the whole suite in one process.

Only a run of the whole suite is split (`python -m pytest [-q]`, no paths, no -m, -k, --lf, -x and the like: what
README.md and .ci/run run); any selection runs as before, in one process. VERGENCE_TESTS_SPLIT=0 runs the whole
suite in one process too. tests/conftest.py calls these at its hooks; the reaper ends the other pytest with the run
(it is a descendant), a SIGKILLed run ends it by its parent-death signal (SIGTERM: its own reaper runs), and a run
that ends waits for it (at most WAIT_S)."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile

CHILD = "VERGENCE_TESTS_CHILD"  # set in the other pytest's environment
BESIDE = "not slow and not realtime"  # the tests it runs: in-process ones that measure no wall-clock time
KEEP = ("slow", "realtime")  # this process's: real processes, and in-process tests that time something
WAIT_S = 1800.0

_child: dict = {}  # "proc", "out" (its output file), "n" (its tests)


def is_child() -> bool:
    return os.environ.get(CHILD) == "1"


def idle() -> None:
    """In the other pytest: idle priority (os.nice(19) where SCHED_IDLE is not to be had), and no Hypothesis
    deadline (an example may wait for a core)."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        os.nice(19)
    from hypothesis import settings

    settings.register_profile("idle", deadline=None)
    settings.load_profile("idle")


def _whole_suite(config) -> bool:
    o = config.option
    selection = (o.file_or_dir, o.markexpr, o.keyword, getattr(o, "lf", False), getattr(o, "failedfirst", False),
                 o.maxfail, getattr(o, "collectonly", False), getattr(o, "deselect", None),
                 getattr(o, "stepwise", False))
    return not any(selection) and os.environ.get("VERGENCE_TESTS_SPLIT", "1") != "0" and (os.cpu_count() or 1) > 1


def modify(config, items: list) -> None:
    """pytest_collection_modifyitems: in a run of the whole suite, this process keeps the slow and the realtime
    tests; the others are counted for the pytest that start() makes."""
    if is_child() or not _whole_suite(config):
        return

    def kept(it) -> bool:
        return any(it.get_closest_marker(m) is not None for m in KEEP)

    fast = [it for it in items if not kept(it)]
    if fast and len(fast) < len(items):
        items[:] = [it for it in items if kept(it)]
        _child["n"] = len(fast)


def start(rootdir) -> None:
    """pytest_collection_finish (after the kernels are compiled): the other pytest, on the tests `modify` left out."""
    if "n" not in _child:
        return
    from services.ops import launch

    out = tempfile.TemporaryFile(mode="w+")
    argv = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", BESIDE]
    launch._prctl()  # (resolved here, before the fork: the child only calls it)
    _child.update(proc=subprocess.Popen(argv, cwd=str(rootdir), stdout=out, stderr=subprocess.STDOUT,
                                        env=dict(os.environ, **{CHILD: "1"}), preexec_fn=launch._die_with_parent),
                  out=out)


def finish(session) -> None:
    """pytest_sessionfinish: wait for the other pytest; its failure is this run's."""
    proc = _child.get("proc")
    if proc is None:
        return
    try:
        proc.wait(WAIT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    if proc.returncode != 0 and session.exitstatus == 0:
        session.exitstatus = 1


def summary(terminalreporter) -> None:
    """pytest_terminal_summary: the other pytest's outcome (its whole output when it failed)."""
    proc = _child.get("proc")
    if proc is None:
        return
    out = _child["out"]
    out.seek(0)
    text = out.read()
    lines = [ln for ln in text.splitlines() if ln.strip()]
    tr = terminalreporter
    if proc.returncode != 0:
        tr.section(f"the {_child['n']} tests that ran beside this run (-m '{BESIDE}'): exit {proc.returncode}")
        tr.write(text)
    last = lines[-1].strip("= ") if lines else "no output"
    tr.write_line(f"beside this run, in a pytest of its own at idle priority, the {_child['n']} tests of "
                  f"-m '{BESIDE}': {last}")
