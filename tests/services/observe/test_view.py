"""`vergence view` (the cockpit in Rerun), `vergence sim --save` and `vergence replay --view`: every test reads
the .rrd back with rerun's own reader (rerun.chunk.RrdReader) and checks the values logged, not only the paths.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from procs import VERGENCE, Procs, free_port, gives_up_without_a_router, run, wait_for
from vergence.wire import messages as M
from vergence.io.recording import Writer

rr = pytest.importorskip("rerun", reason="rerun-sdk (the [view] extra, part of [test]) is not installed")
from rerun.chunk import RrdReader  # noqa: E402

from services.observe import view  # noqa: E402


def read_rrd(path) -> dict[str, list[dict]]:
    """entity path -> its rows, each {"frame": n or None, component: value}, in frame order."""
    out: dict[str, list[dict]] = {}
    for chunk in RrdReader(str(path)).stream().to_chunks():
        b = chunk.to_record_batch()
        comps = [n for n in b.schema.names if ":" in n]
        frames = b.column("frame").to_pylist() if "frame" in b.schema.names else [None] * b.num_rows
        cols = {c: b.column(c).to_pylist() for c in comps}
        rows = out.setdefault(chunk.entity_path, [])
        for i in range(b.num_rows):
            rows.append({"frame": frames[i], **{c: v[i] for c, v in cols.items()}})
    for rows in out.values():
        rows.sort(key=lambda r: -1 if r["frame"] is None else r["frame"])
    return out


def by_frame(rows: list[dict], comp: str) -> dict[int, object]:
    return {r["frame"]: r[comp] for r in rows if r["frame"] is not None and r.get(comp) is not None}


def scalar(rows: list[dict]) -> dict[int, float]:
    return {f: v[0] for f, v in by_frame(rows, "Scalars:scalars").items()}


def image(row: dict) -> np.ndarray:
    fmt = row["Image:format"][0] if isinstance(row["Image:format"], list) else row["Image:format"]
    buf = row["Image:buffer"][0] if isinstance(row["Image:buffer"][0], (list, bytes)) else row["Image:buffer"]
    return np.asarray(buf, np.uint8).reshape(fmt["height"], fmt["width"], -1)


def cpu_s(pid: int) -> float:
    """CPU seconds (user + system) a process used so far, all its threads."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def frames_of(items) -> list[int]:
    return sorted({M.Decision.from_bytes(b).frame for _, b, _ in items})


def missing(frames: list[int]) -> int:
    """Frame ids between the first and the last that got no decision."""
    return frames[-1] - frames[0] + 1 - len(frames) if frames else 0


# ---- the live cockpit beside `vergence up` -------------------------------------------------------------------

