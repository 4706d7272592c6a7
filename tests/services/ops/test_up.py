"""`vergence up` and `vergence router` on a port that is already taken: a clear error, nothing started; and
up's supervision of its children (back-off, counts, shutdown) on small real processes. The SIGKILL of each
child of a real `vergence up` is in tests/scenarios/test_supervise.py."""

from __future__ import annotations

import itertools
import logging
import re
import subprocess
import sys
import threading
import time

import pytest

from procs import Procs, run, wait_for

pytestmark = pytest.mark.slow  # every test here runs real processes


def test_busy_port_is_refused_with_a_hint(tmp_path):
    with Procs(tmp_path) as P:
        P.router()
        up = run("up", "--listen", P.endpoint, timeout=30)
        assert up.returncode == 2 and f"{P.endpoint} is already in use" in up.stderr
        assert "started" not in up.stderr  # no child was started
        router = run("router", "--listen", P.endpoint, timeout=30)
        assert router.returncode == 2
        assert router.stderr.startswith("vergence router: cannot start on")
        assert "Address already in use" in router.stderr
        assert "Traceback" not in router.stderr


RUNS_ON = "import time; time.sleep(60)"  # a child's code, not a wait of the test: a service that runs on


def _child(name: str, code: str, sup=None):
    from services.ops import up

    return up.Child(name, [sys.executable, "-c", code], sup=sup)


def _supervise_until(children, stop, cond, timeout: float) -> int:
    """Run up.supervise in this thread until cond() holds (checked from a timer thread) or timeout."""
    from services.ops import up

    def watch():
        try:
            wait_for(lambda: cond() or stop.is_set(), timeout, "the condition")
        except TimeoutError:
            pass
        stop.set()

    threading.Thread(target=watch, daemon=True).start()
    try:
        return up.supervise(children, stop, poll_s=0.01)
    finally:
        up.stop_all(children)


def test_a_dead_child_is_restarted_with_a_doubling_back_off(caplog):
    from services.runtime import session

    starts = []
    c = _child("flaky", "import sys; sys.exit(1)")
    c.start()
    orig = c.start

    def start():
        orig()
        starts.append(time.monotonic())

    c.start = start
    stop = session.Stop(install=False)
    with caplog.at_level(logging.INFO, logger="vergence.up"):
        assert _supervise_until([c], stop, lambda: len(starts) >= 4, 20) == 0
    assert c.restarts == len(starts) >= 4
    gaps = [b - a for a, b in itertools.pairwise(starts)]
    for gap, backoff in zip(gaps, (0.4, 0.8, 1.6)):  # each wait after its predecessor's exit, doubled
        assert backoff <= gap < backoff + 1.0, gaps  # + the child's own run (a python start)
    lines = [r.getMessage() for r in caplog.records]
    assert sum("flaky (pid" in m and "exited with 1" in m for m in lines) >= 4
    assert [m.rsplit("restarting in ", 1)[1] for m in lines if "restarting in" in m][:4] == \
        ["0.2 s", "0.4 s", "0.8 s", "1.6 s"]
    assert [m.split("restart ", 1)[1].split(";")[0] for m in lines if m.startswith("restarted flaky")] == \
        [str(i) for i in range(1, c.restarts + 1)]  # one line per restart, counted


def test_the_back_off_caps_and_resets_after_a_stable_run(monkeypatch, caplog):
    from services.runtime import session
    from services.ops import up

    from vergence.config import SuperviseSettings

    sup = SuperviseSettings(restart_s=0.1, restart_max_s=0.4)  # [supervise], scaled down from 0.2 and 5.0
    quick = _child("quick", "import sys; sys.exit(1)", sup)
    quick.start()
    stop = session.Stop(install=False)
    with caplog.at_level(logging.INFO, logger="vergence.up"):
        _supervise_until([quick], stop, lambda: quick.restarts >= 5, 20)
    waits = [r.getMessage().rsplit("restarting in ", 1)[1] for r in caplog.records if "restarting in" in r.getMessage()]
    assert waits[:5] == ["0.1 s", "0.2 s", "0.4 s", "0.4 s", "0.4 s"]  # doubled, then capped

    monkeypatch.setattr(up, "STABLE_S", 0.3)  # a child that ran 0.3 s has been stable
    caplog.clear()
    steady = _child("steady", "import sys, time; time.sleep(0.4); sys.exit(1)", sup)  # time under test: runs 0.4 s
    steady.start()
    steady.backoff = 0.4  # as after several quick deaths
    with caplog.at_level(logging.INFO, logger="vergence.up"):
        _supervise_until([steady], session.Stop(install=False), lambda: steady.restarts >= 2, 20)
    waits = [r.getMessage().rsplit("restarting in ", 1)[1] for r in caplog.records if "restarting in" in r.getMessage()]
    assert waits[:2] == ["0.1 s", "0.1 s"]  # every exit after a stable run: the first back-off again


