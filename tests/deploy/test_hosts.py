"""Several hosts on one machine: network namespaces joined by veth pairs to a bridge (ip netns, as root).

    host "r" 10.77.0.1  the router (deploy/router-tls.json5: TLS, mutual TLS, user/password, ACL), the
                        capture, the reducer and an observer that records frames and profiles
    host "a" 10.77.0.2  a worker
    host "b" 10.77.0.3  a worker

The addresses exist only inside namespaces this test creates (names unique per run) and are deleted
at teardown with them. Where namespaces cannot be made (no root, no iproute2, a sandbox that refuses), the
tests skip with the reason."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
import uuid
from pathlib import Path

import msgpack
import numpy as np
import pytest
from deploy_helpers import client_config_file, make_secrets, router_config, start_router
from procs import VERGENCE, Procs, wait_for

from vergence.network import kernel, retina
from vergence.wire.messages import Frame, Profile

pytestmark = pytest.mark.slow  # every test here runs real processes

SUBNET = "10.77.0"
HOSTS = {"r": 1, "a": 2, "b": 3}


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10, check=check)


class Hosts:
    """Namespaces <tag>r, <tag>a, <tag>b; a bridge in r; one veth pair per other host."""

    def __init__(self):
        self.tag = f"vg{uuid.uuid4().hex[:6]}"
        self.ns = {h: f"{self.tag}{h}" for h in HOSTS}
        self.made: list[str] = []

    def addr(self, host: str) -> str:
        return f"{SUBNET}.{HOSTS[host]}"

    def prefix(self, host: str) -> list[str]:
        return ["ip", "netns", "exec", self.ns[host]]

    def up(self) -> None:
        for ns in self.ns.values():
            _ip("netns", "add", ns)
            self.made.append(ns)
            _ip("-n", ns, "link", "set", "lo", "up")
        r = self.ns["r"]
        _ip("-n", r, "link", "add", "br0", "type", "bridge")
        _ip("-n", r, "addr", "add", f"{self.addr('r')}/24", "dev", "br0")
        _ip("-n", r, "link", "set", "br0", "up")
        for h in ("a", "b"):
            # created inside r, so no interface ever appears in the namespace of the test itself
            _ip("-n", r, "link", "add", f"p{h}", "type", "veth", "peer", "name", "eth0", "netns", self.ns[h])
            _ip("-n", r, "link", "set", f"p{h}", "master", "br0")
            _ip("-n", r, "link", "set", f"p{h}", "up")
            _ip("-n", self.ns[h], "addr", "add", f"{self.addr(h)}/24", "dev", "eth0")
            _ip("-n", self.ns[h], "link", "set", "eth0", "up")

    def down(self) -> None:
        for ns in reversed(self.made):
            # any process left in the namespace was killed by the Procs teardown before this runs
            _ip("netns", "del", ns, check=False)
        self.made = []


@pytest.fixture
def hosts():
    if shutil.which("ip") is None:
        pytest.skip("iproute2 (`ip`) is not installed: apt-get install iproute2")
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root (ip netns add)")
    h = Hosts()
    try:
        h.up()
    except subprocess.CalledProcessError as e:
        h.down()
        pytest.skip(f"network namespaces are not permitted here: `{' '.join(e.cmd)}`: {e.stderr.strip()}")
    try:
        yield h
    finally:
        h.down()
        left = _ip("netns", "list").stdout
        assert h.tag not in left, left


@pytest.fixture(scope="module")
def secrets(tmp_path_factory):
    return make_secrets(tmp_path_factory.mktemp("secrets"), f"{SUBNET}.1")


# the children below import procs and deploy_helpers from there; vergence and services first, as conftest.py does
# (on sys.path, tests/vergence/ and tests/services/ would be namespace-package candidates for those names)
TESTS = str(Path(__file__).resolve().parents[1])

OBSERVER = textwrap.dedent("""
    # records every frame and profile of a rig (the raw bytes) until N profiles from W workers, or a timeout
    import sys, msgpack, zenoh
    import vergence, services
    sys.path.insert(0, @TESTS@)
    from deploy_helpers import round_trip
    from procs import wait_for
    conf_file, rig, n, w, out, timeout = sys.argv[1:7]
    from vergence.wire.messages import Profile
    conf = zenoh.Config.from_file(conf_file)
    frames, profiles = [], []
    with zenoh.open(conf) as s:
        s.declare_subscriber(f"vergence/{rig}/frame", lambda x: frames.append(x.payload.to_bytes()))
        s.declare_subscriber(f"vergence/{rig}/profile", lambda x: profiles.append(x.payload.to_bytes()))
        print("observing", flush=True)
        try:
            wait_for(lambda: sum(len(Profile.from_bytes(p).workers) == int(w) for p in list(profiles)) >= int(n),
                     float(timeout), "the profiles", interval=0.1)
        except TimeoutError:
            pass  # the test says what is missing
        round_trip(s)  # whatever the router forwarded so far has arrived
    with open(out, "wb") as f:
        msgpack.pack({"frames": list(frames), "profiles": list(profiles)}, f)