@pytest.mark.slow
def test_view_save_records_3s_of_up(tmp_path):
    """`vergence up` (simulated rig, 60 Hz, previews at 10 Hz and 320 px) and `vergence view --save`: 3 s of
    it in the .rrd, with the images, both boxes where the decisions put them, the profile and the pan, on the
    frame numbers of the decisions the test itself received; and what the view costs the loop (frames left
    without a decision, 3 s without and 3 s with it; VERGENCE_VIEW_COST_S=10 for longer windows)."""
    span = float(os.environ.get("VERGENCE_VIEW_COST_S", "3"))
    cfg = tmp_path / "settings.toml"
    cfg.write_text("[capture]\npreview_hz = 10\npreview_width = 320\n")
    rrd = tmp_path / "cockpit.rrd"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Procs(tmp_path) as P:
        P.endpoint = endpoint
        P.start("up", "up", "--listen", endpoint, "--source", "sim", "--workers", "2", "--rate", "60",
                "--config", str(cfg), "--no-standby", connect=False)
        s = P.session()
        decisions = P.collect(s, P.key("decision"))
        wait_for(lambda: len(decisions) >= 10, 180, "the loop's first decisions", logs=P.logs)  # slow warm-up
        n0 = len(decisions)
        wait_for(lambda: len(decisions) >= n0 + 60 * span, 5 + 3 * span, "decisions without the view", logs=P.logs)
        before = frames_of(decisions.snapshot()[n0:])
        v = P.start("view", "view", "--save", str(rrd))
        wait_for(lambda: "view: rig" in v.text(), 60, "the view to subscribe", logs=P.logs)
        n = len(decisions)  # the view's first second (its first frames and previews) is not measured
        wait_for(lambda: len(decisions) >= n + 60, 10, "a second of decisions with the view", logs=P.logs)
        n1, c0, t0 = len(decisions), cpu_s(v.pid), time.monotonic()
        wait_for(lambda: len(decisions) >= n1 + 60 * span, 5 + 3 * span, "decisions with the view", logs=P.logs)
        during = frames_of(decisions.snapshot()[n1:])
        share = (cpu_s(v.pid) - c0) / (time.monotonic() - t0)
        v.signal(signal.SIGINT)
        assert v.wait(30) == 0, v.tail()
        assert "Traceback" not in v.text()
        got = {d.frame: d for d in (M.Decision.from_bytes(b) for _, b, _ in decisions.snapshot())}
    # the loop's cost: frames left without a decision (gaps in the frame ids), `span` s without and with the view
    lost_before, lost_during = missing(before), missing(during)
    print(f"\nframes without a decision: {lost_before} of {len(before) + lost_before} without the view, "
          f"{lost_during} of {len(during) + lost_during} with it; the view used {100 * share:.0f} % of a core")
    # a shared 2-core machine loses the odd frame with or without it, and on a slow day the view's 0.7 of a core
    # leaves the loop short for a few (6 of 186 once; 9 of 189 beside a fresh-clone test run, 2026-12-03): at most
    # 2 or 6 % more
    assert lost_during <= lost_before + max(2, 0.06 * (len(during) + lost_during))
    e = read_rrd(rrd)
    for path in ("/rig/master", "/rig/slave", "/rig/master/fovea", "/rig/slave/match", "/rig/correlation",
                 "/pan/slave", "/pan/motor", "/decision/confidence", "/workers/alive"):
        assert e.get(path), f"{path} missing from the recording: {sorted(e)}"
    # images: the previews, 320 x 240, textured
    img = image(e["/rig/master"][-1])
    assert img.shape[:2] == (240, 320) and img.std() > 10
    # every decision the view logged is one the rig made, on its frame number, with its values
    pans = scalar(e["/pan/slave"])
    assert len(pans) >= 150, len(pans)  # 3 s at 60 Hz, less what the view missed while it started
    # (the test's own subscriber, a client of the router, may lose a decision the view got under load: 1 of 186 once)
    unseen = set(pans) - set(got)
    assert len(unseen) <= 2, sorted(unseen)[:5]
    for f, deg in pans.items():
        if f not in unseen:
            assert deg == pytest.approx(math.degrees(got[f].pan_rad), abs=1e-9)
    matches = by_frame(e["/rig/slave/match"], "Boxes2D:centers")
    fovea = by_frame(e["/rig/master/fovea"], "Boxes2D:centers")
    assert len(matches) >= 150 and set(matches) - set(got) <= unseen and set(fovea) == set(matches)
    scale = 320 / 640
    for f, centres in matches.items():
        if f in unseen:
            continue
        d = got[f]
        (cx, cy), = centres
        assert cx == pytest.approx((320 + d.offset_px + 0.5) * scale, abs=1e-3)  # the fovea at the centre
        assert cy == pytest.approx((240 + d.v_shift + 0.5) * scale, abs=1e-3)
        assert fovea[f][0] == pytest.approx([320.5 * scale, 240.5 * scale])
    # the profile: layer 4 over K = W - w + 1 offsets, its maximum where the decision's winner is
    bars = by_frame(e["/rig/correlation"], "BarChart:values")
    assert len(bars) >= 100 and set(bars) - set(got) <= unseen
    for f, value in [(f, v) for f, v in bars.items() if f not in unseen][:20]:
        vals = np.asarray(value[0]["buffer"] if isinstance(value, list) else value["buffer"])
        assert len(vals) == 640 - got[f].window + 1
        assert int(np.argmax(vals)) == got[f].k


# ---- offline: the simulator and recordings ---------------------------------------------------------------

@pytest.mark.slow
def test_sim_save_logs_the_views_the_network_saw(tmp_path):
    """`vergence sim --save`: per frame the two views, the boxes, the profile, pan against truth; the views
    are the ones the loop decided on (the network on the recorded images gives the recorded offsets)."""
    from vergence import Params, match

    rrd = tmp_path / "sim.rrd"
    out = run("sim", "--frames", "4", "--save", str(rrd), "--json", timeout=300)
    assert out.returncode == 0, out.stderr
    import json

    steps = [json.loads(line) for line in out.stdout.splitlines()]
    e = read_rrd(rrd)
    assert [r["frame"] for r in e["/rig/master"]] == [0, 1, 2, 3, 4]
    truth = scalar(e["/pan/truth"])
    pan = scalar(e["/pan/slave"])
    for st in steps:
        assert pan[st["frame"]] == pytest.approx(st["pan_deg"])
        assert truth[st["frame"]] == pytest.approx(st["truth_pan_deg"])
    offsets = scalar(e["/decision/offset_px"])
    for row_m, row_s in zip(e["/rig/master"], e["/rig/slave"]):
        f = row_m["frame"]
        m, s = image(row_m), image(row_s)
        assert m.shape[:2] == (480, 640)
        d = match(m[..., 0] if m.shape[2] == 1 else m, s[..., 0] if s.shape[2] == 1 else s, None, Params())
        assert d.decision.offset_px == pytest.approx(offsets[f], abs=1e-6)
        (cx, _), = by_frame(e["/rig/slave/match"], "Boxes2D:centers")[f]
        assert cx == pytest.approx(320 + offsets[f] + 0.5, abs=1e-3)


