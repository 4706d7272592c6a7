"""The `vergence` command itself (issue #28): --version, no command, and a reader of its stdout that goes away
(`vergence sim | head`) ending it quietly."""

from __future__ import annotations

import subprocess
import sys
from importlib import metadata

import pytest

from procs import run
pytestmark = pytest.mark.slow  # every test here runs the real command


def test_version_prints_the_installed_version_and_exits_0():
    r = run("--version", timeout=60, fresh=True)
    assert (r.returncode, r.stdout, r.stderr) == (0, f"vergence {metadata.version('vergence')}\n", "")


def test_no_command_prints_the_help_and_exits_2_and_help_exits_0():
    r = run(timeout=60, fresh=True)
    assert r.returncode == 2 and r.stdout.startswith("usage: vergence") and "--version" in r.stdout
    r = run("-h", timeout=60, fresh=True)
    assert r.returncode == 0 and r.stdout.startswith("usage: vergence") and "COMMAND" in r.stdout


@pytest.mark.parametrize("argv", [["--json"], []], ids=["flushed-lines", "buffered"])
def test_a_closed_pipe_ends_the_command_quietly_with_141(argv):
    """`vergence sim | head -n 1`: no BrokenPipeError traceback, the status of a command ended by SIGPIPE (141).
    --json flushes every line (the pipe breaks in the loop); without, the buffer breaks it in the loop or at
    the last flush."""
    cmd = " ".join([sys.executable, "-m", "services.ops.cli", "sim", "--frames", "2000", "--size", "160x120", *argv])
    r = subprocess.run(["bash", "-c", f"{cmd} | head -n 1; exit ${{PIPESTATUS[0]}}"], capture_output=True,
                       text=True, timeout=120)
    assert r.stdout.startswith("{" if argv else "frame   0")
    assert "Traceback" not in r.stderr and "BrokenPipe" not in r.stderr, r.stderr[-2000:]
    assert r.returncode == 141, (r.returncode, r.stderr[-2000:])


def test_ctrl_c_while_a_command_still_imports_ends_it_quietly_with_130():
    """`vergence up` stops a child it just started (a standby, say) with SIGINT while that child still imports numpy and
    zenoh: exit 130, no traceback. The SIGINT goes at the child's first heartbeat, as up would see it: main() has
    begun and the reducer's imports (0.4 s or more here) are under way. (A fixed 0.2 s once fell before the
    interpreter had its own SIGINT handler on a loaded machine: killed by the signal, -2, not what is under test.)"""
    import os
    import select
    import signal

    from services.runtime import heartbeat

    r, w = os.pipe()
    env = {**os.environ, heartbeat.ENV: f"{w},0"}
    p = subprocess.Popen([sys.executable, "-m", "services.ops.cli", "reducer", "--connect", "tcp/127.0.0.1:9"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, pass_fds=(w,))
    os.close(w)
    try:
        assert select.select([r], [], [], 30)[0], "no heartbeat within 30 s"
        assert os.read(r, 1) == b"h"
    finally:
        os.close(r)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=30)
    assert (p.returncode, "Traceback" in err) == (130, False), err[-2000:]
