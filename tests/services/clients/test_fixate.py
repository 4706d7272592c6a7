"""Fixation from outside: vergence/<rig>/fixate moves the running capture's fovea; bad requests are rejected,
counted and change nothing; `vergence fixate` as a user runs it; and through `vergence up` on the simulated
rig, the first decision at the new point within 0.2 s, the loop re-converged there, its depth measured."""

from __future__ import annotations

import json
import math
import time

import msgpack
import numpy as np
import pytest

from procs import Procs, free_port, gives_up_without_a_router, run, wait_for
from services.pipeline.fovea import Fovea
from services.clients.fixate import refusal
from services.runtime.health import Health
from vergence.observe import monitor, plots, screen
from vergence.head.control import Controller
from vergence.stages.frames import make_frame
from vergence.stages.gather import Reduced
from vergence.network.params import Params
from vergence.stages.shards import compute_correlation
from vergence.wire.messages import SCHEMA, Fixate, Frame, MotorState, Decision, replace as replace_message
from vergence.sim import Rig
from vergence.sim.fixation import truth_at


def fixate(x, y, **kw) -> bytes:
    return Fixate(x=x, y=y, t_ns=time.time_ns(), **kw).to_bytes()


def raw(**fields) -> bytes:
    return msgpack.packb({"v": SCHEMA, "t_ns": 1, **fields}, use_bin_type=True)


def test_fovea_moves_on_a_valid_request_and_nothing_else():
    health = Health("capture", "t")
    fv = Fovea(320, 240, (480, 640), Params(), health)  # window 15, vertical search 6: x 7..632, y 13..466
    assert fv.on_fixate(fixate(100.4, 50.6, source="me")) == (100, 51) and fv.at() == (100, 51)
    assert fv.on_fixate(fixate(7, 13)) == (7, 13) and fv.on_fixate(fixate(632, 466)) == (632, 466)
    bad = [fixate(6, 240), fixate(633, 240), fixate(320, 467), fixate(-5, -5), fixate(1e9, 10),
           raw(x=math.nan, y=10.0), raw(x=10.0, y=math.inf), raw(x="10", y=10.0), raw(y=10.0),
           b"\xc1\xc1 not msgpack", msgpack.packb({"v": SCHEMA + 1, "x": 10.0, "y": 10.0, "t_ns": 1}),
           msgpack.packb([1, 2])]
    for b in bad:
        assert fv.on_fixate(b) is None
        assert fv.at() == (632, 466)
    assert health.bad == {"fixate": len(bad)} and health.counters["fixate_rejected"] == len(bad)
    assert health.counters["fixations"] == 3
    # the status names the latest well-formed request refused (by its t_ns), not the undecodable ones after it
    fv.on_fixate(Fixate(x=1e9, y=10, t_ns=42).to_bytes())
    fv.on_fixate(b"\xc1 not msgpack")
    st = fv.fields()
    assert st["fovea"] == [632, 466] and st["fixate_rejection"]["t_ns"] == 42
    assert st["fixate_rejection"]["why"].startswith("(1e+09, 10): ")


def test_the_command_reads_only_its_own_refusal():
    head = {"role": "capture", "id": "c-1"}  # a status (vergence.wire.status): who sent it
    ok = json.dumps(dict(head, fovea=[1, 2], fixate_rejection={"t_ns": 7, "why": "(1, 2): does not fit"})).encode()
    assert refusal(ok, 7) == "(1, 2): does not fit"
    assert refusal(ok, 8) is None  # another request's
    for bad in (b"", b"\xc1", b"[1, 2]", b"null", b'{"fixate_rejection": [7]}', b'{"fixate_rejection": {"t_ns": 7}}',
                b'{"fixate_rejection": {"t_ns": 7, "why": 3}}', b"[" * 100000):
        assert refusal(bad, 7) is None
    long = json.dumps(dict(head, fixate_rejection={"t_ns": 7, "why": "x" * 10000})).encode()
    assert refusal(long, 7) == "x" * 300
    assert refusal(json.dumps({"fixate_rejection": {"t_ns": 7, "why": "no"}}).encode(), 7) is None  # no sender


@pytest.mark.slow
def test_fixate_command_checks_its_point():
    for arg, says in (("12", "want X,Y"), ("nan,3", "finite"), ("a,b", "want X,Y")):
        r = run("fixate", arg, timeout=60)
        assert r.returncode == 2 and says in r.stderr


def _verdicts(col, since_ns: int = 0) -> list[tuple[int, Decision]]:
    return [(t, Decision.from_bytes(b)) for t, b, _ in col.snapshot() if t >= since_ns]


def _converged_depths(col, xy, since_ns, n):
    vs = [v for _, v in _verdicts(col, since_ns) if (v.x, v.y) == xy and v.converged]
    return [v.depth_m for v in vs[-n:]] if len(vs) >= n else None


