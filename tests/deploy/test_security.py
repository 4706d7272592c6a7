"""The cluster's security as deployed (deploy/router-tls.json5, router-tcp.json5, make-certs.sh), with real
`vergence router` processes on 127.0.0.1 and zenoh clients of the test or real services:
- no credentials or a wrong password cannot connect; a wrong CA, a client certificate from another CA or none
  at all fails TLS;
- only the reducer's identity gets a command through, only the actuator's a motor state, of these roles only the
  ROS 2 bridge's a fixate; wildcard puts do not bypass the rules; the real `vergence actuator --driver sim` never
  receives a forged command;
- the real services, each with its own identity, still run under these rules.
"""

from __future__ import annotations

import re
import time

import pytest
import zenoh
from deploy_helpers import (
    DEPLOY,
    client_config_file,
    client_session,
    make_secrets,
    passwords,
    puts_through_acl,
    round_trip,
    router_config,
    start_router,
)
from procs import VERGENCE, Procs, textured_pair, wait_for

from vergence.wire.messages import Command, MotorState, Decision


@pytest.fixture(scope="module")
def secrets(tmp_path_factory):
    return make_secrets(tmp_path_factory.mktemp("secrets"), "localhost", "127.0.0.1")


@pytest.fixture(scope="module")
def other_ca(tmp_path_factory):
    """A second, unrelated CA with its own router and client certificates."""
    return make_secrets(tmp_path_factory.mktemp("other"), "localhost", "127.0.0.1")


def command(rig: str, pan: float, frame: int = 1) -> bytes:
    return Command(rig=rig, frame=frame, t_capture_ns=time.time_ns(), pan_rad=pan, correction_rad=pan,
                   direction=1, magnitude_px=3.0, confidence=1.0).to_bytes()


def connects(secrets, role, variant, endpoint, **override) -> bool:
    try:
        s = client_session(secrets, role, variant, endpoint, timeout_ms=1500, **override)
    except zenoh.ZError:
        return False
    s.close()
    return True


def connects_each(secrets, attempts: list[tuple[str, str, str, dict]]) -> list[bool]:
    """connects() for each (role, variant, endpoint, override), all at once (threads): a refused one waits out its
    1.5 s connect timeout, and these are independent clients of one router."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(len(attempts)) as pool:
        return list(pool.map(lambda a: connects(secrets, a[0], a[1], a[2], **a[3]), attempts))


def test_router_configs_share_one_acl():
    """router.json5 and router-tcp.json5 carry the same rules and policies; TLS subjects also need the
    certificate's common name. Both disable multicast and gossip scouting."""
    tls = zenoh.Config.from_file(str(DEPLOY / "router-tls.json5"))
    tcp = zenoh.Config.from_file(str(DEPLOY / "router-tcp.json5"))
    import json

    a, b = json.loads(tls.get_json("access_control")), json.loads(tcp.get_json("access_control"))
    assert a["enabled"] and a["default_permission"] == "deny"
    assert a["rules"] == b["rules"] and a["policies"] == b["policies"]
    for sa, sb in zip(a["subjects"], b["subjects"], strict=True):
        assert sa["cert_common_names"] == sa["usernames"] == sb["usernames"]
    for conf in (tls, tcp):
        assert json.loads(conf.get_json("mode")) == "router"
        assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
        assert json.loads(conf.get_json("scouting/gossip/enabled")) is False
    # only the reducer's policy may put on */command, only the actuator's on */motor_state
    rules = {r["id"]: r for r in a["rules"]}
    can = {p["id"]: [k for r in p["rules"] if "put" in rules[r]["messages"] and "ingress" in rules[r]["flows"]
                     for k in rules[r]["key_exprs"]] for p in a["policies"]}
    assert [p for p, keys in can.items() if "vergence/*/command" in keys] == ["reducer"]
    assert [p for p, keys in can.items() if "vergence/*/motor_state" in keys] == ["actuator"]
    assert not any("**" in k for keys in can.values() for k in keys)
    # the fovea is moved by the fixate role and the ROS 2 bridge's (its look_at, when the settings turn it on),
    # which puts nothing else but its own status and token
    assert [p for p, keys in can.items() if "vergence/*/fixate" in keys] == ["fixate", "ros2"]
    assert can["ros2"] == ["vergence/*/fixate", "vergence/*/status/ros2/*", "vergence/*/alive/ros2/*"]


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["tcp", "tls"])
def test_no_credentials_or_wrong_password_cannot_connect(tmp_path, secrets, variant):
    conf, endpoint = router_config(variant, secrets, tmp_path / "router.json5")
    with Procs(tmp_path) as P:
        start_router(P, conf, endpoint)
        intruder = {"transport/auth/usrpwd/user": "intruder", "transport/auth/usrpwd/password": "x"}
        # the right password; a wrong one; an unknown user; another role's password (it does not open this
        # role's name)
        assert connects_each(secrets, [
            ("reducer", variant, endpoint, {}),
            ("reducer", variant, endpoint, {"transport/auth/usrpwd/password": "wrong"}),
            ("reducer", variant, endpoint, intruder),
            ("reducer", variant, endpoint, {"transport/auth/usrpwd/password": passwords(secrets)["worker"]}),
        ]) == [True, False, False, False]
        # no credentials at all: a plain client with only the endpoint (and, for TLS, our CA and a cert)
        conf0 = zenoh.Config()
        conf0.insert_json5("mode", '"client"')
        conf0.insert_json5("connect/endpoints", f'["{endpoint}"]')
        conf0.insert_json5("connect/timeout_ms", "1500")
        conf0.insert_json5("scouting/multicast/enabled", "false")
        if variant == "tls":
            for k in ("root_ca_certificate", "connect_certificate", "connect_private_key"):
                key = {"root_ca_certificate": "ca", "connect_certificate": "reducer",
                       "connect_private_key": "reducer-key"}[k]
                conf0.insert_json5(f"transport/link/tls/{k}", f'"{secrets / (key + ".pem")}"')
            conf0.insert_json5("transport/link/tls/enable_mtls", "true")
        with pytest.raises(zenoh.ZError):
            zenoh.open(conf0).close()


