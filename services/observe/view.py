"""`vergence view [--rig R] [--save FILE.rrd] [--web [--port P]] [--spawn]`: the rig's cockpit in Rerun.

Subscribes (callbacks only queue the samples; the main thread decodes and logs them) to vergence/<rig>/
preview, frame, decision, profile, command, motor/state, status/** and the liveliness tokens alive/**, and
logs them to Rerun on two timelines, `frame` (the frame id) and `capture` (its capture time). It publishes
nothing and declares no token; its subscription to the profile key is what makes the reducer publish
profiles (as for `vergence monitor`).

Entity paths (ENTITIES below): the preview images rig/master and rig/slave, the fovea as a box on the master
image (rig/master/fovea) and its match as a box on the slave image (rig/slave/match), layer 4's winning row
as a bar chart (rig/correlation), the pans in degrees (pan/slave at capture, pan/motor, pan/goal,
pan/command, pan/truth where the frames carry it), depth (where the decision carries it), the decision's
scalars (decision/confidence, decision/offset_px, ...), the workers (workers/alive, workers/<id>) and every
status message as a text log (status/<role>/<id>).

Sinks, any combination (default --spawn): --save FILE.rrd writes a recording; --web serves the web viewer
shipped in the rerun-sdk wheel (no internet needed) on --port and its data on --grpc-port, so the cockpit of
a head is a URL on another machine; --spawn opens the native viewer (needs a display).

rerun-sdk is an optional extra: `pip install 'vergence[view]'`. Rerun's anonymous usage analytics are
switched off before anything of rerun starts (analytics_off), in this and in every process of the project
that uses rerun (`vergence sim --save`, `vergence replay --view`).
"""

from __future__ import annotations

import argparse
import collections
import json
import logging
import math
import os
import socket
import subprocess
import sys
import time
import threading
from pathlib import Path

import numpy as np

from vergence import keys
from vergence.messages import Command, Frame, MessageError, MotorState, Preview, Profile, Verdict

log = logging.getLogger("vergence.view")
APP_ID = "vergence"
INSTALL_HINT = "pip install 'vergence[view]' (in a checkout: pip install -e '.[view]')"
# what the cockpit subscribes to under vergence/<rig>/
WATCHED = (keys.preview, keys.frame, keys.decision, keys.profile, keys.command, keys.motor_state, keys.statuses)
ENTITIES = {
    "rig/master": "the master's preview image",
    "rig/master/fovea": "the fovea, a box on the master image",
    "rig/slave": "the slave's preview image",
    "rig/slave/match": "where the fovea matched, a box on the slave image",
    "rig/correlation": "layer 4's scores along k on the winning row (bar chart)",
    "pan/slave": "the slave pan at capture, degrees",
    "pan/motor": "the pan the motor reports, degrees",
    "pan/goal": "the motor's goal, degrees",
    "pan/command": "the pan commanded, degrees",
    "pan/truth": "the converged pan, degrees (frames that carry the truth)",
    "depth": "the fixated distance, metres (decisions that carry it); depth/sigma its uncertainty",
    "decision/confidence": "the decision's confidence, 0..1",
    "decision/confident": "1 when the camera may move, else 0",
    "decision/offset_px": "how far right of the fovea's column its match lies in the slave, px",
    "decision/window": "the fovea side the frame was decided with, px",
    "latency/decision_ms": "capture to decision, ms",
    "workers/alive": "the number of live workers",
    "workers/<id>": "1 while worker <id> is alive, 0 after",
    "status/<role>/<id>": "each process's status message (text log)",
}


class MissingExtra(RuntimeError):
    """rerun-sdk is not installed."""