def _recording(path: Path, rig: str = "rec") -> list[M.Decision]:
    """A small `vergence record` file: 3 frames of preview, frame, decision, profile, a motor state, a worker's
    token, and one malformed decision."""
    rng = np.random.default_rng(0)
    width, w = 64, 7
    k_count = width - w + 1
    out = []
    with Writer(path, rig=rig) as wr:
        wr.write(f"vergence/{rig}/alive/worker/w1-1", 1, b"", "alive")
        for n in (5, 6, 7):
            t = 1_700_000_000_000_000_000 + n * 10_000_000
            img = rng.integers(0, 255, (24, 32), np.uint8).tobytes()
            wr.write(f"vergence/{rig}/preview", t, M.Preview(rig=rig, frame=n, t_capture_ns=t, width=32, height=24,
                                                              scale=0.5, master=img, slave=img).to_bytes())
            scores = rng.random(k_count)
            k = int(np.argmax(scores))
            fields = dict(rig=rig, frame=n, t_capture_ns=t, t_reduced_ns=t + 3_000_000, window=w, k=k,
                          k_sub=float(k), v_shift=0, k_centre=29, direction=1, magnitude=abs(k - 29),
                          offset_px=float(k - 29), confidence=0.5, confident=True, texture=9.0,
                          pan_rad=0.01 * n)
            v = M.Decision(**fields)
            out.append(v)
            wr.write(f"vergence/{rig}/decision", t, v.to_bytes())
            wr.write(f"vergence/{rig}/profile", t, M.Profile(**fields, width=width, rows=1,
                                                             scores=scores.tobytes()).to_bytes())
            wr.write(f"vergence/{rig}/motor_state", t, M.MotorState(rig=rig, t_ns=t, pan_rad=0.01 * n, goal_rad=0.0,
                                                                    min_rad=-1, max_rad=1, status="ok",
                                                                    frame=n).to_bytes())
        wr.write(f"vergence/{rig}/decision", t, b"\x93garbage")
    return out


@pytest.mark.slow
def test_replay_view_turns_a_recording_into_the_cockpit(tmp_path):
    rec = tmp_path / "run.vrec"
    verdicts = _recording(rec)
    rrd = tmp_path / "replay.rrd"
    out = run("replay", str(rec), "--view", str(rrd), timeout=120)
    assert out.returncode == 0, out.stderr
    assert "'decision': 3" in out.stderr and "bad {'decision': 1}" in out.stderr
    e = read_rrd(rrd)
    assert [r["frame"] for r in e["/rig/master"]] == [5, 6, 7]
    assert scalar(e["/pan/slave"]) == pytest.approx({v.frame: math.degrees(v.pan_rad) for v in verdicts})
    matches = by_frame(e["/rig/slave/match"], "Boxes2D:centers")
    for v in verdicts:  # x = k_centre + w // 2 = 32 (no frame message), y = 24 // 2 ... scaled by 0.5
        (cx, _), = matches[v.frame]
        assert cx == pytest.approx((32 + v.offset_px + 0.5) * 0.5)
    assert [len(r["BarChart:values"][0]["buffer"]) for r in e["/rig/correlation"]] == [58, 58, 58]
    assert scalar(e["/latency/decision_ms"]) == pytest.approx({5: 3.0, 6: 3.0, 7: 3.0})
    assert e["/workers/alive"][0]["Scalars:scalars"] == [1.0]


@pytest.mark.slow
def test_replay_view_rejects_a_bad_target(tmp_path):
    rec = tmp_path / "run.vrec"
    _recording(rec)
    out = run("replay", str(rec), "--view", "out.png", timeout=60)
    assert out.returncode == 2 and "--view wants FILE.rrd, web[:PORT] or spawn" in out.stderr


def test_newer_fields_are_logged_when_present(tmp_path):
    """Fields other branches add (depth on the decision, the truth on the frame) are read with defaults: logged
    when the message carries them, absent otherwise."""
    class Deep(M.Decision, kw_only=True):
        depth_m: float = 1.25
        depth_sigma_m: float = 0.05
        truth_pan_rad: float = 0.02

    rec = rr.RecordingStream("vergence-test")
    path = tmp_path / "c.rrd"
    rec.save(str(path))
    c = view.Cockpit(rr, rec)
    base = dict(rig="r", frame=3, t_capture_ns=1, t_reduced_ns=2, window=7, k=10, k_sub=10.0, v_shift=0,
                k_centre=10, direction=0, magnitude=0, offset_px=0.0, confidence=0.9, confident=True,
                texture=5.0, pan_rad=0.0)
    c._decision(Deep(**base))
    c._decision(M.Decision(**{**base, "frame": 4}))
    assert c.feed("decision", b"not msgpack") is None and c.bad["decision"] == 1
    assert c.feed("status/worker/w1", b"{not json") is None and c.bad["status"] == 1
    rec.disconnect()
    e = read_rrd(path)
    assert scalar(e["/depth"]) == {3: 1.25} and scalar(e["/depth/sigma"]) == {3: 0.05}
    assert scalar(e["/pan/truth"]) == pytest.approx({3: math.degrees(0.02)})
    assert set(scalar(e["/pan/slave"])) == {3, 4}


# ---- what the cockpit shows (issue #28): the profile around its best, one axis per quantity, no tabs -------