@pytest.mark.slow
def test_wrong_ca_fails_tls(tmp_path, secrets, other_ca):
    conf, endpoint = router_config("tls", secrets, tmp_path / "router.json5")
    with Procs(tmp_path) as P:
        start_router(P, conf, endpoint)
        assert connects_each(secrets, [
            ("reducer", "tls", endpoint, {}),
            # the client trusts another CA: it rejects our router's certificate
            ("reducer", "tls", endpoint, {"transport/link/tls/root_ca_certificate": str(other_ca / "ca.pem")}),
            # the client presents a certificate of another CA (right CN, right password): the router rejects it
            ("reducer", "tls", endpoint, {"transport/link/tls/connect_certificate": str(other_ca / "reducer.pem"),
                                          "transport/link/tls/connect_private_key": str(other_ca / "reducer-key.pem")}),
            # no client certificate at all (mutual TLS is required)
            ("reducer", "tls", endpoint, {"transport/link/tls/enable_mtls": False}),
            # a plain tcp client does not reach a tls listener
            ("reducer", "tcp", endpoint.replace("tls/", "tcp/"), {}),
        ]) == [True, False, False, False, False]


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["tcp", "tls"])
def test_only_the_reducer_commands_and_only_the_actuator_reports(tmp_path, secrets, variant):
    conf, endpoint = router_config(variant, secrets, tmp_path / "router.json5")
    with Procs(tmp_path) as P:
        start_router(P, conf, endpoint)
        got = puts_through_acl(secrets, variant, endpoint,
                               ("capture", "worker", "monitor", "replay", "ros2", "reducer", "actuator"),
                               ("vergence/r/command", "vergence/r/motor_state", "vergence/r/frame", "vergence/**",
                                "vergence/*/command", "vergence/r/*", "vergence/*/motor/*", "vergence/replay/frame",
                                "vergence/r/workers", "vergence/r/fixate"),
                               until=("vergence/r/motor_state", b"actuator"))
    assert sorted(got) == sorted([
        ("vergence/r/frame", b"capture"), ("vergence/replay/frame", b"capture"), ("vergence/replay/frame", b"replay"),
        ("vergence/r/command", b"reducer"), ("vergence/*/command", b"reducer"), ("vergence/r/workers", b"reducer"),
        ("vergence/r/motor_state", b"actuator"), ("vergence/r/fixate", b"ros2"),
    ])


