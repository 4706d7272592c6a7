"""Router restart while the pipeline runs: capture, worker, reducer and actuator reconnect by themselves and
commands resume. Measured: from the new router's start to the first command of a frame captured after it,
and the whole gap in commands, with the router down 0.5 s and 3 s (zenoh's default reconnection backs off to
seconds; services.runtime.session (services/runtime/session.py) and the deployed configs retry every 0.1-0.5 s).
Target: within 2 s of the restart.

Two set-ups: the services' own defaults (plain tcp, session.zenoh_config) and the deployed configs
(deploy/router-tls.json5 and the per-role client configs of make-certs.sh: mutual TLS, user/password, ACL)."""

from __future__ import annotations

import json
import signal
import sys
import time

import cv2
import numpy as np
import pytest
from deploy_helpers import client_config_file, client_session, make_secrets, router_config, start_router
from procs import VERGENCE, Procs, free_port, wait_for

from vergence.wire.messages import Command, MotorState

pytestmark = pytest.mark.slow  # every test here runs real processes

RATE = 30
TARGET_S = 2.0
ROLES = ("capture", "worker", "reducer", "actuator")


@pytest.fixture(scope="module")
def secrets(tmp_path_factory):
    return make_secrets(tmp_path_factory.mktemp("secrets"), "localhost", "127.0.0.1")


def _pair(tmp_path) -> str:
    rng = np.random.default_rng(3)
    base = cv2.GaussianBlur(rng.integers(0, 256, (120, 360), np.uint8), (5, 5), 1.5)
    cv2.imwrite(str(tmp_path / "l.png"), base[:, 20:340])
    cv2.imwrite(str(tmp_path / "r.png"), base[:, 8:328])
    return f"files:{tmp_path / 'l.png'},{tmp_path / 'r.png'}"


@pytest.mark.parametrize("variant,down_s", [("plain", 0.5), ("plain", 3.0), ("tls", 3.0)])
def test_router_restart_commands_resume(tmp_path, secrets, variant, down_s):
    settings = tmp_path / "settings.toml"
    settings.write_text("[network]\nmax_window = 0\n[capture]\npreview_hz = 0\n")
    rig = "restart"
    with Procs(tmp_path, rig=rig) as P:
        if variant == "plain":
            port = free_port()
            endpoint = f"tcp/127.0.0.1:{port}"
            router_argv = [VERGENCE, "router", "--listen", endpoint]
            P.endpoint, P.port = endpoint, port
            router = P.spawn("router", router_argv)
            P.wait_port(15)

            def zenoh_args(role):
                return ["--connect", endpoint]

            def observer():  # with the services' own client settings (it must reconnect as fast as they do)
                import zenoh

                from services.runtime import session as zsession

                s = zenoh.open(zsession.zenoh_config("client", [endpoint]))
                P._sessions.append(s)
                return s
        else:
            conf, endpoint = router_config("tls", secrets, tmp_path / "router.json5")
            router = start_router(P, conf, endpoint)
            router_argv = router.argv

            def zenoh_args(role):
                return ["--zenoh-config", str(client_config_file(secrets, role, "tls", endpoint,
                                                                 tmp_path / f"{role}.json5"))]

            def observer():
                s = client_session(secrets, "monitor", "tls", endpoint, timeout_ms=5000)
                P._sessions.append(s)
                return s

        common = ["--rig", rig, "--config", str(settings)]
        P.spawn("actuator", [VERGENCE, "actuator", "--driver", "sim", *common, *zenoh_args("actuator")])
        P.spawn("reducer", [VERGENCE, "reducer", *common, *zenoh_args("reducer")])
        P.spawn("worker", [VERGENCE, "worker", "--name", "w1", *common, *zenoh_args("worker")])
        s = observer()
        P.wait_alive(s, "worker", 1)
        P.spawn("capture", [VERGENCE, "capture", "--source", _pair(tmp_path), "--rate", str(RATE), *common,
                            *zenoh_args("capture")])
        commands = P.collect(s, P.key("command"))
        states = P.collect(s, P.key("motor_state"))
        status = P.collect(s, P.key("status/**"))
        commands.wait(5, 20)

        # the router goes away (SIGKILL: no goodbye to anyone) and comes back on the same endpoint
        t_kill = time.time_ns()
        router.signal_group(signal.SIGKILL)
        router.wait(5)
        time.sleep(down_s)  # time under test: the router stays down down_s
        t_restart = time.time_ns()
        router = P.spawn("router-2", router_argv)
        # the test's own session reconnects too; commands whose frame was captured after the restart
        cmd = wait_for(lambda: next((c for c in (Command.from_bytes(b) for t, b, _ in commands.snapshot()
                                                 if t > t_restart) if c.t_capture_ns > t_restart), None),
                       15, "a command after the router restart", logs=P.logs)
        t_first = next(t for t, b, _ in commands.snapshot() if Command.from_bytes(b).frame == cmd.frame)
        resume_s = (t_first - t_restart) / 1e9
        before = [t for t, _, _ in commands.snapshot() if t < t_kill]
        gap_s = (t_first - before[-1]) / 1e9
        # every service is back: status from capture, worker, reducer; motor states from the actuator that
        # count the new commands
        wait_for(lambda: {k.split("/")[3] for t, _, k in status.snapshot() if t > t_first} >=
                 {"capture", "worker", "reducer"}, 10, "status of every role after the restart", logs=P.logs)
        n0 = max(MotorState.from_bytes(b).commands for t, b, _ in states.snapshot() if t < t_kill)
        wait_for(lambda: any(MotorState.from_bytes(b).commands > n0 for t, b, _ in states.snapshot()
                             if t > t_restart), 10, "the actuator to receive commands again", logs=P.logs)
        n_after, t_after = sum(1 for t, _, _ in commands.snapshot() if t > t_first), time.monotonic()
        # flowing: a third of a second's worth of commands within 1 s
        wait_for(lambda: sum(1 for t, _, _ in commands.snapshot() if t > t_first) >= n_after + RATE // 3, 5,
                 f"{RATE // 3} more commands", logs=P.logs)
        assert time.monotonic() - t_after <= 1.0
        report = {"variant": variant, "resume_after_restart_s": round(resume_s, 3), "command_gap_s":
                  round(gap_s, 3), "router_down_s": round((t_restart - t_kill) / 1e9, 3)}
        print(json.dumps(report), file=sys.stderr)
        (tmp_path / "restart.json").write_text(json.dumps(report))
        assert resume_s <= TARGET_S, report
