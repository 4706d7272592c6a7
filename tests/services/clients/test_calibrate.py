"""`vergence calibrate` against running rigs (real processes): a sim head whose slave camera sits off its encoder's
zero and whose images are at another focal length than the settings say is measured, the settings written, and the
head restarted with them fixates at the right depth; a head it cannot measure is refused, with the reason, within
10 s. The fit itself: tests/vergence/head/test_calibrate.py."""

import math
import re
import statistics
import time
import tomllib

import pytest

from procs import Procs, run, wait_for
from vergence.wire.messages import Decision, Frame

# a draw of its own (the figures in docs/DEPTH.md come from seeds 21-24)
ZERO, FOCAL_TRUE, Z, SEED = -1.5, 540.0, 0.8, 31
CX, CY = 335, 228
# the slave camera's converged pan off the truth: the 0.5 px, and the motor stops on a tick (0.088 deg, 0.83 px
# at f 540): the same draw gave -0.33 and +0.49 px at the centre in two runs, the sim's pinhole at 0.43 (docs/DEPTH.md)
TOL_PX = 0.5 + 0.5 * 540 * math.tan(math.radians(360 / 4096))
LATENCY = 0.066  # s: the images' age when read, not stamped (`vergence latency` is measured on this head too)


def _source(z: float, extra: str = "") -> str:
    # the camera's images LATENCY old when read, and not stamped: the capture stamps them at their read less [camera]
    # latency_s (0 until calibrate writes it); its cameras' principal point 15 and 12 px off the centre, their
    # lenses' barrel k1 = -0.25 (the capture removes it); the target 0.6 m wide
    return (f"sim:motion=still:z={z}:focal=500:zero={ZERO}:focal_true={FOCAL_TRUE}:seed={SEED}:latency={LATENCY}"
            f":stamps=no:cx={CX}:cy={CY}:k1=-0.25:target=0.6{extra}")


def _depth(P: Procs, s, at: tuple[int, int], offset_deg: float) -> tuple[float, float]:
    """At the fovea `at`: the median depth of 40 converged decisions, and of the slave camera's pan less the
    simulator's truth (px at f) over their frames (the camera's pan: the frame's, the encoder's plus offset_deg, less
    offset_deg plus the camera's true zero)."""
    got, frames = P.collect(s, P.key("decision")), P.collect(s, P.key("frame"))
    conv = lambda: [d for d in (Decision.from_bytes(b) for _, b, _ in got.snapshot()) if d.converged  # noqa: E731
                    and (d.x, d.y) == at]
    wait_for(lambda: len(conv()) >= 40, 60, f"40 converged decisions at {at}", logs=P.logs)
    seen = {d.frame for d in conv()}
    lie = math.radians(ZERO - offset_deg)
    errs = [FOCAL_TRUE * math.tan(f.pan_rad + lie - f.truth_pan_rad) for f in (Frame.from_bytes(b) for _, b, _ in
                                                                          frames.snapshot()) if f.frame in seen]
    got.close()
    frames.close()
    return statistics.median(d.depth_m for d in conv()), statistics.median(errs)


