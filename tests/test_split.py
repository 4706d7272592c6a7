"""tests/split.py: a run of the whole suite runs its in-process tests beside it, in a pytest of their own at idle
priority, and the slow tests of its scenarios folder in another at normal priority, and their outcomes are the run's.
A real pytest run of a tiny tree (its conftest wires tests/split.py as tests/conftest.py does) with slow, realtime
and fast tests that record where they ran, at its top and in a scenarios folder, and two that fail on demand."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # real pytest runs

TESTS = Path(__file__).resolve().parent

CONFTEST = f"""
import sys
import vergence, services  # noqa: E401,F401  (as tests/conftest.py: the real packages first)
sys.path.insert(0, {str(TESTS)!r})
import split
if split.is_child():
    split.idle()
import pytest
@pytest.fixture(autouse=True)
def _turn(request):
    with split.turn(request.node.get_closest_marker("alone") is not None):
        yield
def pytest_collection_modifyitems(session, config, items):
    split.modify(config, items)
def pytest_collection_finish(session):
    split.start(session.config.rootpath)
def pytest_sessionfinish(session, exitstatus):
    split.finish(session)
def pytest_terminal_summary(terminalreporter):
    split.summary(terminalreporter)
"""

TESTS_PY = """
import json, os
import pytest

def _where(name, span=0.0):
    import time
    t0 = time.time()
    time.sleep(span)
    with open(os.environ["INNER_OUT"], "a") as f:
        f.write(json.dumps({"test": name, "pid": os.getpid(), "child": os.environ.get("VERGENCE_TESTS_CHILD"),
                            "policy": os.sched_getscheduler(0), "t0": t0, "t1": time.time()}) + "\\n")
    if os.environ.get("INNER_HANG") == "1":  # until the outer test kills the run
        import time
        time.sleep(60)

@pytest.mark.slow
def test_slow():
    _where("slow")

def test_fast():
    _where("fast")

@pytest.mark.realtime
def test_realtime():
    _where("realtime")

@pytest.mark.slow
@pytest.mark.alone
def test_alone():
    _where("alone", 0.6)

def test_fast_fails_on_demand():
    assert os.environ.get("INNER_FAIL") != "1", "failed on demand"
"""

SCENARIO_PY = """
import os
import pytest
from test_inner import _where

@pytest.mark.slow
def test_scenario_slow():
    _where("scenario_slow", 0.6)
    assert os.environ.get("INNER_FAIL_SCENARIO") != "1", "a scenario failed on demand"

def test_scenario_fast():
    _where("scenario_fast")