def _profile_msg(frame: int = 9, confident: bool = True) -> M.Profile:
    """A profile as the rig's: a 64-px row, w = 7, K = 58 scores near 255 w^2 (12495) with a spread of 3 % and
    the winner at k = 40, the fovea's column at k_centre = 29 (offset +11 px); three rows, v_shift 0."""
    rng = np.random.default_rng(frame)
    scores = 255 * 49 * (0.97 + 0.02 * rng.random((3, 58)))
    scores[1, 40] = 255 * 49 * 0.999
    return M.Profile(rig="r", frame=frame, t_capture_ns=1, t_reduced_ns=2, window=7, k=40, k_sub=40.0, v_shift=0,
                     k_centre=29, direction=1, magnitude=11, offset_px=11.0, confidence=0.8, confident=confident,
                     texture=5.0, pan_rad=0.01, width=64, rows=3, scores=scores.tobytes())


def _cockpit_rrd(tmp_path, *messages) -> dict[str, list[dict]]:
    """The entities a Cockpit logs for these messages (profiles or decisions), read back from a file."""
    rec = rr.RecordingStream("vergence-test")
    path = tmp_path / "cockpit.rrd"
    rec.save(str(path))
    c = view.Cockpit(rr, rec)
    c.scale, c.size = 1.0, (64, 24)  # as after a preview of the full size
    for m in messages:
        c._profile(m) if isinstance(m, M.Profile) else c._decision(m)
    rec.disconnect()
    return read_rrd(path)


def _buffer(value) -> np.ndarray:
    return np.asarray((value[0] if isinstance(value, list) else value)["buffer"], np.float64)


def test_the_profile_is_logged_relative_to_its_best_so_the_winner_stands_out(tmp_path):
    """Layer 4's scores sit near 255 w^2 and differ by a few per cent: on the bar chart's axis from 0 every bar
    looked the same. The cockpit logs them scaled from the row's worst (0) to its best (1), over the offset in
    px (k - k_centre), and the winner once more as a wide bar of its own, coloured as the match box."""
    p = _profile_msg()
    e = _cockpit_rrd(tmp_path, p, M.replace(_profile_msg(10), confident=False))
    row = e["/rig/correlation"][0]
    vals = _buffer(row["BarChart:values"])
    assert len(vals) == 58 and vals.max() == 1.0 and vals.min() == 0.0
    assert int(np.argmax(vals)) == p.k and np.sort(vals)[-2] < 0.8  # the winner is the one bar at the top
    raw = p.array()[1]
    assert vals == pytest.approx((raw - raw.min()) / (raw.max() - raw.min()))
    assert _buffer(row["BarChart:abscissa"]) == pytest.approx(np.arange(58) - 29.0)
    winners = e["/rig/correlation/winner"]
    assert [list(_buffer(r["BarChart:abscissa"])) for r in winners] == [[11.0], [11.0]]
    assert [list(_buffer(r["BarChart:values"])) for r in winners] == [[1.0], [1.0]]
    assert winners[0]["BarChart:widths"][0] >= 5  # several pixels wide at 1600 px
    colours = [r["BarChart:color"][0] for r in winners]
    assert colours[0] != colours[1] and colours[0] != row["BarChart:color"][0]  # confident, abstaining, the rest


def test_a_flat_profile_is_logged_flat_not_divided_by_zero(tmp_path):
    p = _profile_msg()
    flat = M.replace(p, scores=np.full((3, 58), 12495.0).tobytes())
    vals = _buffer(_cockpit_rrd(tmp_path, flat)["/rig/correlation"][0]["BarChart:values"])
    assert np.all(vals == 0.0)


def _walk(node):
    """Every container and view of a blueprint's tree, depth first."""
    yield node
    for child in getattr(node, "contents", None) or []:
        yield from _walk(child)


def _covers(v, path: str) -> bool:
    """Whether a view's contents (origin and its query: $origin, $origin/sub, $origin/**) take the entity."""
    contents = [v.contents] if isinstance(v.contents, str) else list(v.contents)
    for q in contents:
        q = q.replace("$origin", v.origin.strip("/")).strip("/")
        if q == path or (q.endswith("/**") and (path == q[:-3] or path.startswith(q[:-2]))):
            return True
    return False


def test_the_cockpits_blueprint_opens_every_view_at_once_one_quantity_each():
    """No tabs (depth, latency and workers were tabs behind the first, hidden): one tree of vertical and
    horizontal containers, every view in it; and each time series one quantity on its own axis (the window,
    15 px, flattened the confidence and the offset on a shared one)."""
    bp = view.blueprint(rr)
    nodes = list(_walk(bp.root_container))
    containers = [n for n in nodes if hasattr(n, "kind")]
    views = [n for n in nodes if hasattr(n, "class_identifier")]
    assert containers and all(str(c.kind) != "Tabs" and "tabs" not in str(c.kind).lower() for c in containers)
    needed = {"rig/master": "2D", "rig/slave": "2D", "rig/correlation": "BarChart", "rig/readout": "TextDocument",
              "motor/status": "TextLog", "pan/slave": "TimeSeries", "decision/confidence": "TimeSeries",
              "decision/offset_px": "TimeSeries", "decision/window": "TimeSeries", "depth": "TimeSeries",
              "latency/decision_ms": "TimeSeries", "workers/alive": "TimeSeries"}
    for path, kind in needed.items():
        assert [v for v in views if kind in v.class_identifier and _covers(v, path)], f"{path}: no {kind} view"
    quantities = ["decision/confidence", "decision/offset_px", "decision/window", "pan/slave", "depth",
                  "latency/decision_ms", "workers/alive"]
    for v in views:
        if "TimeSeries" in v.class_identifier:
            shown = [q for q in quantities if _covers(v, q)]
            assert len(shown) == 1, f"{v.name}: {shown} on one axis"
    confidence = next(v for v in views if _covers(v, "decision/confidence"))
    assert _covers(confidence, "decision/confident")  # the 1/0 on the same 0..1 axis
    assert confidence.properties["ScalarAxis"].range is not None  # 0..1.05, not zoomed to its noise