@pytest.mark.slow
def test_calibrate_measures_the_zero_focal_and_latency_and_the_head_restarted_with_them_fixates_at_the_depth(
        tmp_path):
    """The head's images 66 ms old and not stamped, [camera] latency_s unset, its depth off by the zero: `vergence
    latency` measures the latency (issue #33's 66 ms case), calibrate measures it all, and the head restarted with
    the file converges at the right depth, at the centre and at a fovea 150 px off it."""
    from procs import free_port

    cfg = tmp_path / "head.toml"
    cfg.write_text("# my head\n[actuator.motor]\nmax_step_deg = 8  # kept\n")
    with Procs(tmp_path) as P:
        P.endpoint = f"tcp/127.0.0.1:{free_port()}"
        up = P.start("up", "up", "--listen", P.endpoint, "--workers", "1", "--rate", "60", "--source", _source(Z),
                     "--config", str(cfg), "--no-standby", connect=False)
        got = P.collect(P.session(timeout=30), P.key("decision"))
        wait_for(lambda: sum(Decision.from_bytes(b).confident for _, b, _ in got.snapshot()) >= 10, 60,
                 "10 confident decisions", logs=P.logs)
        got.close()
        r = run("latency", "--connect", P.endpoint, "--rig", P.rig, timeout=60)
        assert r.returncode == 0, r.stdout + r.stderr
        measured = float(re.search(r"exposure to read: (-?[\d.]+) \+- ([\d.]+) ms", r.stdout)[1])
        print(f"\nvergence latency: {measured:.1f} ms (truth {LATENCY * 1e3:.0f})")
        # the read time a latency ends at is the capture's, later under load: 67.7-68.5 ms here idle, 71.6 once beside
        # a fresh-clone CI run's background work (2026-12-03); the 5 ms Must is test_latency.py's, on its own head
        assert measured == pytest.approx(LATENCY * 1e3, abs=6.5)
        t0 = time.monotonic()
        r = run("calibrate", "--connect", P.endpoint, "--rig", P.rig, "--config", str(cfg),
                "--distance", str(Z), "--write", str(cfg), timeout=60)
        took = time.monotonic() - t0
        assert r.returncode == 0, r.stdout + r.stderr
        print(f"\n{r.stdout}calibrate took {took:.1f} s")
        off = float(re.search(r"pan zero: off by ([-+\d.]+) \+-", r.stdout)[1])
        focal = float(re.search(r"focal length: ([\d.]+) \+-", r.stdout)[1])
        latency = float(re.search(r"camera latency: ([\d.]+) \+-", r.stdout)[1])
        # the Must; this draw, 7 runs: -1.4968 to -1.5109 (with 9 steps, not 17: -1.488 to -1.531 over 11 runs)
        assert off == pytest.approx(ZERO, abs=0.015)
        assert focal == pytest.approx(FOCAL_TRUE, rel=0.01)
        assert latency == pytest.approx(LATENCY * 1e3, abs=5.0)
        assert "the image follows the motor" in r.stdout
        written = tomllib.loads(cfg.read_text())
        assert written["actuator"]["motor"]["max_step_deg"] == 8 and "# kept" in cfg.read_text()
        assert written["actuator"]["motor"]["offset_deg"] == pytest.approx(ZERO, abs=0.015)
        assert written["rig"]["focal_px"] == pytest.approx(focal, abs=0.051)  # (printed to 0.1 px: 538.95 as 538.9)
        assert written["camera"]["latency_s"] == pytest.approx(latency / 1e3, abs=0.0005)
        up.stop()
        # without the settings the depth would be off by about +54 % (the zero's 1.5 deg at 0.8 m: docs/DEPTH.md)
        P.start("up2", "up", "--listen", P.endpoint, "--workers", "1", "--rate", "60", "--source", _source(Z),
                "--config", str(cfg), "--no-standby", connect=False)
        s = P.session(timeout=30)
        offset = written["actuator"]["motor"]["offset_deg"]
        after, err = _depth(P, s, (320, 240), offset)
        print(f"depth with the written settings: {after:.4f} m, the slave {err:+.2f} px off the truth")
        assert after == pytest.approx(Z, rel=0.01) and abs(err) <= TOL_PX
        # a fovea 150 px off the centre, where the lens bends the image most: as at the centre (a pinhole's figures)
        r = run("fixate", "470,240", "--connect", P.endpoint, "--rig", P.rig, timeout=30)
        assert r.returncode == 0, r.stdout + r.stderr
        off_centre, err = _depth(P, s, (470, 240), offset)
        print(f"at (470, 240): depth {off_centre:.4f} m, the slave {err:+.2f} px off the truth")
        assert off_centre == pytest.approx(Z, rel=0.01) and abs(err) <= TOL_PX


@pytest.mark.slow
def test_calibrate_refuses_a_head_it_cannot_measure_within_10_s_with_the_reason(tmp_path):
    """Two heads side by side: a flat scene, a motor too weak to move (a camera turning against its motor:
    tests/scenarios/test_faults.py, on its reversed head)."""
    from procs import free_port

    slow = tmp_path / "slow.toml"
    slow.write_text("[actuator.motor]\nmax_speed_deg_s = 0.01\n")
    heads = {"flat": ("sim:motion=still:z=1.5:seed=33:texture=flat", None, r"none of the last \d+ decisions is "
                      r"confident .*textured scene"),
             "weak": ("sim:motion=still:z=3:seed=34", slow, r"the motor moved 0.0\d+ deg .*does not follow")}
    with Procs(tmp_path) as P:
        ends = {}
        for name, (src, conf, _) in heads.items():
            ends[name] = f"tcp/127.0.0.1:{free_port()}"
            P.start(name, "up", "--listen", ends[name], "--workers", "1", "--rate", "30", "--source", src,
                    *(["--config", str(conf)] if conf else []), "--no-standby", connect=False)
        for name in heads:
            P.endpoint = ends[name]
            s = P.session(timeout=30)
            got = P.collect(s, P.key("decision"))
            got.wait(5, 60)
            got.close()
        for name, (_, conf, why) in heads.items():
            t0 = time.monotonic()
            r = run("calibrate", "--hold-s", "0.1", "--connect", ends[name], "--rig", P.rig,
                    *(["--config", str(conf)] if conf else []), timeout=60)
            took = time.monotonic() - t0
            print(f"\n{name}: {took:.1f} s: {r.stderr.strip()}")
            assert r.returncode == 2, r.stdout + r.stderr
            assert re.search(why, r.stderr), r.stderr
            assert took < 10
        # an --at for each --distance, or none
        r = run("calibrate", "--connect", ends["flat"], "--distance", "1", "--distance", "2", "--at", "320,240",
                timeout=30)
        assert r.returncode == 2 and "1 --at for 2 --distance" in r.stderr, r.stderr