@pytest.mark.slow
def test_fixate_through_vergence_up(tmp_path):
    """`vergence up --source sim` (the generated scene, f = 512 px) with [rig] baseline_m = 0.06: converged on
    the centre object (d = 24 px: Z = 1.28 m); an outside client asks for (440, 240), a nearer object
    (d = 36 px: 0.853 m): its first decision there within 0.2 s at 30 Hz, the slave pan re-converged within
    1 px of that point's converged pan, the depth within 1 %. Out-of-image, NaN and non-msgpack requests are
    rejected and counted, and the fovea stays. `vergence fixate 320,400` (the background, d = 8 px) as a user
    runs it (within two stated sigmas there: 8 px of disparity hold no 1 % depth)."""
    rig = Rig.from_spec("")
    cfg = tmp_path / "v.toml"
    cfg.write_text("[rig]\nbaseline_m = 0.06\n")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Procs(tmp_path) as P:
        P.endpoint = endpoint
        P.start("up", "up", "--listen", endpoint, "--source", "sim", "--workers", "2", "--rate", "30",
                "--config", str(cfg), "--no-standby", connect=False)
        s = P.session()
        decisions = P.collect(s, P.key("decision"))
        states = P.collect(s, P.key("motor_state"))
        status = P.collect(s, P.key("status/capture/*"))
        frames = P.collect(s, P.key("frame"))

        def truths(t0: int) -> list[tuple[tuple[int, int], float]]:  # (fovea, truth) of the frames read after t0
            return [((f.x, f.y), f.truth_pan_rad) for f in (Frame.from_bytes(b) for t, b, _ in frames.snapshot()
                                                            if t > t0) if f.t_read_ns > t0]

        def pan() -> float:
            return MotorState.from_bytes(states.snapshot()[-1][1]).pan_rad

        z = wait_for(lambda: _converged_depths(decisions, (320, 240), 0, 10), 60, "converged decisions at the centre",
                     logs=P.logs)
        assert np.median(z) == pytest.approx(0.06 * 512 / 24, rel=0.01)
        assert abs(pan() - rig.truth_pan_rad) <= rig.one_px_rad

        # an outside client asks for a new point
        truth, d = truth_at(rig, 440, 240)
        assert d == 36 and abs(truth - rig.truth_pan_rad) > 8 * rig.one_px_rad
        t0 = time.time_ns()
        s.put(P.key("fixate"), fixate(440, 240, source="test"))
        t_first, first = wait_for(lambda: next(((t, v) for t, v in _verdicts(decisions, t0)
                                                if (v.x, v.y) == (440, 240)), None),
                                  5, "a decision at (440, 240)", logs=P.logs)
        assert (t_first - t0) / 1e9 <= 0.2
        # decided on a frame read after the request (its exposure, t_capture_ns, may be a little before it: the sim
        # camera's image is as old as the motor's newest report of its pan, up to 20 ms)
        assert first.t_read_ns >= t0 and first.t_capture_ns >= t0 - 0.05e9
        wait_for(lambda: abs(pan() - truth) <= rig.one_px_rad, 10, "the slave re-converged", logs=P.logs)
        # the simulator's truth follows the fovea: every frame read since carries the new point's (the service's,
        # and so the monitor's and the reducer's tracking error)
        t_c = time.time_ns()
        seen = wait_for(lambda: (lambda got: got if len(got) >= 5 else None)(truths(t_c)), 5, "frames", logs=P.logs)
        assert {at for at, _ in seen} == {(440, 240)}
        assert [v for _, v in seen] == pytest.approx([truth] * len(seen), abs=1e-9)
        z = wait_for(lambda: _converged_depths(decisions, (440, 240), t0, 10), 10, "converged decisions there",
                     logs=P.logs)
        assert np.median(z) == pytest.approx(0.06 * 512 / 36, rel=0.01)

        # bad requests: nothing moves
        t1 = time.time_ns()
        for b in (fixate(5000, 10), raw(x=math.nan, y=100.0), b"\xc1 not msgpack"):
            s.put(P.key("fixate"), b)

        def rejected():
            for t, b, _ in status.snapshot():
                st = json.loads(b)
                if t > t1 and st["counters"].get("fixate_rejected", 0) >= 3:
                    return st
            return None

        st = wait_for(rejected, 10, "the capture's status to count the rejected requests", logs=P.logs)
        assert st["bad"]["fixate"] == 3 and st["counters"]["fixate_rejected"] == 3 and st["fovea"] == [440, 240]
        t2 = time.time_ns()
        wait_for(lambda: len(_verdicts(decisions, t2)) >= 10, 10, "more decisions", logs=P.logs)
        assert all((v.x, v.y) == (440, 240) for _, v in _verdicts(decisions, t1))
        assert "fixate request rejected, the fovea stays at (440, 240)" in (tmp_path / "up.log").read_text()

        # `vergence fixate` as a user runs it: it waits for the first decision at its point and says so
        r = run("fixate", "320,400", "--connect", endpoint, "--rig", P.rig, "--wait", "10", timeout=60)
        assert r.returncode == 0, r.stderr
        assert " at (320, 400): offset " in r.stdout and "ms after the request" in r.stdout
        truth, d = truth_at(rig, 320, 400)
        wait_for(lambda: abs(pan() - truth) <= rig.one_px_rad, 10, "the slave converged on (320, 400)", logs=P.logs)
        t3 = time.time_ns()
        z = wait_for(lambda: _converged_depths(decisions, (320, 400), t3, 10), 10, "converged there", logs=P.logs)
        # 3.84 m at 8 px: a 0.1 px residual is 1.3 %, and the decisions say so (sigma about 1.8 %): within two of
        # their own sigmas (measured 3.89-3.90 m; the 1 % bar above is for d = 24 and 36 px)
        sigma = np.median([v.depth_sigma_m for _, v in _verdicts(decisions, t3) if (v.x, v.y) == (320, 400)
                           and v.converged])
        assert d == 8 and 0.01 * 3.84 < sigma < 0.03 * 3.84
        assert np.median(z) == pytest.approx(0.06 * 512 / 8, abs=2 * sigma)

        # a point where the fovea does not fit: the command says the capture refused it, and why, at once
        t = time.monotonic()
        r = run("fixate", "9999,150", "--connect", endpoint, "--rig", P.rig, "--wait", "20", timeout=60)
        assert r.returncode == 2, (r.stdout, r.stderr)
        assert "the capture refused (9999, 150): " in r.stderr and "the fovea stays" in r.stderr
        assert time.monotonic() - t < 15  # the next status (1 s), not the 20 s wait