def test_no_restart_during_shutdown_and_exit_2_at_first_start_stops_up(caplog):
    from services.runtime import session

    runner = _child("runner", RUNS_ON)
    runner.start()
    stop = session.Stop(install=False)
    stop.set()  # SIGINT already received: supervise returns, stop_all stops the child, nothing restarted
    assert _supervise_until([runner], stop, lambda: True, 5) == 0
    assert runner.restarts == 0 and runner.p.returncode is not None
    bad = _child("bad", "import sys; sys.exit(2)")
    other = _child("other", RUNS_ON)
    bad.start()
    other.start()
    with caplog.at_level(logging.INFO, logger="vergence.up"):
        assert _supervise_until([bad, other], session.Stop(install=False), lambda: False, 20) == 2
    assert bad.restarts == 0 and other.p.returncode is not None  # all stopped
    assert any("bad (pid" in r.getMessage() and "refused its options" in r.getMessage() for r in caplog.records)


def test_a_standby_takes_over_at_once_and_leaves_when_up_stops(monkeypatch, caplog):
    from services.runtime import session
    from services.ops import up

    monkeypatch.setattr(up, "STANDBY_DELAY_S", 0.2)
    # a child that, as every service, waits in session.open_session's standby hook before its work
    c = _child("svc", "from services.runtime import session; session._standby(); " + RUNS_ON)
    c.standby_due = 0.0
    c.start()
    stop = session.Stop(install=False)
    first = c.p
    killed = []

    def cond():
        if c.standby is not None and c.standby.ready and not killed:
            killed.append(c.standby.p.pid)
            first.kill()
        return killed and c.p.pid == killed[0] and c.standby is not None and c.standby.ready

    with caplog.at_level(logging.INFO, logger="vergence.up"):
        assert _supervise_until([c], stop, cond, 30) == 0
    lines = [r.getMessage() for r in caplog.records]
    assert any(f"svc (pid {first.pid}) exited with -9" in m and f"its standby (pid {killed[0]}, ready) takes over, "
               "restart 1; restarts: svc 1" in m for m in lines), lines
    assert c.restarts == 1 and not any(m.startswith("restarted svc") for m in lines)  # no fresh start
    assert sum(m.startswith("started a standby of svc") for m in lines) == 2  # and another standby after it
    assert not any("did not stop" in m for m in lines)  # the waiting standby left when its pipe closed
    assert c.p.returncode is not None


BEATS = "from services.runtime import heartbeat; heartbeat.start(); "  # what cli.main does first


