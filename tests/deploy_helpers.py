"""Helpers for the cluster deployment tests (tests/services/test_deploy_*.py): the deploy/ configs made runnable on
127.0.0.1 with secrets from deploy/make-certs.sh in a temporary directory, and a router started from them.

The deploy/ files name /etc/vergence/secrets and listen on 0.0.0.0:7447 (their place in a container); the
tests rewrite exactly those two strings, so what is tested is the committed file."""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
from pathlib import Path

from procs import VERGENCE, Proc, Procs, free_port, wait_for

ROOT = Path(__file__).resolve().parent.parent
DEPLOY = ROOT / "deploy"
SECRETS_IN_CONFIGS = "/etc/vergence/secrets"
ROLES = ("capture", "worker", "reducer", "actuator", "monitor", "record", "replay", "fixate", "ros2")


def make_secrets(out: Path, *router_names: str) -> Path:
    """Run deploy/make-certs.sh into `out` (configs pointing at `out`); returns `out`."""
    if shutil.which("openssl") is None:
        import pytest

        pytest.skip("openssl is not installed (apt-get install openssl)")
    env = dict(os.environ, SECRETS_DIR=str(out))
    names = router_names or ("localhost", "127.0.0.1")
    r = subprocess.run(["sh", str(DEPLOY / "make-certs.sh"), "-o", str(out), *names], env=env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return out


def passwords(secrets: Path) -> dict[str, str]:
    return dict(line.split(":", 1) for line in (secrets / "users.txt").read_text().split())


def router_config(variant: str, secrets: Path, dest: Path, host: str = "127.0.0.1", port: int | None = None) \
        -> tuple[Path, str]:
    """deploy/router-<variant>.json5 (variant "tls" or "tcp") with the secrets at `secrets` and the listener
    on host:port (a free port by default). Returns (file, endpoint)."""
    name = f"router-{variant}.json5"
    port = port or free_port()
    text = (DEPLOY / name).read_text()
    assert SECRETS_IN_CONFIGS in text and f"{variant}/0.0.0.0:7447" in text
    text = text.replace(SECRETS_IN_CONFIGS, str(secrets))
    text = text.replace(f"{variant}/0.0.0.0:7447", f"{variant}/{host}:{port}")
    dest.write_text(text)
    return dest, f"{variant}/{host}:{port}"


def client_config_file(secrets: Path, role: str, variant: str, endpoint: str, dest: Path) -> Path:
    """The per-role client config written by make-certs.sh, pointed at `endpoint` (a copy in `dest`)."""
    src = secrets / "clients" / f"{role}-{variant}.json5"
    text, n = re.subn(r'endpoints: \["[^"]*"\]', f"endpoints: [{json.dumps(endpoint)}]", src.read_text())
    assert n == 1, f"{src}: no single connect endpoint"
    dest.write_text(text)
    return dest


def client_session(secrets: Path, role: str, variant: str, endpoint: str, timeout_ms: int = 3000,
                   **override):
    """A zenoh session of the test with a role's identity; override = {"transport/auth/usrpwd/user": ...}.
    The connect timeout is bounded (the deployed configs retry forever)."""
    import zenoh

    src = secrets / "clients" / f"{role}-{variant}.json5"
    conf = zenoh.Config.from_file(str(src))
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("connect/timeout_ms", str(timeout_ms))
    for k, v in override.items():
        conf.insert_json5(k, json.dumps(v))
    return zenoh.open(conf)


def start_router(P: Procs, config: Path, endpoint: str, name: str = "router", prefix: list[str] | None = None,
                 timeout: float = 15.0) -> Proc:
    """`vergence router --zenoh-config config` (optionally under a prefix such as `ip netns exec NS`);
    returns once its port accepts TCP connections (checked from the same namespace when prefixed)."""
    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    p = P.spawn(name, [*(prefix or []), VERGENCE, "router", "--zenoh-config", str(config)])
    P.endpoint, P.port = endpoint, int(port)

    def up():
        if not p.alive():
            raise RuntimeError(f"router exited\n{p.tail()}")
        if prefix:
            r = subprocess.run([*prefix, "python3", "-c",
                                f"import socket,sys; s=socket.socket(); s.settimeout(0.2); "
                                f"sys.exit(s.connect_ex(({host!r},{port})))"], capture_output=True, timeout=5)
            return r.returncode == 0
        with socket.socket() as s:
            s.settimeout(0.2)
            return s.connect_ex((host, int(port))) == 0

    wait_for(up, timeout, f"the router to listen on {endpoint}", interval=0.1, logs=P.logs)
    return p


def round_trip(session, timeout: float = 5.0) -> None:
    """A barrier, not a sleep: a liveliness query answered by the router. Its answer comes on the same link,
    after whatever the router sent this session before (the subscribers it declared to a new client, the
    messages it forwarded), and the router handled whatever this session sent before the query (its puts)."""
    for _ in session.liveliness().get("vergence/barrier/**", timeout=timeout):
        pass


def puts_through_acl(secrets: Path, variant: str, endpoint: str, roles, keys, until: tuple[str, bytes]) \
        -> list[tuple[str, bytes]]:
    """Each role (its own credentials) puts its name on each key; what a `monitor` client subscribed to
    vergence/** receives through the router's ACL, as (key, role). `until`: one (key, role) the ACL lets
    through, waited for before the last barrier (the router forwards asynchronously)."""
    got: list[tuple[str, bytes]] = []
    watch = client_session(secrets, "monitor", variant, endpoint)
    try:
        sub = watch.declare_subscriber("vergence/**", lambda s: got.append((str(s.key_expr), s.payload.to_bytes())))
        for role in roles:
            s = client_session(secrets, role, variant, endpoint)
            try:
                round_trip(s)  # the router has told this client about the subscriber
                for key in keys:
                    s.put(key, role.encode())
                round_trip(s)  # the router has taken (or refused) every put
            finally:
                s.close()
        wait_for(lambda: until in got, 5, f"{until[1].decode()}'s put on {until[0]}")
        round_trip(watch)  # whatever the router forwarded has arrived
        sub.undeclare()
    finally:
        watch.close()
    return got