@pytest.mark.slow
def test_forged_command_never_reaches_the_real_actuator(tmp_path, secrets):
    conf, endpoint = router_config("tls", secrets, tmp_path / "router.json5")
    with Procs(tmp_path) as P:
        start_router(P, conf, endpoint)
        act_conf = client_config_file(secrets, "actuator", "tls", endpoint, tmp_path / "actuator.json5")
        P.spawn("actuator", [VERGENCE, "actuator", "--driver", "sim", "--rig", "r",
                             "--zenoh-config", str(act_conf), "--state-hz", "20"])
        watch = client_session(secrets, "monitor", "tls", endpoint)
        try:
            states = P.collect(watch, "vergence/r/motor_state")
            states.wait(2, 15)  # the actuator is up and reports through the ACL
            for role in ("worker", "capture", "monitor", "replay"):
                s = client_session(secrets, role, "tls", endpoint)
                try:
                    round_trip(s)  # the router has told this client about the actuator's subscriber
                    for i in range(5):
                        s.put("vergence/r/command", command("r", 0.3, frame=i + 1))
                        round_trip(s)  # one at a time, each taken (or refused) by the router
                finally:
                    s.close()
            n = len(states)
            wait_for(lambda: len(states) > n + 2, 5, "more motor states", logs=P.logs)  # still reporting
            forged = [MotorState.from_bytes(b) for _, b, _ in states.snapshot()]
            assert all(m.commands == 0 and m.goal_rad == 0.0 and m.pan_rad == 0.0 for m in forged), forged[-1]
            # the reducer's identity does move it
            s = client_session(secrets, "reducer", "tls", endpoint)
            try:
                round_trip(s)
                s.put("vergence/r/command", command("r", 0.05, frame=100))
                def reached():
                    got = [MotorState.from_bytes(b) for _, b, _ in states.snapshot()]
                    return next((m for m in got if m.commands >= 1 and m.goal_rad != 0.0), None)

                moved = wait_for(reached, 10, "the reducer's command to reach the actuator", logs=P.logs)
            finally:
                s.close()
            assert moved.commands == 1 and moved.goal_rad == pytest.approx(0.05, abs=0.02)
        finally:
            watch.close()


@pytest.mark.slow
def test_services_run_under_the_acl(tmp_path, secrets):
    """capture, worker, reducer and actuator, each with its own identity over mutual TLS: the pipeline runs,
    commands reach the actuator and its state comes back. The fixation's centre 17 px are flat, so the
    capture's dynamic window must read the reducer's decisions (vergence/r/decision) to reach 23 px, where
    the network is confident: no command comes unless the rules let those decisions through."""
    source = textured_pair(tmp_path, flat=17)
    settings = tmp_path / "settings.toml"
    settings.write_text("[network]\nmax_window = 31\n[capture]\npreview_hz = 2\n")
    conf, endpoint = router_config("tls", secrets, tmp_path / "router.json5")
    with Procs(tmp_path) as P:
        router = start_router(P, conf, endpoint)

        def start(role, *args):
            c = client_config_file(secrets, role, "tls", endpoint, tmp_path / f"{role}.json5")
            return P.spawn(role, [VERGENCE, role, "--rig", "r", "--zenoh-config", str(c),
                                  "--config", str(settings), *args])

        start("actuator", "--driver", "sim")
        start("reducer")
        start("worker", "--name", "w1")
        watch = client_session(secrets, "monitor", "tls", endpoint)
        try:
            wait_for(lambda: list(watch.liveliness().get("vergence/r/alive/worker/*", timeout=1.0)), 15,
                     "the worker's token", interval=0.2, logs=P.logs)
            cmds = P.collect(watch, "vergence/r/command")
            decisions = P.collect(watch, "vergence/r/decision")
            states = P.collect(watch, "vergence/r/motor_state")
            status = P.collect(watch, "vergence/r/status/**")
            start("capture", "--source", source, "--rate", "20")
            cmds.wait(3, 20)
            verdicts = [Decision.from_bytes(b) for _, b, _ in decisions.snapshot()]
            assert any(v.window == 23 and v.confident for v in verdicts)
            wait_for(lambda: any(MotorState.from_bytes(b).commands > 0 for _, b, _ in states.snapshot()), 10,
                     "a motor state that counts commands", logs=P.logs)
            def roles():
                return {k.split("/")[3] for _, _, k in status.snapshot()}

            wait_for(lambda: roles() >= {"capture", "worker", "reducer"}, 10, "status from every role",
                     logs=P.logs)
        finally:
            watch.close()
        assert router.alive()
        # nothing was refused by the router's rules on the way (zenoh logs denials at debug level only, so
        # the positive evidence above is what counts); the services never logged a connection error
        for p in P.procs:
            assert not re.search(r"(?i)traceback", p.text()), p.tail()