def test_the_decision_is_in_large_print_and_the_boxes_labels_are_short(tmp_path):
    """Rerun draws a box's label in a fixed small font (egui's body text), unreadable over the image at 1600 x
    1000 with its numbers: the numbers go into the readout, markdown headings (large), one short word stays on
    each box."""
    e = _cockpit_rrd(tmp_path, _profile_msg())
    doc = e["/rig/readout"][0]
    text = doc["TextDocument:text"][0]
    assert doc["TextDocument:media_type"][0] == "text/markdown"
    assert text.startswith("## +11.0 px, confidence 0.80 (confident)")
    assert "### window 7 px, k 40, pan +0.57 deg" in text
    assert e["/rig/master/fovea"][0]["Boxes2D:labels"] == ["fovea"]
    assert e["/rig/slave/match"][0]["Boxes2D:labels"] == ["match"]


def test_the_web_viewers_files_are_cached_gzipped_and_revalidated(tmp_path, monkeypatch):
    """The web viewer's first picture (issue #28): its files come from the user's cache after the first start (no
    helper process), the 43 MB wasm goes gzip-compressed to a browser that accepts it, and a browser that has
    it gets 304 (it keeps its compiled wasm)."""
    import gzip
    import urllib.request

    from services.observe import web

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    wasm = bytes(range(256)) * 1024
    made = {a: ("application/wasm" if a.endswith(".wasm") else "text/html", wasm if a.endswith(".wasm") else b"x")
            for a in web.ASSETS}
    monkeypatch.setattr(web, "_read_assets", lambda timeout: made)
    first = web.viewer_assets()
    assert first["/re_viewer_bg.wasm"][2] is not None and first["/"][2] is None
    monkeypatch.setattr(web, "_read_assets", lambda timeout: pytest.fail("read again although cached"))
    assert web.viewer_assets() == first and (web.cache_dir() / "index.json").is_file()
    port = free_port()
    httpd = web.serve_offline("127.0.0.1", port, first, 9876)
    try:
        url = f"http://127.0.0.1:{port}/re_viewer_bg.wasm"
        with urllib.request.urlopen(urllib.request.Request(url, headers={"Accept-Encoding": "gzip"})) as r:
            assert r.headers["Content-Encoding"] == "gzip" and r.headers["Content-Type"] == "application/wasm"
            assert gzip.decompress(r.read()) == wasm and "default-src" in r.headers["Content-Security-Policy"]
            tag = r.headers["ETag"]
        with urllib.request.urlopen(url) as r:  # no gzip asked for: the plain file
            assert r.read() == wasm and r.headers.get("Content-Encoding") is None
        try:
            urllib.request.urlopen(urllib.request.Request(url, headers={"If-None-Match": tag}))
            pytest.fail("no 304")
        except urllib.error.HTTPError as e:
            assert e.code == 304
    finally:
        httpd.shutdown()


def test_the_readout_follows_at_most_ten_times_a_second(tmp_path):
    """A person reads the readout; at 60 Hz it would cost the view for nothing: at most one per 0.1 s of
    capture time (and again when the clock goes back, as a new run's)."""
    base = _profile_msg()
    frames = [(1, 0), (2, 50), (3, 99), (4, 120), (5, 230), (6, 20)]  # (frame, capture ms)
    e = _cockpit_rrd(tmp_path, *(M.replace(base, frame=f, t_capture_ns=1 + ms * 1_000_000) for f, ms in frames))
    assert [r["frame"] for r in e["/rig/readout"]] == [1, 4, 5, 6]


@pytest.mark.slow
def test_a_missing_extra_says_how_to_install_it(tmp_path):
    code = ("import sys; sys.modules['rerun_cli'] = None; sys.modules['rerun'] = None\n"
            "from services.ops.cli import main; sys.exit(main(['view', '--save', 'x.rrd', '--connect', "
            "'tcp/127.0.0.1:1']))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        "vergence view: rerun-sdk is not installed; install the viewer extra: pip install 'vergence[view]' "
        "(in a checkout: pip install -e '.[view]')"]


@pytest.mark.slow
def test_analytics_are_off_for_the_user_after_a_project_process_used_rerun(tmp_path):
    """Rerun's one switch (analytics.json under the user's config dir) says disabled after analytics_off, in
    a fresh config dir too."""
    import json

    env = {**os.environ, "XDG_CONFIG_HOME": str(tmp_path / "cfg")}
    code = "from services.observe import view; view.import_rerun()"
    subprocess.run([sys.executable, "-c", code], env=env, check=True, timeout=120, capture_output=True)
    conf = json.loads((tmp_path / "cfg" / "rerun" / "analytics.json").read_text())
    assert conf["analytics_enabled"] is False