"""


def _tree(tmp_path: Path) -> Path:
    """The tiny tree: its pytest.ini (the markers), its conftest (tests/split.py wired in) and its tests."""
    inner = tmp_path / "inner"
    inner.mkdir(exist_ok=True)
    (inner / "pytest.ini").write_text("[pytest]\nmarkers =\n    slow: real processes\n    realtime: timing\n"
                                      "    alone: no other test of real processes beside it\n")
    (inner / "conftest.py").write_text(CONFTEST)
    (inner / "test_inner.py").write_text(TESTS_PY)
    (inner / "scenarios").mkdir(exist_ok=True)
    (inner / "scenarios" / "test_scenario.py").write_text(SCENARIO_PY)
    return inner


def _run(tmp_path: Path, *args: str, **env: str) -> tuple[subprocess.CompletedProcess, list[dict]]:
    inner = _tree(tmp_path)
    out = tmp_path / "where.jsonl"
    out.unlink(missing_ok=True)
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *args], cwd=inner,
                       env=dict(os.environ, INNER_OUT=str(out), **env), capture_output=True, text=True, timeout=120)
    return r, [json.loads(line) for line in out.read_text().splitlines()] if out.exists() else []


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="the split needs two cores")
def test_the_whole_run_runs_the_in_process_tests_beside_it_at_idle_priority(tmp_path):
    r, where = _run(tmp_path, VERGENCE_TESTS_SPLIT="1")
    assert r.returncode == 0, r.stdout + r.stderr
    by = {w["test"]: w for w in where}
    assert by["slow"]["child"] is None and by["slow"]["policy"] == os.SCHED_OTHER
    assert by["fast"]["child"] == "1" and by["fast"]["policy"] == os.SCHED_IDLE
    assert by["realtime"]["child"] is None and by["realtime"]["pid"] == by["slow"]["pid"]
    assert by["fast"]["pid"] != by["slow"]["pid"]
    assert by["scenario_slow"]["child"] == "scenarios" and by["scenario_slow"]["policy"] == os.SCHED_OTHER
    assert by["scenario_slow"]["pid"] not in (by["slow"]["pid"], by["fast"]["pid"])
    assert by["scenario_fast"]["pid"] == by["fast"]["pid"]  # the scenarios' in-process tests: with the others
    assert "at idle priority, the 3 tests of -m 'not slow and not realtime': 3 passed" in r.stdout
    assert "at normal priority, the 1 tests of the scenarios folder's -m 'slow or realtime': 1 passed" in r.stdout
    assert "3 passed" in r.stdout.strip().splitlines()[-1]  # this process's own: the slow, realtime and alone ones
    # the alone test had no test of the scenarios' pytest beside it (each sleeps 0.6 s: they would overlap)
    alone, other = by["alone"], by["scenario_slow"]
    assert alone["t1"] <= other["t0"] or other["t1"] <= alone["t0"], (alone, other)


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="the split needs two cores")
def test_a_failure_beside_the_run_fails_the_run_and_is_shown_in_full(tmp_path):
    r, _ = _run(tmp_path, VERGENCE_TESTS_SPLIT="1", INNER_FAIL="1")
    assert r.returncode == 1, r.stdout + r.stderr
    assert "the 3 tests that ran beside this run (-m 'not slow and not realtime'): exit 1" in r.stdout
    assert "failed on demand" in r.stdout and "1 failed, 2 passed" in r.stdout
    assert "3 passed" in r.stdout.strip().splitlines()[-1]
    r, _ = _run(tmp_path, VERGENCE_TESTS_SPLIT="1", INNER_FAIL_SCENARIO="1")
    assert r.returncode == 1, r.stdout + r.stderr
    assert ("the 1 tests that ran beside this run (the scenarios folder's -m 'slow or realtime'): exit 1"
            in r.stdout)
    assert "a scenario failed on demand" in r.stdout and "3 passed" in r.stdout
    assert "3 passed" in r.stdout.strip().splitlines()[-1]


def test_a_selection_or_split_0_runs_in_one_process(tmp_path):
    for args, env in ((("test_inner.py",), {}), ((), {"VERGENCE_TESTS_SPLIT": "0"}), (("-m", "not slow"), {})):
        r, where = _run(tmp_path, *args, **env)
        assert r.returncode == 0, r.stdout + r.stderr
        assert {w["child"] for w in where} == {None} and len({w["pid"] for w in where}) == 1, (args, env)
        assert "beside this run" not in r.stdout


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="the split needs two cores")
def test_the_pytest_beside_a_sigkilled_run_ends_with_it(tmp_path):
    """SIGKILL runs no reaper: the pytests beside the run end by their parent-death signal (SIGTERM) within 5 s."""
    import psutil

    inner = _tree(tmp_path)
    out = tmp_path / "where.jsonl"
    run = subprocess.Popen([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"], cwd=inner,
                           env=dict(os.environ, INNER_OUT=str(out), INNER_HANG="1", VERGENCE_TESTS_SPLIT="1"),
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            where = [json.loads(line) for line in out.read_text().splitlines()] if out.exists() else []
            if {w["child"] for w in where} >= {None, "1", "scenarios"}:  # (each hangs in its first test)
                break
            time.sleep(0.05)
        children = {w["pid"] for w in where if w["child"] is not None}
        assert len(children) == 2 and run.pid not in children and all(map(psutil.pid_exists, children))
        run.send_signal(signal.SIGKILL)
        run.wait(10)
        deadline = time.monotonic() + 5
        for child in children:
            while psutil.pid_exists(child) and psutil.Process(child).status() != psutil.STATUS_ZOMBIE:
                assert time.monotonic() < deadline, "a pytest beside the run outlived it by 5 s"
                time.sleep(0.05)
    finally:
        run.kill()
        run.wait(10)
        if out.exists():
            for w in (json.loads(line) for line in out.read_text().splitlines()):
                if psutil.pid_exists(w["pid"]):
                    try:
                        psutil.Process(w["pid"]).kill()
                    except psutil.Error:
                        pass