@pytest.mark.slow
def test_fixate_without_a_capture_says_so(tmp_path):
    with Procs(tmp_path) as P:
        P.router()
        r = run("fixate", "100,100", "--connect", P.endpoint, "--rig", P.rig, "--wait", "1", timeout=60)
        assert r.returncode == 1 and "no decision at (100, 100) within 1 s" in r.stderr
        r = run("fixate", "100,100", "--connect", P.endpoint, "--rig", P.rig, "--wait", "0", timeout=60)
        assert r.returncode == 0 and f"sent on vergence/{P.rig}/fixate" in r.stdout


@pytest.mark.slow
def test_fixate_without_a_router_gives_up_within_its_wait():
    """Issue #28: it kept trying, saying "still trying", forever; --wait bounds the router's answer too."""
    gives_up_without_a_router("fixate", "100,100", "--wait", "1", within=1)


def test_monitor_shows_the_fovea_and_the_depth():
    """`vergence monitor`'s model: the fovea of the latest frame, the decision's converged depth; a profile of
    an older fovea says so."""
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (120, 200), np.uint8)
    p = Params(max_window=0)
    f = make_frame(img, img, rig="head", frame=3, pan_rad=0.0, focal_px=100.0, params=p,
                   plan=[["w", 0, 186]], at=(80, 60))
    r = Reduced.of(f, compute_correlation(f, "w").array(), p, Controller())
    mon = monitor.Monitor("head")
    mon.feed("vergence/head/frame", f.to_bytes())
    mon.feed("vergence/head/profile", replace_message(r.profile, x=80, y=60, converged=True, depth_m=1.234,
                                                          depth_sigma_m=0.012).to_bytes())
    s = mon.snapshot()
    assert s.fovea == (80, 60)
    assert "fovea (80, 60)   converged, depth 1.234 m ± 0.012" in screen.render_text(s, color=False)
    f.x, f.frame = 90, 4  # the fovea moved; the latest profile is still the old point's
    mon.feed("vergence/head/frame", f.to_bytes())
    text = screen.render_text(mon.snapshot(), color=False)
    assert "fovea (90, 60) (the profile's: (80, 60))" in text
    mon.feed("vergence/head/profile", replace_message(r.profile, frame=4, x=90, y=60).to_bytes())
    assert "fovea (90, 60)   not converged, no depth" in screen.render_text(mon.snapshot(), color=False)
    assert plots.monitor_figure(mon.snapshot()).axes[0].get_title(loc="left").endswith(
        "\nfovea (90, 60)   not converged, no depth")  # the PNG says it too


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["tcp", "tls"])
def test_only_the_fixate_role_may_fixate(tmp_path, variant):
    """Under the deployed ACL (deploy/router-*.json5, secrets from make-certs.sh): a put on
    vergence/<rig>/fixate gets through from the `fixate` role only, and that role puts nothing else."""
    from deploy_helpers import make_secrets, puts_through_acl, router_config, start_router

    secrets = make_secrets(tmp_path / "secrets")
    conf, endpoint = router_config(variant, secrets, tmp_path / "router.json5")
    with Procs(tmp_path) as P:
        start_router(P, conf, endpoint)
        got = puts_through_acl(secrets, variant, endpoint,
                               ("capture", "worker", "reducer", "actuator", "monitor", "replay", "fixate"),
                               ("vergence/r/fixate", "vergence/*/fixate", "vergence/r/command", "vergence/r/frame"),
                               until=("vergence/*/fixate", b"fixate"))  # its later put: both are in
    assert sorted(k for k in got if k[0].endswith("/fixate")) == [("vergence/*/fixate", b"fixate"),
                                                                  ("vergence/r/fixate", b"fixate")]
    assert not any(who == b"fixate" and not key.endswith("/fixate") for key, who in got)