def test_a_child_whose_heartbeat_stops_is_killed_and_restarted(caplog):
    """Liveness by heartbeat (issue #29): a child that SIGSTOPs itself after 0.5 s, one that never beats (past
    start_grace_s) and one whose loop stops turning (past stall_s) are each SIGKILLed and restarted, the log
    saying why; the stopped one is gone (not left stopped)."""
    from vergence.config import SuperviseSettings
    from services.runtime import session
    from services.ops import up

    sup = SuperviseSettings(heartbeat_s=0.3, start_grace_s=1.0, stall_s=0.6)
    stops = up.Child("stops", [sys.executable, "-c", BEATS + "import os, signal, time; time.sleep(0.5); "
                                                            "os.kill(os.getpid(), signal.SIGSTOP)"], sup=sup)
    mute = up.Child("mute", [sys.executable, "-c", RUNS_ON], sup=sup)
    stalls = up.Child("stalls", [sys.executable, "-c", BEATS + "heartbeat.progress(); " + RUNS_ON], sup=sup)
    children = [stops, mute, stalls]
    for c in children:
        c.start()
    first = {c.name: c.p for c in children}
    stop = session.Stop(install=False)
    with caplog.at_level(logging.INFO, logger="vergence.up"):
        assert _supervise_until(children, stop, lambda: all(c.restarts >= 1 for c in children), 30) == 0
    lines = [r.getMessage() for r in caplog.records]
    print("\n".join(lines))
    pid = {n: p.pid for n, p in first.items()}
    for name, why in (("stops", r"no heartbeat for 0\.[3-6] s \(stopped or hung\)"),
                      ("mute", r"no first heartbeat within 1\.[0-3] s of its start"),
                      ("stalls", r"no heartbeat for 0\.[3-6] s \(stopped or hung\)")):
        assert any(re.fullmatch(rf"{name} \(pid {pid[name]}\): {why}: SIGKILL", m) for m in lines), (name, lines)
        assert any(re.match(rf"{name} \(pid {pid[name]}\) was killed by up \({why}\) after [\d.]+ s: restarting "
                            r"in 0\.2 s", m) for m in lines), (name, lines)
        assert first[name].returncode == -9  # reaped: no stopped process left behind
    ran = {n: float(re.search(rf"{n} \(pid {pid[n]}\) was killed by up \(.*\) after ([\d.]+) s", "\n".join(lines))[1])
           for n in pid}
    # killed heartbeat_s after its last beat, which came up to one BEAT_S (0.1 s) before it stopped (and the log
    # rounds to 0.1 s)
    assert 0.5 + 0.3 - 0.15 <= ran["stops"] < 0.5 + 0.3 + 1.0
    assert 1.0 <= ran["mute"] < 2.0
    assert 0.6 + 0.3 - 0.15 <= ran["stalls"] < 0.6 + 0.3 + 1.0  # stall_s after its progress, then heartbeat_s


def test_a_slow_spawn_does_not_eat_the_start_grace(caplog, monkeypatch):
    """The start grace counts from when the child exists, as its "after N s" does: a fork and exec that took 0.3 s
    (a loaded machine's 0.1 s once killed a mute child "after 0.9 s" of its 1 s grace) leave it its whole grace."""
    from vergence.config import SuperviseSettings
    from services.runtime import session
    from services.ops import up

    slow = up.Proc

    def proc(*a, **k):
        time.sleep(0.3)
        return slow(*a, **k)

    monkeypatch.setattr(up, "Proc", proc)
    mute = up.Child("mute", [sys.executable, "-c", RUNS_ON], sup=SuperviseSettings(heartbeat_s=0.3, start_grace_s=0.5))
    mute.start()
    pid = mute.p.pid
    with caplog.at_level(logging.INFO, logger="vergence.up"):
        assert _supervise_until([mute], session.Stop(install=False), lambda: mute.restarts >= 1, 30) == 0
    ran = float(re.search(rf"mute \(pid {pid}\) was killed by up \(no first heartbeat within 0\.[5-9] s of its start\) "
                          r"after ([\d.]+) s", "\n".join(r.getMessage() for r in caplog.records))[1])
    assert 0.5 <= ran < 1.5


def test_a_busy_child_that_beats_is_not_killed(caplog):
    """A child busy in Python (a compile, a heavy frame: the main thread never sleeps) for 2 s, 6 times its
    heartbeat_s, keeps beating from its thread: it ends by itself, never killed."""
    from vergence.config import SuperviseSettings
    from services.runtime import session
    from services.ops import up

    sup = SuperviseSettings(heartbeat_s=0.3, start_grace_s=5.0, stall_s=0)
    busy = up.Child("busy", [sys.executable, "-c", BEATS + "import time\nt = time.monotonic()\n"
                                                           "while time.monotonic() - t < 2.0: sum(range(10000))"],
                    sup=sup)
    busy.start()
    stop = session.Stop(install=False)
    with caplog.at_level(logging.INFO, logger="vergence.up"):
        assert _supervise_until([busy], stop, lambda: busy.restarts >= 1, 30) == 0
    lines = [r.getMessage() for r in caplog.records]
    assert any(re.match(r"busy \(pid \d+\) exited with 0 after 2\.\d s", m) for m in lines), lines
    assert not any("heartbeat" in m for m in lines), lines