# ---- the web viewer in headless Chromium -------------------------------------------------------------------

def image_panel_shown(png: bytes) -> float:
    """The share of the screenshot covered by the grey, textured camera image (the viewer's own UI is flat,
    its text small, dark on light or light on dark): 16 x 16 tiles that are grey (R = G = B within 6) with
    contrast (std > 12), of a mean between 40 and 180."""
    import cv2

    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).astype(np.int16)
    h, w = (img.shape[0] // 16) * 16, (img.shape[1] // 16) * 16
    tiles = img[:h, :w].reshape(h // 16, 16, w // 16, 16, 3).swapaxes(1, 2).reshape(-1, 256, 3)
    grey = (np.abs(tiles[..., 0] - tiles[..., 1]).max(1) <= 6) & (np.abs(tiles[..., 1] - tiles[..., 2]).max(1) <= 6)
    textured = tiles.mean(2).std(1) > 12
    mean = tiles.mean((1, 2))
    return float((grey & textured & (mean > 40) & (mean < 180)).mean())  # < 180: not text on a light page


def colours(png: bytes) -> int:
    """Distinct colours of a screenshot (at 5 bits a channel): the loading page has fewer than 100."""
    import cv2

    q = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).reshape(-1, 3).astype(np.int32) // 8
    return len(np.unique(q[:, 0] * 1024 + q[:, 1] * 32 + q[:, 2]))


def profile_shown(png: bytes) -> tuple[int, float]:
    """In the profile's panel (the middle row's left half at 1600 x 1000): the pixels of the winner's bar (green
    or orange, as the match box) and the spread (std, px) of the other bars' heights (their translucent grey-blue,
    per column; on an axis from 0, raw, they were all of a height)."""
    import cv2

    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[440:780, :800, ::-1].astype(np.int16)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    winner = int((((g - r >= 60) & (g - b >= 60)) | ((r - b >= 80) & (r > g))).sum())
    heights = ((b - r >= 10) & (g >= r) & (img.max(2) < 240)).sum(0)
    return winner, float(heights[heights > 0].std()) if (heights > 0).sum() > 50 else 0.0


@pytest.mark.slow
def test_web_viewer_shows_the_cockpit_in_headless_chromium(tmp_path):
    """`vergence view --web` beside `vergence up`: Debian's headless Chromium (SwiftShader WebGL) at 1600 x 1000
    loads the viewer the wheel ships, and the screenshot shows the cockpit: the camera image, the profile with
    the winner's bar and bars of differing heights, many colours; no request leaves for another host. Prints the
    time from the view's start to the viewer's first picture (the camera image shown) and to the profile's. Set
    VERGENCE_SCREENSHOT=FILE.png to keep the screenshot (docs/cockpit.png)."""
    from cdp import Browser, find_browser

    exe = find_browser()
    if exe is None:
        pytest.skip("no headless Chromium (apt-get install chromium-headless-shell): the web viewer is not "
                    "screenshot here; the .rrd tests still run")
    cfg = tmp_path / "settings.toml"
    cfg.write_text("[capture]\npreview_hz = 5\npreview_width = 320\n")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    web, grpc, devtools = free_port(), free_port(), free_port()
    with Procs(tmp_path) as P:
        P.endpoint = endpoint
        # the default source, README's demo: the target moving in depth (the pan panel: the slave and the truth)
        P.start("up", "up", "--listen", endpoint, "--workers", "1", "--rate", "20", "--config", str(cfg),
                connect=False)
        s = P.session()
        decisions = P.collect(s, P.key("decision"))
        wait_for(lambda: len(decisions) >= 3, 180, "the loop's first decisions", logs=P.logs)
        t0 = time.monotonic()
        v = P.start("view", "view", "--web", "--port", str(web), "--grpc-port", str(grpc), "--bind", "127.0.0.1")
        url = wait_for(lambda: next((w for w in v.text().split() if w.startswith(f"http://127.0.0.1:{web}/")),
                                    None), 60, "the viewer's URL", logs=P.logs, interval=0.05)
        t_url = time.monotonic() - t0
        with open(tmp_path / "chromium.log", "wb") as log:
            b = Browser(exe, "about:blank", devtools, str(tmp_path / "profile"), log, width=1600, height=1000)
            try:
                b.connect()
                b.call("Network.enable", maxTotalBufferSize=4096, maxResourceBufferSize=1024)  # no bodies kept
                b.call("Page.navigate", url=url)  # once the requests are watched
                shots, first, times = [], [], []

                def shown():
                    png = b.screenshot()
                    if png is None:
                        return False
                    shots.append(png)
                    times.append(time.monotonic() - t0)
                    if not first and image_panel_shown(png) > 0.1:  # the camera image: past the loading and
                        first.append(times[-1])  # welcome pages
                    return bool(first) and profile_shown(png)[0] > 200

                # the cockpit takes 20-50 s on 2 shared cores in software GL; a loaded machine takes longer
                wait_for(shown, 300, "the cockpit in the screenshot", interval=1,
                         logs=lambda: f"{len(shots)} screenshots, last cover {image_panel_shown(shots[-1]):.3f}, "
                                      f"profile {profile_shown(shots[-1])}" if shots else "no screenshot")
                t_cockpit = time.monotonic() - t0
                png = shots[-1]
            finally:
                b.close()
        assert v.alive(), v.tail()
    for t, shot in zip(times, shots):  # each, to look at
        (tmp_path / f"shot-{t:05.1f}s.png").write_bytes(shot)
    (tmp_path / "cockpit.png").write_bytes(png)
    if os.environ.get("VERGENCE_SCREENSHOT"):
        Path(os.environ["VERGENCE_SCREENSHOT"]).write_bytes(png)
    print(f"\nweb viewer at 1600 x 1000: URL {t_url:.1f} s, first picture {first[0]:.1f} s, the profile "
          f"{t_cockpit:.1f} s after `vergence view --web` started (screenshots at "
          f"{', '.join(f'{t:.1f}' for t in times)} s)")
    winner, spread = profile_shown(png)
    assert colours(png) > 300 and winner > 200 and spread > 15, (colours(png), winner, spread)
    # nothing left for another host: the bundled viewer's analytics, release check and fonts are blocked by
    # the page's Content-Security-Policy before they are sent
    out = {u for i, u in b.requests.items() if not u.startswith(("http://127.0.0.1", "data:", "blob:"))
           and b.blocked.get(i) != "csp"}
    print("blocked by the page's CSP:", sorted({b.requests[i].split("?")[0] for i, r in b.blocked.items()
                                                 if r == "csp" and i in b.requests}))
    assert not out, out
    # and the console says why: the viewer's analytics calls were refused by the policy, none sent
    console = (tmp_path / "chromium.log").read_text(errors="replace")
    calls = [line for line in console.splitlines() if "tel.rerun.io" in line]
    assert all("Content Security Policy" in line for line in calls), calls[:3]


@pytest.mark.slow
def test_view_without_a_router_gives_up_at_its_timeout(tmp_path):
    """A client keeps trying to reach its router; the view still stops (its --timeout here, Ctrl-C the same
    way), saying why, with nothing left behind."""
    out = run("view", "--save", str(tmp_path / "x.rrd"), "--connect", f"tcp/127.0.0.1:{free_port()}", "--timeout", "2",
              timeout=60)
    assert out.returncode == 1
    assert "vergence view: no Zenoh router or peer answered at tcp/127.0.0.1:" in out.stderr
    assert "Traceback" not in out.stderr


@pytest.mark.slow
def test_view_without_a_router_gives_up_within_its_wait(tmp_path):
    """Issue #28: without --timeout it kept trying forever; --wait (default 5 s) bounds the wait for a router."""
    gives_up_without_a_router("view", "--save", str(tmp_path / "x.rrd"), "--wait", "1", within=1)


@pytest.mark.slow
def test_spawn_without_a_display_says_what_to_do_instead(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    out = subprocess.run([VERGENCE, "view", "--timeout", "2", "--connect", f"tcp/127.0.0.1:{free_port()}"],
                         capture_output=True, text=True, timeout=60, env=env)
    assert out.returncode == 2
    assert "--spawn needs a display" in out.stderr and "give --web" in out.stderr


def test_each_change_of_the_motors_status_is_a_text_log_faults_as_errors(tmp_path):
    """Issue #29: the cockpit logs the motor's status at motor/status when it changes, ERROR for disconnected and
    absent (a fault), INFO otherwise; the same status again logs nothing."""
    rec = rr.RecordingStream("vergence-test")
    path = tmp_path / "m.rrd"
    rec.save(str(path))
    c = view.Cockpit(rr, rec)
    st = M.MotorState(rig="r", t_ns=1, pan_rad=0.0, goal_rad=0.0, min_rad=-1, max_rad=1, status="ok", frame=1)
    for i, (status, note) in enumerate([("ok", ""), ("ok", ""), ("disconnected", "no answer for 0.6 s"),
                                        ("absent", "command ignored: motor absent for 2.1 s"), ("ok", "")]):
        c._motor(M.replace(st, t_ns=1 + i, frame=1 + i, status=status, note=note))
    rec.disconnect()
    rows = read_rrd(path)["/motor/status"]
    got = [(r["TextLog:text"][0], r["TextLog:level"][0]) for r in rows]
    assert got == [("motor ok", "INFO"), ("motor disconnected: no answer for 0.6 s", "ERROR"),
                   ("motor absent: command ignored: motor absent for 2.1 s", "ERROR"), ("motor ok", "INFO")], got


def test_a_named_fault_is_an_error_in_the_cockpit_and_its_clearing_an_info(tmp_path):
    """Issue #35: the reducer's `fault` (vergence.head.doubt) goes to `fault` when it changes, ERROR with what to
    check; cleared, INFO; the same fault again, or a forged name, logs nothing."""
    import json

    rec = rr.RecordingStream("vergence-test")
    path = tmp_path / "f.rrd"
    rec.save(str(path))
    c = view.Cockpit(rr, rec)
    st = {"role": "reducer", "id": "r-1", "counters": {}, "bad": {}}
    for i, extra in enumerate([{}, {"fault": "reversed", "fault_note": "flip it"},
                               {"fault": "reversed", "fault_note": "flip it"}, {"fault": "gremlins"},
                               {"fault": "stalled", "fault_note": "torque"}]):
        c._status("status/reducer/r-1", json.dumps(dict(st, **extra)).encode(), 1 + i)
    rec.disconnect()
    got = [(r["TextLog:text"][0], r["TextLog:level"][0]) for r in read_rrd(path)["/fault"]]
    assert got == [("FAULT reversed: flip it", "ERROR"), ("fault cleared", "INFO"),
                   ("FAULT stalled: torque", "ERROR")], got


def test_a_search_is_a_warning_in_the_cockpit_each_time_it_says_more(tmp_path):
    """Issue #35: the reducer's search (vergence.head.search) goes to `search` when what it says changes: searching,
    a sweep that found nothing (asking whether the slave can see the point), over; the same again logs nothing."""
    import json

    rec = rr.RecordingStream("vergence-test")
    path = tmp_path / "s.rrd"
    rec.save(str(path))
    c = view.Cockpit(rr, rec)
    st = {"role": "reducer", "id": "r-1", "counters": {}, "bad": {}}
    for i, extra in enumerate([{}, {"searching": True, "sweeps_empty": 0}, {"searching": True, "sweeps_empty": 0},
                               {"searching": True, "sweeps_empty": 1}, {"searching": False, "sweeps_empty": 0}]):
        c._status("status/reducer/r-1", json.dumps(dict(st, **extra)).encode(), 1 + i)
    rec.disconnect()
    got = [(r["TextLog:text"][0], r["TextLog:level"][0]) for r in read_rrd(path)["/search"]]
    assert [level for _, level in got] == ["WARN", "WARN", "INFO"], got
    assert got[0][0] == "searching: no confident match at the fovea" and got[2][0] == "search over"
    assert got[1][0].startswith("searching: no confident match at the fovea; 1 sweep of the pan range found nothing")


def test_a_fovea_with_no_texture_is_a_warning_in_the_cockpit_and_its_end_an_info(tmp_path):
    """Issue #35 ("no texture / black: abstain, and name it"): the reducer's `no_texture` goes to `texture` as a
    warning when it begins, once, and as an info when the fovea has texture again."""
    import json

    rec = rr.RecordingStream("vergence-test")
    path = tmp_path / "t.rrd"
    rec.save(str(path))
    c = view.Cockpit(rr, rec)
    st = {"role": "reducer", "id": "r-1", "counters": {}, "bad": {}}
    for i, extra in enumerate([{}, {"no_texture": True}, {"no_texture": True}, {"no_texture": False}]):
        c._status("status/reducer/r-1", json.dumps(dict(st, **extra)).encode(), 1 + i)
    rec.disconnect()
    got = [(r["TextLog:text"][0], r["TextLog:level"][0]) for r in read_rrd(path)["/texture"]]
    assert [level for _, level in got] == ["WARN", "INFO"], got
    assert got[0][0].startswith("no texture at the fovea (a black or flat image") and \
        got[1][0] == "texture at the fovea again"


@pytest.mark.slow
def test_view_save_on_a_full_filesystem_stops_with_one_line(tmp_path, tiny_fs):
    """`vergence view --save` into a 1 MiB tmpfs (issue #29): Rerun's writer fails silently, so the view
    watches the file: exit 1 within 2 s of the disk filling (its check runs every second), one line naming
    the file and the error. Needs root to mount the tmpfs."""
    mnt = tiny_fs
    rrd = mnt / "cockpit.rrd"
    with Procs(tmp_path) as P:
        P.router()
        s = P.session()
        v = P.start("view", "view", "--save", str(rrd))
        wait_for(lambda: "view: rig" in v.text(), 60, "the view's subscriptions", logs=P.logs)
        pub = s.declare_publisher(P.key("preview"))
        rng = np.random.default_rng(1)
        full: list[float] = []
        frame = 0
        deadline = time.monotonic() + 30
        while v.alive() and time.monotonic() < deadline:
            frame += 1
            img = rng.integers(0, 256, (2, 120, 160), np.uint8)  # noise: it does not compress
            pub.put(M.Preview(rig=P.rig, frame=frame, t_capture_ns=time.time_ns(), width=160, height=120,
                              scale=0.5, master=img[0].tobytes(), slave=img[1].tobytes()).to_bytes())
            st = os.statvfs(mnt)
            if not full and st.f_bavail * st.f_frsize < view.SaveWatch.MIN_FREE:
                full.append(time.monotonic())
            time.sleep(0.01)  # the load under test: 100 previews (3.8 MB) a second
        t_exit = time.monotonic()
        assert v.wait(10) == 1, v.tail()
        lines = [x for x in v.text().splitlines() if x.startswith("vergence view:")]
        print(lines, f"; exit {t_exit - full[0]:.2f} s after the disk filled")
        assert len(lines) == 1 and f"cannot write '{rrd}': No space left on device" in lines[0]
        assert t_exit - full[0] < 2.0