""").replace("@TESTS@", repr(TESTS))


def _pair(tmp_path: Path) -> str:
    import cv2

    rng = np.random.default_rng(3)
    base = cv2.GaussianBlur(rng.integers(0, 256, (120, 360), np.uint8), (5, 5), 1.5)
    cv2.imwrite(str(tmp_path / "l.png"), base[:, 20:340])
    cv2.imwrite(str(tmp_path / "r.png"), base[:, 8:328])
    return f"files:{tmp_path / 'l.png'},{tmp_path / 'r.png'}"


def test_pub_sub_across_namespaces(tmp_path, hosts, secrets):
    """The plumbing: router on host r, a publisher on host a, a subscriber on host b, over mutual TLS."""
    conf, endpoint = router_config("tls", secrets, tmp_path / "router.json5", host=hosts.addr("r"), port=7447)
    script = textwrap.dedent("""
        import sys, zenoh
        import vergence, services
        sys.path.insert(0, @TESTS@)
        from procs import wait_for
        role, conf_file, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
        with zenoh.open(zenoh.Config.from_file(conf_file)) as s:
            if role == "capture":
                pub = s.declare_publisher("vergence/x/frame")
                wait_for(lambda: pub.matching_status.matching, 10, "the subscriber on host b")
                for i in range(n):
                    pub.put(b"%d" % i)
            else:
                got = []
                s.declare_subscriber("vergence/x/frame", lambda x: got.append(x.payload.to_bytes()))
                try:
                    wait_for(lambda: len(got) >= n, 10, "the frames")
                except TimeoutError:
                    pass  # the test says what is missing
                print(b",".join(got).decode(), flush=True)
    """).replace("@TESTS@", repr(TESTS))
    with Procs(tmp_path) as P:
        start_router(P, conf, endpoint, prefix=hosts.prefix("r"))
        sub_conf = client_config_file(secrets, "monitor", "tls", endpoint, tmp_path / "monitor.json5")
        pub_conf = client_config_file(secrets, "capture", "tls", endpoint, tmp_path / "capture.json5")
        sub = P.spawn("sub", [*hosts.prefix("b"), sys.executable, "-c", script, "monitor", str(sub_conf),
                              "5"])
        P.spawn("pub", [*hosts.prefix("a"), sys.executable, "-c", script, "capture", str(pub_conf), "20"])
        assert sub.wait(20) == 0, P.logs()
        assert sub.text().strip().split(",")[:5] == ["0", "1", "2", "3", "4"], P.logs()


def test_workers_on_two_hosts_give_the_single_host_profile(tmp_path, hosts, secrets):
    """Router, capture and reducer on host r, one worker on each of hosts a and b: the profiles of frames
    sharded over both hosts equal vergence.correlate on the same frames in this process."""
    conf, endpoint = router_config("tls", secrets, tmp_path / "router.json5", host=hosts.addr("r"), port=7447)
    settings = tmp_path / "settings.toml"
    settings.write_text("[network]\nmax_window = 0\n[capture]\npreview_hz = 0\n")
    rig = "multi"

    def client(role: str) -> str:
        return str(client_config_file(secrets, role, "tls", endpoint, tmp_path / f"{role}.json5"))

    with Procs(tmp_path) as P:
        start_router(P, conf, endpoint, prefix=hosts.prefix("r"))
        common = ["--rig", rig, "--config", str(settings)]
        for h in ("a", "b"):
            P.spawn(f"worker-{h}", [*hosts.prefix(h), VERGENCE, "worker", "--name", f"host{h}",
                                    "--zenoh-config", client("worker"), *common])
        P.spawn("reducer", [*hosts.prefix("r"), VERGENCE, "reducer", "--zenoh-config", client("reducer"),
                            *common])
        (tmp_path / "observer.py").write_text(OBSERVER)
        out = tmp_path / "observed.msgpack"
        obs = P.spawn("observer", [*hosts.prefix("r"), sys.executable, str(tmp_path / "observer.py"),
                                   client("monitor"), rig, "5", "2", str(out), "40"])
        wait_for(lambda: "observing" in obs.text(), 20, "the observer", logs=P.logs)
        P.spawn("capture", [*hosts.prefix("r"), VERGENCE, "capture", "--source", _pair(tmp_path),
                            "--rate", "20", "--zenoh-config", client("capture"), *common])
        assert obs.wait(45) == 0, P.logs()
    data = msgpack.unpackb(out.read_bytes())
    frames = {f.frame: f for f in map(Frame.from_bytes, data["frames"])}
    two = [p for p in map(Profile.from_bytes, data["profiles"]) if len(p.workers) == 2]
    assert len(two) >= 5, P.logs()
    for prof in two:
        assert sorted(w.split("-")[0] for w in prof.workers) == ["hosta", "hostb"]
        f = frames[prof.frame]
        assert len(f.plan) == 2 and f.plan[0][2] == f.plan[1][1]  # two shards that tile the offsets
        fovea, band = retina.planes(f.fovea_strip()), retina.planes(f.band_strip())
        w = kernel.support_weights(fovea, f.support_gamma, f.support_radius) if f.support else None
        want = np.atleast_2d(kernel.correlate(fovea, band, circular=f.circular, weights=w))
        assert np.array_equal(prof.array(), want)  # bit-identical to one host, in-process
        assert prof.k - prof.k_centre == 12 and prof.confident