def test_a_hung_standby_is_killed_and_another_started(monkeypatch, caplog):
    """A standby beats while it waits its turn; one SIGSTOPped is SIGKILLed (it could not take over) and a
    fresh one follows after the back-off, while the child itself runs on."""
    import os
    import signal

    from vergence.config import SuperviseSettings
    from services.runtime import session
    from services.ops import up

    monkeypatch.setattr(up, "STANDBY_DELAY_S", 0.2)
    sup = SuperviseSettings(heartbeat_s=0.3, start_grace_s=5.0, stall_s=0, restart_max_s=0.5)
    c = up.Child("svc", [sys.executable, "-c", BEATS + "from services.runtime import session; session._standby(); "
                         + RUNS_ON], sup=sup)
    c.standby_due = 0.0
    c.start()
    stop = session.Stop(install=False)
    stopped = []

    def cond():
        if c.standby is not None and c.standby.ready and not stopped:
            stopped.append(c.standby.p.pid)
            os.kill(stopped[0], signal.SIGSTOP)
        return stopped and c.standby is not None and c.standby.p.pid != stopped[0] and c.standby.ready

    with caplog.at_level(logging.INFO, logger="vergence.up"):
        assert _supervise_until([c], stop, cond, 30) == 0
    lines = [r.getMessage() for r in caplog.records]
    assert any(re.fullmatch(rf"standby of svc \(pid {stopped[0]}\): no heartbeat for 0\.[3-6] s \(stopped or hung\): "
                            "SIGKILL", m) for m in lines), lines
    assert any(m.startswith(f"standby of svc (pid {stopped[0]}) exited with -9") for m in lines), lines
    assert sum(m.startswith("started a standby of svc") for m in lines) == 2 and c.restarts == 0


def _up(*args: str, cwd=None) -> tuple[subprocess.CompletedProcess, float]:
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "services.ops.cli", "up", *args], capture_output=True, text=True,
                       timeout=60, cwd=cwd)
    return r, time.monotonic() - t0


