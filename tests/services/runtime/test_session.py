"""A process whose router does not answer (not started yet, a wrong --connect) says so, and still stops cleanly
on SIGINT/SIGTERM: zenoh.open keeps trying, and a main thread blocked in it ran no signal handler (monitor,
worker, record and the other services ignored SIGTERM until killed)."""

from __future__ import annotations

import signal
import time

import pytest

from procs import VERGENCE, Procs, free_port, run, wait_for

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["term", "int"])
# a client's wait of at most session.SAY_QUIET_S ends in its one line, with no "still trying" before it: 60 s here
@pytest.mark.parametrize("argv", [["worker"], ["reducer"], ["record", "{tmp}/x.vrec", "--wait", "60"],
                                  ["monitor", "--wait", "60"]],
                         ids=["worker", "reducer", "record", "monitor"])
def test_waiting_for_a_router_stops_on_a_signal(tmp_path, argv, sig):
    argv = [a.format(tmp=tmp_path) for a in argv]
    with Procs(tmp_path) as P:
        p = P.spawn("client", [VERGENCE, *argv, "--connect", f"tcp/127.0.0.1:{free_port()}"])
        wait_for(lambda: "still trying (Ctrl-C stops)" in p.text(), 60, "the waiting line", logs=p.tail)
        t0 = time.monotonic()
        p.signal(sig)
        assert p.wait(10) == 0
        assert time.monotonic() - t0 < 2


def test_monitor_once_gives_up_at_its_timeout(tmp_path):
    t0 = time.monotonic()
    r = run("monitor", "--once", "--timeout", "2", "--connect", f"tcp/127.0.0.1:{free_port()}", timeout=60)
    assert r.returncode == 1 and time.monotonic() - t0 < 20
    assert r.stderr.strip().splitlines()[-1].startswith("vergence monitor: no Zenoh router or peer answered at "
                                                        "tcp/127.0.0.1:")
