"""The test tree mirrors the code: tests/vergence/ tests the library (vergence/*.py, motors/, sim/), tests/services/
the services (processes, the CLI, the deployment); tests/ itself holds the project-wide checks (lint, install,
layout, the split run) and the helpers the test files share (procs, emulators, middlebury, cdp, deploy_helpers,
references, samples), imported by their bare names.

pytest runs in importlib mode (pyproject.toml), so two test files may share a name in different folders (e.g.
tests/vergence/test_monitor.py and tests/services/observe/test_monitor.py) and no test folder is a package; this
file puts tests/ on sys.path for the helpers. The real vergence and services are imported first: on sys.path,
the folder tests/vergence/ would otherwise be a namespace-package candidate for the name `vergence`."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

import vergence  # noqa: F401  (before tests/ is on sys.path: see above)
import services  # noqa: F401

HERE = str(Path(__file__).resolve().parent)
if HERE not in sys.path:
    sys.path.insert(0, HERE)

# the reaper: on SIGTERM or SIGINT, and at the session's end, every process the run started ends (tests/reaper.py)
from reaper import pytest_configure, pytest_runtest_setup, pytest_unconfigure  # noqa: E402, F401

import background  # noqa: E402
import split  # noqa: E402

if split.is_child():  # the in-process tests' pytest beside a whole run (tests/split.py): idle priority
    split.idle()
from services.runtime import warm  # noqa: E402  (no numba: compiled() only looks at the cache)

# Where the environment says not to write bytecode (PYTHONDONTWRITEBYTECODE, as this machine and its CI do), every
# process the tests start would compile vergence and services from source at each start (the editable install leaves
# them uncompiled): compiled once here, the processes read the .pyc (each import checks it against its source).
if sys.flags.dont_write_bytecode:
    import compileall

    for _pkg in ("vergence", "services"):
        compileall.compile_dir(str(Path(HERE).parent / _pkg), quiet=1, workers=0)

# On a fresh install the kernels are compiled once, in a process of their own, while pytest collects (as `vergence up`
# does on a first start: else the first processes of the tests all compile them at once, inside timed tests, and the
# in-process tests compile them too); pytest_collection_finish waits for it.
_T0 = time.monotonic()
_compile = None if warm.compiled() else subprocess.Popen([sys.executable, "-m", "services.runtime.warm"],
                                                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def pytest_collection_finish(session):
    """The kernels compiled (see above) before the first test; then, in a run of the whole suite, the in-process tests
    start beside it in a pytest of their own (tests/split.py), and the slow tests' long computations in the
    background, ahead of the tests (tests/background.py)."""
    if _compile is not None and _compile.returncode is None:
        t0 = time.monotonic()
        _, err = _compile.communicate(timeout=600)
        print(f"\ncompiled the kernels once while the tests were collected (numba's cache was empty): "
              f"{time.monotonic() - _T0:.1f} s, {time.monotonic() - t0:.1f} s of it after the collection"
              + ("" if _compile.returncode == 0 else f", failed (exit {_compile.returncode}): {err[-500:]}"))
    split.start(session.config.rootpath)
    background.start(session.items)


@pytest.fixture(autouse=True)
def _turn(request):
    """In a whole run, a test marked `alone` has no test of the other pytest of real processes beside it
    (split.turn)."""
    with split.turn(request.node.get_closest_marker("alone") is not None):
        yield


def pytest_collection_modifyitems(session, config, items):
    split.modify(config, items)  # a run of the whole suite: the tests of real processes here, the others beside


def pytest_sessionfinish(session, exitstatus):
    split.finish(session)
    background.stop()


def pytest_terminal_summary(terminalreporter):
    split.summary(terminalreporter)


@pytest.fixture
def tiny_fs(tmp_path):
    """A 1 MiB tmpfs mounted at tmp_path/small for the test, unmounted after it (a full disk, for the writers'
    tests); skips where it cannot be mounted (not root)."""
    if os.geteuid() != 0:
        pytest.skip("mounting a 1 MiB tmpfs needs root")
    mnt = tmp_path / "small"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)