@pytest.mark.parametrize("args,says", [
    (["--driver", "foo"], "vergence up: error: argument --driver: invalid choice: 'foo' (choose from 'sim', "
                          "'dynamixel', 'line', 'ros2')"),
    (["--rate", "-5"], "vergence up: error: argument --rate: must be from 0 to 1000 (0: as fast as possible), "
                       "got '-5'"),
    (["--port", "/dev/ttyUSB9"], "vergence up: --port applies to a real driver (dynamixel, line, ros2); the sim "
                                 "driver has no port"),
    (["--config", "bad.toml"], "vergence up: bad.toml: capture.rate_hz: must be from 0 to 1000 (0: as fast as "
                               "the source gives them), got -5.0"),
])
def test_nonsense_is_refused_before_any_child_starts(tmp_path, args, says):
    """Exit 2 within seconds, one line naming the option (or table.key) and what it may be; no child started:
    nobody listens on up's --listen port, and up logged no start."""
    from services.ops.launch import accepts, free_port

    (tmp_path / "bad.toml").write_text("[capture]\nrate_hz = -5\n")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    r, took = _up("--listen", endpoint, *args, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines()[-1] == says
    assert "started" not in r.stderr and "Traceback" not in r.stderr
    assert not accepts(endpoint)
    assert took < 15


@pytest.mark.parametrize("argv,toml,says", [
    (["--source", "foo:x"], "", "--source: unknown source 'foo:x': want files:LEFT,RIGHT"),
    (["--source", "files:nope_l.png,nope_r.png"], "", "--source: source files: nope_l.png: no such file"),
    (["--source", "sim:bogus=1"], "", "--source: sim source: unknown key 'bogus'"),
    (["--source", "sim:latency=5"], "", "--source: sim source: latency: must be from 0 to 1"),
    (["--source", "ros2:a"], "", "--source: source ros2:'a': want ros2:LEFT_TOPIC,RIGHT_TOPIC"),
    ([], '[capture]\nsource = "video:nope.mp4"\n', "[capture] source: source video:'nope.mp4': want video:LEFT,RIGHT"),
    (["--driver", "dynamixel"], "", "driver 'dynamixel' needs a serial port: pass --port URL"),
    ([], '[actuator]\ndriver = "line"\n', "driver 'line' needs a serial port"),
    (["--driver", "sim", "--port", "loop://"], "", "--port applies to a real driver (dynamixel, line, ros2)"),
    (["--no-actuator", "--port", "loop://"], "", "--port applies to the actuator, which --no-actuator does not"),
    (["--no-actuator", "--driver", "line"], "", "--driver applies to the actuator, which --no-actuator does not"),
    (["--rig", "a/b"], "", "--rig: rig 'a/b'"),
    (["--source", "sim:stall=1-2", "--driver", "ros2", "--port", "c"], "",
     "the source's stall=1-2 makes the sim actuator lie: run it (--driver sim, no --no-actuator)"),
    (["--source", "sim:encoder_noise=0.1", "--no-actuator"], "", "the source's encoder_noise=0.1 makes the sim actu"),
    (["--source", "sim:stall=2-1"], "", "--source: sim source: stall"),
])
def test_up_checks_what_it_would_hand_its_children(tmp_path, monkeypatch, argv, toml, says):
    """up.check: the source (without opening a camera or a file), the driver and its port, an option that does
    not apply; up.run refuses with it before it starts anything."""
    from services.ops import cli, up
    from vergence.config import load

    monkeypatch.chdir(tmp_path)
    conf = tmp_path / "v.toml"
    conf.write_text(toml)
    args = cli.build_parser("up").parse_args(["up", "--config", str(conf), *argv])
    assert (up.check(args, load(conf)) or "").startswith(says)


def test_up_passes_what_its_children_take():
    from services.ops import cli, up
    from vergence.config import load

    for ok in ([], ["--driver", "line", "--port", "loop://", "--source", "camera:0,1"],
               ["--driver", "ros2", "--port", "ctrl", "--no-standby", "--source", "sim:focal=500", "--rate", "0"],
               ["--no-actuator", "--source", "ros2:/l,/r"]):
        assert up.check(cli.build_parser("up").parse_args(["up", *ok]), load(None)) is None, ok


def test_up_gives_the_sim_sources_motor_lies_to_the_sim_actuator(tmp_path):
    """`--source sim:...:stall=T0-T1:encoder_noise=DEG`: the actuator's argv carries them (--faults), the capture's the
    whole spec (it renders where the shaft is and reads each frame's pan as the noisy encoder would); none without."""
    from services.ops import cli, up
    from vergence.io.sources import motor_faults

    spec = "sim:focal=500:freeze=1-2:encoder_noise=0.05:stall=3-4.5"
    args = cli.build_parser("up").parse_args(["up", "--source", spec])
    assert motor_faults(spec) == "stall=3-4.5:encoder_noise=0.05"
    children = dict(up.commands(args, "head", motor_faults(spec)))
    assert children["actuator"][-2:] == ["--faults", "stall=3-4.5:encoder_noise=0.05"]
    assert children["capture"][-2:] == ["--source", spec]
    assert "--faults" not in dict(up.commands(args, "head", motor_faults("sim:freeze=1-2")))["actuator"]
    assert motor_faults("files:a.png,b.png") == ""


def test_a_bad_driver_in_the_settings_is_refused_naming_actuator_driver(tmp_path):
    from vergence.config import ConfigError, load

    (tmp_path / "v.toml").write_text('[actuator]\ndriver = "foo"\n')
    with pytest.raises(ConfigError, match=r"actuator\.driver: must be one of sim, dynamixel, line, ros2, got 'foo'"):
        load(tmp_path / "v.toml")