def analytics_off() -> None:
    """Make sure Rerun's anonymous usage analytics are off before any rerun code runs in this process.

    Rerun reads one switch, `analytics_enabled` in its per-user config (<XDG_CONFIG_HOME or ~/.config>/rerun/
    analytics.json), written by `rerun analytics disable`. When the config does not say disabled, this runs
    exactly that command of the wheel's own CLI, once (a head's network has no business calling out)."""
    base = os.environ.get("XDG_CONFIG_HOME") or os.path.join(os.path.expanduser("~"), ".config")
    path = Path(base) / "rerun" / "analytics.json"
    try:
        if json.loads(path.read_text()).get("analytics_enabled") is False:
            return
    except (OSError, ValueError, AttributeError):
        pass
    try:
        subprocess.run([sys.executable, "-m", "rerun_cli", "analytics", "disable"], stdin=subprocess.DEVNULL,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=60, check=True)
    except (OSError, subprocess.SubprocessError) as e:
        raise MissingExtra(f"cannot switch rerun's analytics off (`rerun analytics disable`): {e}") from None
    log.info("rerun analytics disabled for this user (%s)", path)


def import_rerun():
    """The rerun module with analytics off; MissingExtra (one line, how to install) without the extra."""
    try:
        import rerun_cli  # noqa: F401  (the wheel's CLI: analytics_off runs it)
    except ImportError:
        raise MissingExtra(f"rerun-sdk is not installed; install the viewer extra: {INSTALL_HINT}") from None
    analytics_off()
    import rerun as rr

    return rr


def blueprint(rr):
    """The cockpit's layout: the two images with their boxes above, the curves below."""
    rrb = rr.blueprint
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(rrb.Spatial2DView(origin="rig/master", name="master (fovea)"),
                           rrb.Spatial2DView(origin="rig/slave", name="slave (match)")),
            rrb.Horizontal(rrb.BarChartView(origin="rig/correlation", name="layer 4 (winning row)"),
                           rrb.TimeSeriesView(origin="pan", name="pan, degrees"),
                           rrb.TimeSeriesView(origin="decision", name="decision")),
            row_shares=[3, 2]),
        rrb.TimeSeriesView(origin="depth", name="depth, m"), rrb.TimeSeriesView(origin="latency", name="latency"),
        rrb.TimeSeriesView(origin="workers", name="workers"),
        rrb.TextLogView(origin="motor", name="motor status (faults in red)"),
        collapse_panels=True)


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


