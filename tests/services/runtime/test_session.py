"""A process whose router does not answer (not started yet, a wrong --connect) says so, and still stops cleanly
on SIGINT/SIGTERM: zenoh.open keeps trying, and a main thread blocked in it ran no signal handler (monitor,
worker, record and the other services ignored SIGTERM until killed)."""

from __future__ import annotations

import signal
import time

import pytest

from procs import VERGENCE, Procs, free_port, run, wait_for

pytestmark = pytest.mark.slow


# a client's wait of at most session.SAY_QUIET_S ends in its one line, with no "still trying" before it: 60 s here
CLIENTS = {"worker": ["worker"], "reducer": ["reducer"], "record": ["record", "{tmp}/x.vrec", "--wait", "60"],
           "monitor": ["monitor", "--wait", "60"]}
SIGNALS = {"term": signal.SIGTERM, "int": signal.SIGINT}


@pytest.fixture(scope="module")
def waiting(tmp_path_factory):
    """Every client of CLIENTS twice (one for each signal), all started at once, each waiting for a router that does
    not answer (each says it is still trying after SAY_WAITING_S): the tests below signal one each."""
    tmp = tmp_path_factory.mktemp("waiting")
    with Procs(tmp) as P:
        yield {(name, sig): P.spawn(f"{name}-{sig}", [VERGENCE, *[a.format(tmp=tmp) for a in argv],
                                                      "--connect", f"tcp/127.0.0.1:{free_port()}"])
               for name, argv in CLIENTS.items() for sig in SIGNALS}


@pytest.mark.parametrize("sig", list(SIGNALS))
@pytest.mark.parametrize("name", list(CLIENTS))
def test_waiting_for_a_router_stops_on_a_signal(waiting, name, sig):
    p = waiting[name, sig]
    wait_for(lambda: "still trying (Ctrl-C stops)" in p.text(), 60, "the waiting line", logs=p.tail)
    t0 = time.monotonic()
    p.signal(SIGNALS[sig])
    assert p.wait(10) == 0
    assert time.monotonic() - t0 < 2


def test_monitor_once_gives_up_at_its_timeout(tmp_path):
    t0 = time.monotonic()
    r = run("monitor", "--once", "--timeout", "2", "--connect", f"tcp/127.0.0.1:{free_port()}", timeout=60)
    assert r.returncode == 1 and time.monotonic() - t0 < 20
    assert r.stderr.strip().splitlines()[-1].startswith("vergence monitor: no Zenoh router or peer answered at "
                                                        "tcp/127.0.0.1:")


STOP_SCRIPT = r"""
import os, signal, sys, threading
from services.runtime.session import Stop
stop = Stop()
# the main thread inside the event's lock (as Event.wait or a first handler's Event.set hold it between two bytecodes)
# when the signal's handler runs: the lock is not reentrant, so a handler that set the event itself hung for good
with stop.event._cond:
    os.kill(os.getpid(), signal.SIGTERM)
    for _ in range(1000):  # bytecodes: the handler runs between two of them
        pass
sys.exit(0 if stop.wait(5) else 3)
"""


@pytest.mark.parametrize("times", [1, 3])
def test_a_signal_that_comes_while_the_main_thread_holds_the_stops_lock_still_stops_it(times):
    """`vergence up` hung for good after SIGINT and then SIGTERM (a `timeout` forwarding its own signal): the second
    signal's handler ran inside the first one's Event.set, holding the event's lock, and waited for it forever (its
    children exited, never reaped). The handler no longer takes the lock itself. Here the main thread holds it when
    1 or 3 signals arrive: the process stops within its 5 s wait (before: hung until the timeout killed it)."""
    import subprocess
    import sys

    script = STOP_SCRIPT.replace("os.kill(os.getpid(), signal.SIGTERM)",
                                 "; ".join(["os.kill(os.getpid(), signal.SIGTERM)"] * times))
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=30,
                       cwd=str(__import__("pathlib").Path(__file__).resolve().parents[3]))
    assert r.returncode == 0, r.stderr


THREADS_SCRIPT = r"""
import json, os, sys, time
from services.runtime import session
import zenoh
a = zenoh.open(session.zenoh_config("peer", listen=[sys.argv[1]]))
b = zenoh.open(session.zenoh_config("peer", connect=[sys.argv[1]]))
deadline = time.monotonic() + 10
while not b.info.peers_zid() and time.monotonic() < deadline:
    time.sleep(0.02)
def threads():
    return sorted(open(f"/proc/self/task/{t}/comm").read().strip() for t in os.listdir("/proc/self/task"))
while not set(sys.argv[2].split(",")) <= set(names := threads()) and time.monotonic() < deadline:
    time.sleep(0.02)  # (tokio starts a runtime's workers as work comes: rx-1 may come a little after the link)
print(json.dumps({"env": os.environ["ZENOH_RUNTIME"], "threads": names, "linked": bool(b.info.peers_zid())}))
b.close(); a.close()
"""


@pytest.mark.parametrize("user", [None, "(rx: (worker_threads: 2))"], ids=["ours", "the user's"])
def test_zenoh_reads_the_links_on_one_thread_of_its_own_unless_the_user_says_otherwise(user):
    """session.ZENOH_RUNTIME: one rx thread reads every link and runs the link set-up (net, acc) too: no net or acc
    thread; sending keeps its tx thread. zenoh's default has net-0 and acc-0. A ZENOH_RUNTIME the user set is kept."""
    import json
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    if user:
        env["ZENOH_RUNTIME"] = user
    want = "rx-0,rx-1,net-0,acc-0" if user else "rx-0,tx-0"  # (waited for: a loaded machine starts them late)
    r = subprocess.run([sys.executable, "-c", THREADS_SCRIPT, f"tcp/127.0.0.1:{free_port()}", want], env=env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got["linked"]
    names = set(got["threads"])
    if user is None:
        from services.runtime import session

        assert got["env"] == session.ZENOH_RUNTIME
        # (tokio names its blocking threads like the workers: rx-1 and on may be those, so the names tell no count)
        assert {"rx-0", "tx-0"} <= names and not {n for n in names if n.startswith(("net-", "acc-"))}, names
    else:
        assert got["env"] == user and {"rx-0", "rx-1", "net-0", "acc-0"} <= names, names