@pytest.mark.slow
def test_calibrate_measures_the_pan_axis_from_three_points_and_the_head_restarted_with_it_fixates_at_the_depth(
        tmp_path):
    """A head whose slave turns about an axis 3 cm behind its optical centre (the sim's axis=), its camera 0.4 deg
    off its encoder, a target at 0.5 m, a square at 0.8 m beside it (side=) and the wall at 3 m: calibrate with a
    point on each measures the axis, the zero, the baseline and the focal length (the steps' slopes read 1-6 % over
    it through the axis's parallax), and the head restarted with them fixates the target at 0.5 m within 1 % (0.530 m
    with pan_axis_m 0: the slave's centre 3.3 mm nearer the master as it turned, taken for a shorter baseline)."""
    from procs import free_port

    cfg = tmp_path / "head.toml"
    source = "sim:motion=still:z=0.5:side=0.8:focal=500:axis=0.03:zero=0.4:seed=47"
    with Procs(tmp_path) as P:
        P.endpoint = f"tcp/127.0.0.1:{free_port()}"
        up = P.start("up", "up", "--listen", P.endpoint, "--workers", "1", "--rate", "60", "--source", source,
                     "--no-standby", connect=False)
        got = P.collect(P.session(timeout=30), P.key("decision"))
        wait_for(lambda: sum(Decision.from_bytes(b).confident for _, b, _ in got.snapshot()) >= 10, 60,
                 "10 confident decisions", logs=P.logs)
        got.close()
        r = run("calibrate", "--connect", P.endpoint, "--rig", P.rig, "--distance", "0.5", "--at", "320,240",
                "--distance", "0.8", "--at", "512,240", "--distance", "3", "--at", "100,240", "--write", str(cfg),
                "--hold-s", "0.2", timeout=90)  # (0.2 s a step, not 0.3: 5 s less; the same draw by hand: 29.0 mm)
        assert r.returncode == 0, r.stdout + r.stderr
        print(f"\n{r.stdout}")
        written = tomllib.loads(cfg.read_text())
        # seeds 43, 61, 62 by hand (docs/DEPTH.md): the axis 1-3 mm off, the zero 0.0007-0.0025 deg, the focal 0.1 %
        assert written["rig"]["pan_axis_m"] == pytest.approx(0.03, abs=0.004)
        assert written["actuator"]["motor"]["offset_deg"] == pytest.approx(0.4, abs=0.015)
        assert written["rig"]["baseline_m"] == pytest.approx(0.06, abs=0.0006)
        assert written["rig"]["focal_px"] == pytest.approx(500, rel=0.005)
        up.stop()
        P.start("up2", "up", "--listen", P.endpoint, "--workers", "1", "--rate", "60", "--source", source,
                "--config", str(cfg), "--no-standby", connect=False)
        got = P.collect(P.session(timeout=30), P.key("decision"))
        conv = lambda: [d.depth_m for d in (Decision.from_bytes(b) for _, b, _ in got.snapshot())  # noqa: E731
                        if d.converged and math.isfinite(d.depth_m)]
        wait_for(lambda: len(conv()) >= 30, 60, "30 converged decisions", logs=P.logs)
        z = statistics.median(conv()[-30:])
        print(f"depth with the written settings: {z:.4f} m (target at 0.5)")
        assert z == pytest.approx(0.5, rel=0.01)


