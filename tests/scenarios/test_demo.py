"""The README's first command as a new user runs it: `vergence up` with no options shows the job in the
project's name, a target moving in depth and the slave following it, within 20 s of the command; the monitor
shows the truth beside the pan, and the truth follows the fovea where `vergence fixate` moves it (issue #28)."""

from __future__ import annotations

import math
import re
import shutil
import time

import pytest

from procs import VERGENCE, Procs, free_port, run, tmux, wait_for

pytestmark = pytest.mark.slow

PAN_HISTORY = re.compile(r"pan history +\(([-+]\d+\.\d+)°\.\.([-+]\d+\.\d+)°, \d+ s\)")
TRACKING = re.compile(r"tracking over the last 5 s: the frames' pans are (\d+\.\d+) px RMS off the truth")
TRUTH = re.compile(r"truth +([-+]\d+\.\d+)° \(")


@pytest.mark.skipif(shutil.which("tmux") is None, reason="needs tmux (apt-get install tmux)")
def test_up_with_no_options_follows_a_target_moving_in_depth(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # the one option: not to meet a router of this machine's
    name = f"vergence-demo-{tmp_path.name}"[:60].replace(".", "-")
    with Procs(tmp_path) as P:
        P.endpoint = endpoint
        t0 = time.monotonic()
        up = P.start("up", "up", "--listen", endpoint, connect=False, rig=False)
        P.wait_port(20)
        tmux("new-session", "-d", "-s", name, "-x", "100", "-y", "45",
              f"{VERGENCE} monitor --connect {endpoint} --refresh 0.3; sleep 30")
        try:
            def screen() -> str:
                return tmux("capture-pane", "-p", "-J", "-t", name)

            def following(text: str) -> str | None:
                """The screen once the slave follows: its pans over more than a degree (the target moves),
                within 1.5 px RMS of the truth over the last 5 s."""
                span, err = PAN_HISTORY.search(text), TRACKING.search(text)
                if span and err and float(span.group(2)) - float(span.group(1)) > 1.0 and float(err.group(1)) < 1.5:
                    return text
                return None

            first = wait_for(lambda: following(screen()), 40, "the slave following the target", logs=P.logs)
            took = time.monotonic() - t0
            print(f"following {took:.1f} s after `vergence up`\n{first}")
            assert took < 20, first
            assert "truth history (" in first and "status ok" in first, first
            truth_before = float(TRUTH.search(first).group(1))
            assert -7.5 < truth_before < -2.5, first  # the target, between 0.5 and 1.1 m: -6.8..-3.1 deg

            # the fovea to the background left of the target (3 m away): the truth goes with it, and the slave
            r = run("fixate", "40,240", "--connect", endpoint, "--wait", "10", timeout=30)
            assert r.returncode == 0, r.stderr
            u = (40 - 320) / 512
            there = math.degrees(math.atan2(3 * u - 0.06, 3) - math.atan(u))  # -0.875 deg

            def moved(text: str) -> str | None:
                t = TRUTH.search(text)
                return (text if "fovea (40, 240)" in text and t and abs(float(t.group(1)) - there) < 0.01
                        and (e := TRACKING.search(text)) and float(e.group(1)) < 1.5 else None)

            after = wait_for(lambda: moved(screen()), 20, "the truth and the slave at the new fovea", logs=P.logs)
            print(after)
        finally:
            tmux("kill-session", "-t", name, check=False)
    assert up.poll() is not None