class Cockpit:
    """Decodes the rig's messages and logs them to a Rerun recording stream. Malformed messages are counted
    (bad) and skipped; fields that newer messages carry (truth, depth, x/y on the decision) are read with
    defaults, so older and newer peers both work."""

    def __init__(self, rr, recording=None):
        self.rr, self.rec = rr, recording
        self.counts: collections.Counter = collections.Counter()
        self.bad: collections.Counter = collections.Counter()
        self.scale: float | None = None  # preview px per image px (latest preview)
        self.size: tuple[int, int] | None = None  # the full image (width, height), from the frames
        self.at: dict[int, tuple[int, int]] = {}  # frame id -> fovea (x, y), recent frames
        self.point: tuple[int, int] | None = None  # the latest frame's fovea point (the capture keeps it)
        self.decided: set[int] = set()  # frames whose decision was logged (recent)
        self.workers: set[str] = set()
        self.motor_status: str | None = None  # the latest motor state's status (logged as text when it changes)

    # -- helpers -------------------------------------------------------------------------------------------

    def _log(self, path: str, what) -> None:
        self.rr.log(path, what, recording=self.rec)

    def _time(self, frame: int | None, t_ns: int | None) -> None:
        rr = self.rr
        if frame is not None and frame >= 0:
            rr.set_time("frame", sequence=int(frame), recording=self.rec)
        else:
            rr.reset_time(recording=self.rec)
        if t_ns:
            rr.set_time("capture", timestamp=np.datetime64(int(t_ns), "ns"), recording=self.rec)

    def _scalar(self, path: str, value) -> None:
        if _finite(value):
            self._log(path, self.rr.Scalars(float(value)))

    def _remember(self, d: dict, key: int, value) -> None:
        d[key] = value
        if len(d) > 512:  # recent frames only
            for k in sorted(d)[:256]:
                del d[k]

    # -- one sample ----------------------------------------------------------------------------------------

    def feed(self, rest: str, payload: bytes, t_ns: int | None = None) -> str | None:
        """Log one message whose key is vergence/<rig>/<rest>; returns its kind (vergence.keys), or None when
        skipped."""
        kind = keys.kind_of(rest)
        try:
            if kind == keys.PREVIEW:
                self._preview(Preview.from_bytes(payload))
            elif kind == keys.FRAME:
                self._frame(Frame.from_bytes(payload))
            elif kind == keys.DECISION:
                self._decision(Verdict.from_bytes(payload))
            elif kind == keys.PROFILE:
                self._profile(Profile.from_bytes(payload))
            elif kind == keys.COMMAND:
                self._command(Command.from_bytes(payload))
            elif kind == keys.MOTOR_STATE:
                self._motor(MotorState.from_bytes(payload))
            elif kind == keys.STATUS:
                self._status(rest, payload, t_ns)
            else:
                return None
        except (MessageError, ValueError, TypeError) as e:
            self.bad[kind] += 1
            if sum(self.bad.values()) <= 10:
                log.warning("malformed message on %s skipped: %s", rest, e)
            return None
        self.counts[kind] += 1
        return kind

    def alive(self, rest: str, present: bool, t_ns: int | None = None) -> None:
        """A liveliness token vergence/<rig>/<rest> (alive/<role>/<id>) appeared or went away."""
        k = keys.Key("", keys.kind_of(rest), rest)
        if k.kind != keys.ALIVE or k.role != "worker" or "/" in k.ident:
            return
        (self.workers.add if present else self.workers.discard)(k.ident)
        self._time(None, t_ns)
        self._scalar(f"workers/{k.ident}", 1.0 if present else 0.0)
        self._scalar("workers/alive", len(self.workers))

    def _preview(self, p: Preview) -> None:
        master, slave = p.images()
        self.scale = p.scale
        if self.size is None and p.scale > 0:  # until a frame says
            self.size = (round(p.width / p.scale), round(p.height / p.scale))
        self._time(p.frame, p.t_capture_ns)
        self._log("rig/master", self.rr.Image(master))
        self._log("rig/slave", self.rr.Image(slave))

    def _frame(self, f: Frame) -> None:
        self.size = (f.width, f.height)
        self._remember(self.at, f.frame, (f.x, f.y))
        self.point = (f.x, f.y)
        truth = getattr(f, "truth_pan_rad", None)
        if _finite(truth):
            self._time(f.frame, f.t_capture_ns)
            self._scalar("pan/truth", math.degrees(truth))

    def _boxes(self, v: Verdict) -> None:
        at = (getattr(v, "x", None), getattr(v, "y", None))
        if not all(isinstance(c, int) and c >= 0 for c in at):  # -1: a decision that does not say
            at = self.at.get(v.frame) or self.point
        if at is None:  # the capture's default point: the centre (k_centre = x - w // 2)
            height = self.size[1] if self.size else None
            if height is None:
                return
            at = (v.k_centre + v.window // 2, height // 2)
        if self.scale is None:  # no image to draw them on yet (no preview so far)
            return
        s = self.scale
        x, y = at
        half = (v.window * s / 2, v.window * s / 2)
        # pixel centres: pixel i covers [i, i + 1) in Rerun's image space
        self._log("rig/master/fovea", self.rr.Boxes2D(centers=[((x + 0.5) * s, (y + 0.5) * s)], half_sizes=[half],
                                                      labels=[f"fovea {v.window} px"]))
        mx, my = x + v.offset_px, y + v.v_shift
        color = (40, 220, 60) if v.confident else (230, 150, 30)
        self._log("rig/slave/match", self.rr.Boxes2D(centers=[((mx + 0.5) * s, (my + 0.5) * s)], half_sizes=[half],
                                                     colors=[color],
                                                     labels=[f"{v.offset_px:+.1f} px, c={v.confidence:.2f}"]))

    def _decision(self, v: Verdict) -> None:
        if v.frame in self.decided:  # its profile came first and logged it
            return
        self._time(v.frame, v.t_capture_ns)
        self._boxes(v)
        self._scalar("pan/slave", math.degrees(v.pan_rad))
        self._scalar("decision/confidence", v.confidence)
        self._scalar("decision/confident", 1.0 if v.confident else 0.0)
        self._scalar("decision/offset_px", v.offset_px)
        self._scalar("decision/window", v.window)
        if v.t_reduced_ns and v.t_capture_ns:
            self._scalar("latency/decision_ms", (v.t_reduced_ns - v.t_capture_ns) / 1e6)
        depth = getattr(v, "depth_m", None)
        if _finite(depth):
            self._scalar("depth", depth)
            self._scalar("depth/sigma", getattr(v, "depth_sigma_m", None))
        truth = getattr(v, "truth_pan_rad", None)
        if _finite(truth):
            self._scalar("pan/truth", math.degrees(truth))
        self.decided.add(v.frame)
        if len(self.decided) > 512:
            self.decided = set(sorted(self.decided)[256:])

    def _profile(self, p: Profile) -> None:
        if p.frame not in self.decided:  # a rig (or a recording) without decision messages
            self._decision(p)
        self._time(p.frame, p.t_capture_ns)
        scores = p.array()
        row = scores[min(max(p.v_shift + (p.rows - 1) // 2, 0), p.rows - 1)]
        self._log("rig/correlation", self.rr.BarChart(np.asarray(row, np.float64)))

    def _command(self, c: Command) -> None:
        self._time(c.frame, c.t_capture_ns)
        self._scalar("pan/command", math.degrees(c.pan_rad))

    def _motor(self, m: MotorState) -> None:
        self._time(m.frame, m.t_capture_ns or m.t_ns)
        self._scalar("pan/motor", math.degrees(m.pan_rad))
        self._scalar("pan/goal", math.degrees(m.goal_rad))
        if m.status != self.motor_status:  # a change of status is an event: disconnected, absent (issue #29), back
            self.motor_status = m.status
            fault = m.status in ("disconnected", "absent")
            self._log("motor/status", self.rr.TextLog(f"motor {m.status}" + (f": {m.note}" if m.note else ""),
                                                      level="ERROR" if fault else "INFO"))

    def _status(self, rest: str, payload: bytes, t_ns: int | None) -> None:
        text = bytes(payload).decode("utf-8")
        json.loads(text)  # a status is a JSON object: anything else is malformed
        self._time(None, t_ns)
        self._log(rest, self.rr.TextLog(text))


# -- sinks ---------------------------------------------------------------------------------------------------

def host_address() -> str:
    """An address other machines can reach this one on (the hostname's, else 127.0.0.1)."""
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect(("10.255.255.255", 1))  # no packet is sent: only picks the outgoing interface
            return s.getsockname()[0]
    except OSError:
        return "127.0.0.1"


class SaveWatch:
    """Whether the --save file can still be written (issue #29): Rerun writes it from a thread of its own and
    says nothing when a write fails, so every CHECK_S the file must still be the one opened (not removed or
    replaced) and its filesystem must have MIN_FREE bytes left. fault(): why not (kept once found), or ""."""

    CHECK_S = 1.0
    MIN_FREE = 256 * 1024  # less than this left: Rerun's next chunks do not fit

    def __init__(self, path: str | None):
        self.path, self.why, self._ident, self._next = path, "", None, 0.0

    def fault(self) -> str:
        now = time.monotonic()
        if self.path is None or self.why or now < self._next:
            return self.why
        self._next = now + self.CHECK_S
        try:
            st = os.stat(self.path)
            fs = os.statvfs(self.path)
        except OSError:
            if self._ident is not None:
                self.why = f"cannot write {self.path!r}: it was removed"
            return self.why  # not created yet (Rerun opens it with its first data): next time
        if self._ident is None:
            self._ident = (st.st_dev, st.st_ino)
        elif (st.st_dev, st.st_ino) != self._ident:
            self.why = f"cannot write {self.path!r}: it was replaced by another file"
        if fs.f_bavail * fs.f_frsize < self.MIN_FREE:
            self.why = (f"cannot write {self.path!r}: No space left on device (its filesystem has "
                        f"{fs.f_bavail * fs.f_frsize // 1024} KiB free)")
        return self.why


def start(rr, app: str, *, save: str | None = None, web: bool = False, port: int = 9090, grpc_port: int = 9876,
          spawn: bool = False, bind: str = "0.0.0.0") -> str | None:
    """rr.init and the sinks asked for; returns the web viewer's URL when serving it."""
    rr.init(app, spawn=False)
    sinks, url = [], None
    if save:
        sinks.append(rr.FileSink(save))
    if web:
        server = rr.GrpcServerSink(bind_ip=bind, port=grpc_port)
        sinks.append(server)
    if spawn and sys.platform.startswith("linux") and not (os.environ.get("DISPLAY")
                                                         or os.environ.get("WAYLAND_DISPLAY")):
        raise RuntimeError("--spawn needs a display (DISPLAY or WAYLAND_DISPLAY is not set): give --web to watch "
                           "from a browser, or --save FILE.rrd")
    if spawn:
        rr.spawn(connect=False, port=grpc_port + 1 if web else 9876)
        sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{grpc_port + 1 if web else 9876}/proxy"))
    rr.set_sinks(*sinks, default_blueprint=blueprint(rr))
    if web:
        host = "127.0.0.1" if bind.startswith("127.") else host_address()
        data = server.uri.replace("0.0.0.0", host)
        serve_offline(bind, port, viewer_assets(), grpc_port)
        from urllib.parse import quote

        url = f"http://{host}:{port}/?url={quote(data, safe='')}"
    return url


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def csp(grpc_port: int) -> str:
    """The Content-Security-Policy the cockpit's page is served with: the page may load only from where it
    came and fetch only from the cockpit's data port. The bundled viewer otherwise calls out from the
    browser: its usage analytics (tel.rerun.io, no opt-out in the web build), a check for a newer release
    (api.github.com) and Google's fonts; a head's network has no business calling out."""
    data = f"http://*:{grpc_port} ws://*:{grpc_port}"
    return ("default-src 'self'; script-src 'self' 'unsafe-inline' 'wasm-unsafe-eval'; "
            "style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; font-src 'self' data:; "
            f"worker-src 'self' blob:; connect-src 'self' {data}; form-action 'none'; base-uri 'self'")


ASSETS = ("/", "/re_viewer.js", "/re_viewer_bg.wasm", "/favicon.ico", "/apple-touch-icon.png")


def viewer_assets(timeout: float = 120.0) -> dict[str, tuple[str, bytes]]:
    """The web viewer's files (path -> (content type, bytes)), read once from rerun's own web server, run in a
    helper process that stops once they are read: that server listens on every interface (it cannot be told
    otherwise) and serves the page without the policy of csp()."""
    import time
    import urllib.request

    inner = _free_port()
    code = ("import sys, time, rerun as rr\n"
            "rr.serve_web_viewer(web_port=int(sys.argv[1]), open_browser=False)\n"
            "time.sleep(3600)\n")
    helper = subprocess.Popen([sys.executable, "-c", code, str(inner)], stdin=subprocess.DEVNULL,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    out: dict[str, tuple[str, bytes]] = {}
    try:
        end = time.monotonic() + timeout
        for path in ASSETS:
            while True:
                try:
                    with urllib.request.urlopen(f"http://127.0.0.1:{inner}{path}", timeout=30) as r:
                        out[path] = (r.headers.get("Content-Type", "application/octet-stream"), r.read())
                    break
                except OSError as e:
                    if helper.poll() is not None or time.monotonic() > end:
                        raise RuntimeError(f"the web viewer's files: {e}") from None
                    time.sleep(0.2)
    finally:
        helper.terminate()
        try:
            helper.wait(10)
        except subprocess.TimeoutExpired:
            helper.kill()
            helper.wait(5)
    return out


def serve_offline(bind: str, port: int, assets: dict[str, tuple[str, bytes]], grpc_port: int):
    """Serve the viewer's files on bind:port with csp(grpc_port), from a daemon thread."""
    import http.server

    policy = csp(grpc_port)

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 (the http.server API)
            path = self.path.split("?", 1)[0]
            hit = assets.get("/" if path == "/index.html" else path)
            if hit is None:
                self.send_error(404)
                return
            ctype, body = hit
            self.send_response(200)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Content-Security-Policy", policy)
            self.send_header("Cache-Control", "no-cache")
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):  # quiet
            pass

    httpd = http.server.ThreadingHTTPServer((bind, port), Handler)
    httpd.daemon_threads = True
    threading.Thread(target=httpd.serve_forever, name="viewer-http", daemon=True).start()
    return httpd


# -- recordings and the simulator -----------------------------------------------------------------------

def parse_target(text: str) -> dict:
    """`replay --view TARGET`: FILE.rrd (save), web[:PORT] (serve), or spawn (the native viewer)."""
    if text == "spawn":
        return {"spawn": True}
    if text == "web" or text.startswith("web:"):
        port = text.partition(":")[2]
        if port and not port.isdigit():
            raise ValueError(f"--view web:PORT wants a port number, got {text!r}")
        return {"web": True, "port": int(port or 9090)}
    if text.endswith(".rrd"):
        return {"save": text}
    raise ValueError(f"--view wants FILE.rrd, web[:PORT] or spawn, got {text!r}")


def view_recording(path: str, target: str, rig: str | None, stop=None) -> int:
    """`vergence replay FILE --view TARGET`: a `vergence record` file into the cockpit's Rerun view (no Zenoh,
    nothing published). Serving (web, spawn) keeps running until stopped, so the viewer can read it."""
    from vergence.recording import Reader, RecordingError

    try:
        sinks = parse_target(target)
        rr = import_rerun()
        reader = Reader(path)
    except (ValueError, MissingExtra, RecordingError) as e:
        print(f"vergence replay: {e}", file=sys.stderr)
        return 2
    rig = rig or reader.header.get("rig") or "head"
    with reader:
        url = start(rr, f"{APP_ID}-{rig}", **sinks)
        if url:
            print(f"vergence replay: the cockpit of the recording is at {url}", file=sys.stderr, flush=True)
        cockpit = Cockpit(rr)
        try:
            for rec in reader:
                k = keys.parse(rec.key)
                if k is None or k.rig != rig:
                    continue
                rest = k.rest
                if rec.event in ("alive", "dead"):
                    cockpit.alive(rest, rec.event == "alive", rec.t_ns)
                elif rec.event == "put":
                    cockpit.feed(rest, rec.payload, rec.t_ns)
        except RecordingError as e:
            print(f"vergence replay: {e}", file=sys.stderr)
            return 2
    log.info("recording %s of rig %s into Rerun: logged %s, bad %s", path, rig, dict(cockpit.counts),
             dict(cockpit.bad))
    if (sinks.get("web") or sinks.get("spawn")) and stop is not None:
        print("vergence replay: serving the view until Ctrl-C", file=sys.stderr, flush=True)
        stop.wait()
    rr.disconnect()
    return 0


def log_sim_step(rr, s, master: np.ndarray, slave: np.ndarray, at: tuple[int, int], rate_hz: float) -> None:
    """`vergence sim --save`: one Step of the simulated loop with the views it was decided on, under the
    cockpit's entity paths (capture time: the virtual clock, from 0)."""
    x, y = at
    if True:
        rr.set_time("frame", sequence=s.frame)
        rr.set_time("capture", duration=s.frame / rate_hz)
        rr.log("rig/master", rr.Image(master))
        rr.log("rig/slave", rr.Image(slave))
        half = [(s.window / 2, s.window / 2)]
        rr.log("rig/master/fovea", rr.Boxes2D(centers=[(x + 0.5, y + 0.5)], half_sizes=half,
                                              labels=[f"fovea {s.window} px"]))
        color = (40, 220, 60) if s.confident else (230, 150, 30)
        rr.log("rig/slave/match", rr.Boxes2D(centers=[(x + s.offset_px + 0.5, y + s.v + 0.5)], half_sizes=half,
                                             colors=[color], labels=[f"{s.offset_px:+.1f} px"]))
        rr.log("rig/correlation", rr.BarChart(np.asarray(s.scores, np.float64)))
        rr.log("pan/slave", rr.Scalars(s.pan_deg))
        if math.isfinite(s.truth_pan_deg):
            rr.log("pan/truth", rr.Scalars(s.truth_pan_deg))
        if s.target_deg is not None:
            rr.log("pan/command", rr.Scalars(s.target_deg))
        rr.log("decision/confidence", rr.Scalars(s.confidence))
        rr.log("decision/confident", rr.Scalars(1.0 if s.confident else 0.0))
        rr.log("decision/offset_px", rr.Scalars(s.offset_px))
        rr.log("decision/window", rr.Scalars(float(s.window)))


# -- the process ---------------------------------------------------------------------------------------------

def configure(p: argparse.ArgumentParser) -> None:
    from services.runtime import session

    session.add_options(p)
    p.add_argument("--save", metavar="FILE.rrd", help="write a Rerun recording")
    p.add_argument("--web", action="store_true", help="serve the web viewer (shipped in the wheel, offline)")
    p.add_argument("--port", type=int, default=9090, metavar="P", help="--web: the viewer's HTTP port (default 9090)")
    p.add_argument("--grpc-port", type=int, default=9876, metavar="P",
                   help="--web: the port the viewer fetches the data from (default 9876)")
    p.add_argument("--bind", default="0.0.0.0", metavar="IP",
                   help="--web: the address to serve on (default 0.0.0.0: other machines; 127.0.0.1: this one)")
    p.add_argument("--spawn", action="store_true", help="open the native viewer (needs a display); the default "
                                                         "when neither --save nor --web is given")
    p.add_argument("--timeout", type=float, default=None, metavar="S", help="exit after S seconds")
    p.add_argument("--nice", type=int, default=10, metavar="N",
                   help="run at this niceness, so that the loop's processes come first on a busy CPU (default 10)")


def main(rig: str, conf, stop, *, save: str | None = None, web: bool = False, port: int = 9090,
         grpc_port: int = 9876, spawn: bool = False, bind: str = "0.0.0.0", timeout: float | None = None,
         nice: int = 10) -> int:
    import time

    import zenoh

    from services.runtime import session

    if nice:
        try:  # before rerun's and zenoh's threads start: they inherit it
            os.nice(nice)
        except OSError:
            pass
    try:
        rr = import_rerun()
    except MissingExtra as e:
        print(f"vergence view: {e}", file=sys.stderr)
        return 2
    try:
        url = start(rr, f"{APP_ID}-{rig}", save=save, web=web, port=port, grpc_port=grpc_port, spawn=spawn,
                    bind=bind)
    except (OSError, RuntimeError, ValueError) as e:
        print(f"vergence view: {e}", file=sys.stderr)
        return 2
    if url:
        print(f"vergence view: the cockpit of rig {rig} is at {url}", file=sys.stderr, flush=True)
    cockpit = Cockpit(rr)
    inbox: collections.deque = collections.deque(maxlen=20000)  # zenoh threads -> this thread
    ready = threading.Event()
    prefix = keys.prefix(rig)  # what the callbacks strip: the cockpit takes the rest of the key

    full = [0]  # samples pushed out of a full inbox (the viewer fell behind)

    def on_sample(sample) -> None:
        if len(inbox) == inbox.maxlen:
            full[0] += 1
        inbox.append((str(sample.key_expr)[len(prefix):], sample.payload.to_bytes(), time.time_ns()))
        ready.set()

    def on_alive(sample) -> None:
        inbox.append((str(sample.key_expr)[len(prefix):], sample.kind == zenoh.SampleKind.PUT, time.time_ns()))
        ready.set()

    end = time.monotonic() + timeout if timeout is not None else None
    try:
        s = session.open_session(conf, timeout=timeout)
    except SystemExit:  # Ctrl-C before a router answered
        rr.disconnect()
        raise
    except ConnectionError as e:  # no router within --timeout
        print(f"vergence view: {e}", file=sys.stderr)
        rr.disconnect()
        return 1
    except Exception as e:  # a bad endpoint or config
        print(f"vergence view: cannot open a zenoh session: {e}", file=sys.stderr)
        rr.disconnect()
        return 2
    with s:
        # frames (30 KB each at 640 px) too, for what decisions may not carry: the fovea's point (older reducers)
        # and the simulator's truth
        subs = [s.declare_subscriber(k(rig), on_sample) for k in WATCHED]
        subs.append(s.liveliness().declare_subscriber(keys.alives(rig), on_alive, history=True))
        log.info("view: rig %s -> %s", rig, ", ".join(x for x in (save and f"file {save}", url, spawn and "viewer")
                                                       if x))
        watch = SaveWatch(save)
        try:
            while not stop.is_set() and (end is None or time.monotonic() < end):
                ready.wait(0.1)
                ready.clear()
                if watch.fault():  # --save can no longer be written: say it once, stop (exit 1)
                    print(f"vergence view: {watch.fault()}; stopped", file=sys.stderr)
                    break
                while inbox:
                    rest, payload, t_ns = inbox.popleft()
                    try:
                        if isinstance(payload, bool):
                            cockpit.alive(rest, payload, t_ns)
                        else:
                            cockpit.feed(rest, payload, t_ns)
                    except Exception as e:  # no message may end the cockpit
                        cockpit.bad["error"] += 1
                        log.warning("message on %s not logged: %s", rest, e)
        finally:
            for sub in subs:
                sub.undeclare()
    while inbox:  # what arrived before the subscriptions closed
        rest, payload, t_ns = inbox.popleft()
        (cockpit.alive if isinstance(payload, bool) else cockpit.feed)(rest, payload, t_ns)
    rr.disconnect()  # flushes the file
    log.info("view exits: logged %s, bad %s, dropped %d (behind)", dict(cockpit.counts), dict(cockpit.bad), full[0])
    return 1 if watch.fault() else 0


def run(args: argparse.Namespace) -> int:
    from vergence.config import load

    from services.runtime import session

    import zenoh

    spawn = args.spawn or not (args.save or args.web)
    rig = args.rig or load(args.config).rig
    try:
        conf = session.config_from_args(args)
    except zenoh.ZError as e:
        print(f"vergence view: bad zenoh options: {str(e).split(' at /')[0]}", file=sys.stderr)
        return 2
    return main(rig, conf, session.Stop(), save=args.save, web=args.web, port=args.port,
                grpc_port=args.grpc_port, spawn=spawn, bind=args.bind, timeout=args.timeout, nice=args.nice)
