"""The whole suite in three processes at once (issue #33: CI under 10 minutes on 2 cores).

The slow tier (real processes: routers, services, ROS 2 nodes) mostly waits on real time: the machine is 10-50 %
busy while it runs (measured 2026-12-07: 44 % on average over its 537 s, the first 100 s the background sweeps'
at idle priority). So it runs in two pytests at normal priority: this one, and beside it one of its own on the
slow and realtime tests of the scenarios folder (tests/scenarios: whole services end to end, 45 % of the tier's time).
The rest (what runs in the test's own process and times nothing, `-m "not slow and not realtime"`: CPU, no waiting;
a `realtime` test, in-process but timing something, a thread's wake-up say, stays at normal priority) runs in a
third, at idle priority (SCHED_IDLE: it runs only on a core nothing else wants, so the timings under test are not
disturbed, as tests/background.py's sweeps are not). The outcomes of both join this run's: their summary lines,
their failures in full, and this run's exit status (1 when one failed). The two pytests of real processes share
the machine's ports (each test takes free ones) and its ROS 2 network (each picks its domains from a half of its
own: tests/rosnode.py). Measured on this machine (2026-12-07, a fresh clone's `.ci/run`, headless Chromium
installed): 489-558 s in all, this pytest's 206 tests 430-494 s, the scenarios' 91 339-398 s beside it, the 1104
in-process tests 287-395 s; with the scenarios in this pytest 542 s of pytest, about 600 s in all.

A test marked `alone` (the ROS 2 ones: their DDS discovery and the test's own camera and joint nodes, starved by a
second pytest of real processes beside them, made the loop name a false slave_frozen in 2 of 4 CI runs) runs with no
test of the other pytest of real processes beside it: each test of the two holds a lock on a file of the run's (`turn`),
shared, an `alone` one exclusive.

Only a run of the whole suite is split (`python -m pytest [-q]`, no paths, no -m, -k, --lf, -x and the like: what
README.md and .ci/run run); any selection runs as before, in one process. VERGENCE_TESTS_SPLIT=0 runs the whole
suite in one process too. tests/conftest.py calls these at its hooks; the reaper ends the other pytests with the run
(they are descendants), a SIGKILLed run ends them by their parent-death signal (SIGTERM: their own reaper runs), and
a run that ends waits for them (at most WAIT_S)."""

from __future__ import annotations

import contextlib
import fcntl
import os
import subprocess
import sys
import tempfile
from pathlib import Path

CHILD = "VERGENCE_TESTS_CHILD"  # in the other pytests' environment: IDLE or SCENARIOS
IDLE, SCENARIOS = "1", "scenarios"
BESIDE = "not slow and not realtime"  # the idle pytest's tests: in-process ones that measure no wall-clock time
KEEP = ("slow", "realtime")  # this process's: real processes, and in-process tests that time something
FOLDER = "scenarios"  # ...but those of a folder of this name go to a pytest of their own, at normal priority
WAIT_S = 1800.0
LOCK = "VERGENCE_TESTS_LOCK"  # the run's lock file and its pytest's pid ("PATH:PID"), for `turn`

_children: dict[str, dict] = {}  # IDLE / SCENARIOS -> "argv", "n" (its tests), "proc", "out" (its output file)


def is_child() -> bool:
    """The idle pytest (the scenarios' pytest is not: it runs at normal priority)."""
    return os.environ.get(CHILD) == IDLE


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
    tests but the scenarios'; the others are counted for the pytests that start() makes."""
    if os.environ.get(CHILD) or not _whole_suite(config):
        return
    root = Path(str(config.rootpath))

    def kept(it) -> bool:
        return any(it.get_closest_marker(m) is not None for m in KEEP)

    def scenario(it) -> bool:
        return FOLDER in Path(str(it.path)).relative_to(root).parts[:-1]

    fast = [it for it in items if not kept(it)]
    scenes = [it for it in items if kept(it) and scenario(it)]
    if fast and len(fast) < len(items):
        _children[IDLE] = dict(n=len(fast), argv=["-m", BESIDE])
    if scenes and len(scenes) < len(items) - len(fast):
        files = sorted({str(Path(str(it.path)).relative_to(root)) for it in scenes})
        _children[SCENARIOS] = dict(n=len(scenes), argv=["-m", " or ".join(KEEP), *files])
    if SCENARIOS in _children:
        fd, path = tempfile.mkstemp(prefix="vergence-tests-", suffix=".lock")
        os.close(fd)
        os.environ[LOCK] = f"{path}:{os.getpid()}"
    items[:] = [it for it in items if not (IDLE in _children and not kept(it))
                and not (SCENARIOS in _children and kept(it) and scenario(it))]


def _lock() -> tuple[str, bool]:
    """The run's lock file ("" outside a split run), and whether this pytest made it (the run's own)."""
    path, _, pid = os.environ.get(LOCK, "").rpartition(":")
    return path, pid == str(os.getpid())


@contextlib.contextmanager
def turn(alone: bool):
    """Around each test of the two pytests of real processes in a whole run: a shared lock on the run's file, or an
    exclusive one for a test that runs alone (elsewhere, as in any other run: nothing)."""
    path, mine = _lock()
    if not path or not (os.environ.get(CHILD) == SCENARIOS or mine):
        yield
        return
    with open(path) as f:
        fcntl.flock(f, fcntl.LOCK_EX if alone else fcntl.LOCK_SH)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def start(rootdir) -> None:
    """pytest_collection_finish (after the kernels are compiled): the other pytests, on the tests `modify` left out."""
    from services.ops import launch

    launch._prctl()  # (resolved here, before the fork: the child only calls it)
    for name, c in _children.items():
        out = tempfile.TemporaryFile(mode="w+")
        argv = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *c["argv"]]
        c.update(proc=subprocess.Popen(argv, cwd=str(rootdir), stdout=out, stderr=subprocess.STDOUT,
                                       env=dict(os.environ, **{CHILD: name}), preexec_fn=launch._die_with_parent),
                 out=out)


def finish(session) -> None:
    """pytest_sessionfinish: wait for the other pytests; a failure of theirs is this run's; the lock file goes."""
    for c in _children.values():
        proc = c.get("proc")
        if proc is None:
            continue
        try:
            proc.wait(WAIT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if proc.returncode != 0 and session.exitstatus == 0:
            session.exitstatus = 1
    path, mine = _lock()
    if path and mine:
        with contextlib.suppress(OSError):
            os.unlink(path)


def summary(terminalreporter) -> None:
    """pytest_terminal_summary: the other pytests' outcomes (the whole output of one that failed)."""
    tr = terminalreporter
    for name, c in _children.items():
        proc = c.get("proc")
        if proc is None:
            continue
        c["out"].seek(0)
        text = c["out"].read()
        lines = [ln for ln in text.splitlines() if ln.strip()]
        which = f"-m '{BESIDE}'" if name == IDLE else f"the {FOLDER} folder's -m '{' or '.join(KEEP)}'"
        if proc.returncode != 0:
            tr.section(f"the {c['n']} tests that ran beside this run ({which}): exit {proc.returncode}")
            tr.write(text)
        last = lines[-1].strip("= ") if lines else "no output"
        how = "at idle priority" if name == IDLE else "at normal priority"
        tr.write_line(f"beside this run, in a pytest of its own {how}, the {c['n']} tests of {which}: {last}")