def test_the_report_measures_the_pan_axis_from_three_distances_and_keeps_the_settings_from_two():
    """calibrate's report of its runs' fits (in-process): points at 0.4, 0.8 and 3 m (two off the centre) of a head
    whose slave turns about an axis 2.5 cm behind its optical centre, its camera 0.4 deg off its encoder: the axis,
    the baseline, the zero and the focal length (out of the fits' parallax), with the TOML values; the first two points
    alone: the baseline and zero, the axis the settings'."""
    from types import SimpleNamespace as NS

    from services.clients.calibrate import report
    from vergence.config import load
    from vergence.head.calibrate import slope_focal
    from vergence.sim.moving import MovingRig

    settings = load(None)
    frame = NS(principal=(320, 240), slave_principal=(320, 240), width=640, height=480, master_pan_rad=0.0,
               tilt_rad=0.0, focal_px=500.0)
    lat = NS(latency_s=0.0, sigma_s=0.001, delta_s=0.0)
    points = []
    for z, x in ((0.4, 320), (0.8, 420), (3.0, 230)):  # each on the target, 240 px wide
        truth = MovingRig.from_options(motion=f"still:z={z}", focal="500", axis="0.025", bg="6").truth_at(x, 240)
        # each fit's focal length as the axis's parallax makes it (5 % at 0.4 m: tests/vergence/head/)
        fit = NS(n=17, r2=0.9999, rms_px=0.02, focal_px=slope_focal(500.0, 0.025, 0.06, z, x - 320, x - 320),
                 focal_sigma_px=0.5, latency=lat, pan0_rad=truth - math.radians(0.4),
                 pan0_sigma_rad=math.radians(0.003))
        points.append((fit, (x, 240), z))
    states = [NS(offset_deg=0.0)]
    values, lines = report(points, states, frame, settings)
    text = "\n".join(lines)
    assert values["rig"]["pan_axis_m"] == pytest.approx(0.025, abs=0.001), text
    assert values["rig"]["baseline_m"] == pytest.approx(0.06, abs=0.0003)
    assert values["rig"]["focal_px"] == pytest.approx(500, abs=0.5)  # the fits' mean: 517.2
    assert values["actuator.motor"]["offset_deg"] == pytest.approx(0.4, abs=0.005)
    assert re.search(r"pan axis: \+2[45]\.\d \+- \d\.\d mm behind", text)
    assert re.search(r"focal length: 50[01]\.\d", text)
    values, lines = report(points[:2], states, frame, settings)
    assert "pan_axis_m" not in values["rig"] and "points at three distances or more" in "\n".join(lines)


def test_the_report_takes_the_settings_pan_axis_out_of_the_focal_length_at_one_point(tmp_path):
    """One point at 0.5 m on a head whose settings say its pan axis is 3 cm behind the optical centre: the steps' fit
    reads 6 % over the focal length (the parallax, slope_focal); the report writes the focal length itself (500 px),
    and the zero as the axis moves the pan (0.4 deg, where ignoring the axis would be 0.13 deg off at 3 cm)."""
    from types import SimpleNamespace as NS

    from services.clients.calibrate import report
    from vergence.config import load
    from vergence.head.calibrate import slope_focal
    from vergence.sim.moving import MovingRig

    cfg = tmp_path / "axis.toml"
    cfg.write_text("[rig]\npan_axis_m = 0.03\n")
    settings = load(str(cfg))
    frame = NS(principal=(320, 240), slave_principal=(320, 240), width=640, height=480, master_pan_rad=0.0,
               tilt_rad=0.0, focal_px=500.0)
    lat = NS(latency_s=0.0, sigma_s=0.001, delta_s=0.0)
    truth = MovingRig.from_options(motion="still:z=0.5", focal="500", axis="0.03").truth_at(320, 240)
    seen = slope_focal(500.0, 0.03, 0.06, 0.5, 0.0, 0.0)
    fit = NS(n=17, r2=0.9999, rms_px=0.02, focal_px=seen, focal_sigma_px=0.5, latency=lat,
             pan0_rad=truth - math.radians(0.4), pan0_sigma_rad=math.radians(0.003))
    values, lines = report([(fit, None, 0.5)], [NS(offset_deg=0.0)], frame, settings)
    assert seen == pytest.approx(530, abs=1.5)
    assert values["rig"]["focal_px"] == pytest.approx(500, abs=0.2), lines
    assert values["actuator.motor"]["offset_deg"] == pytest.approx(0.4, abs=0.002)
    # and with no distance at all: the point's distance from its pan with the settings, the focal length the same
    values, _ = report([(fit, None, None)], [NS(offset_deg=0.0)], frame, settings)
    assert values["rig"]["focal_px"] == pytest.approx(500, abs=2.0)
