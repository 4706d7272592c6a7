"""`vergence bench pipeline [--source SPEC] [--workers N ...] [--rate HZ] [--seconds S] [--heavy] [--json]`.

Measures what `vergence up` runs, as a user's client sees it: for each source, worker count and rate, it starts
`vergence up --source SPEC --workers N --rate HZ` (the embedded router, the sim actuator, the workers, the reducer
and the capture with their standbys, all as real processes on this machine), waits for its first decision and WARM_S
more, then subscribes for --seconds to the decisions, the commands and the motor states, as a peer of the pipeline's
processes (connected to up's router, it then hears each process directly, as any program of the user's on the same
host can with `--mode peer`; through the router, a client, each decision comes 60-200 us later). Reported per run:
decisions against the frames the rate asks for in that time (rate x seconds; drops: the difference; undecided: the
frame ids between the first and the last decided that have no decision, frames made and lost), capture-to-
decision latency p50/p99/max (a decision's arrival here minus its frame's t_capture_ns, the master's exposure: one
hop more than the reducer's own), the commands and how many were wrong (files: an offset other than the pair's SHIFT
px, or older than one sent before it), capture-to-executed (the first motor state naming a frame, at the actuator),
beside the in-process vergence.match time on a pair of the same source (overhead = p50 / match).
Sources (default all three): vga, a synthetic textured pair as a `files:` source (the slave sees the scene
SHIFT px further left, whatever the motor does: every frame yields a command); sim, the simulated still scene;
demo, `vergence up`'s default source (a target moving in depth). --source SPEC: that source only.
Without --rate: 100, 250, 500, then 1000 Hz until a run drops frames. --heavy adds a 3840 x 1080 pair
(w = 31, vertical search +-16) at a few Hz, where sharding pays. --floor: the CPU per message (psutil) of a
router and of a subscriber process (`vergence bench pipeline --subscriber ENDPOINT`). Processes start and stop
through services/ops/launch.py, each logging into the run's temporary folder (shown on failure).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from services.runtime.args import number, whole
from services.ops.launch import Proc, free_port, stop_all, vergence, wait_for, wait_listening

RATES = [100, 250, 500, 1000]
HEAVY_RATES = [10, 25, 50, 100]
WARM_S = 1.0  # after the first decision: the first frames of fresh processes are slow (imports, first messages)
DEMO = "sim:motion=sine:z=0.8,amp=0.3,hz=0.2"  # vergence up's default source (vergence.config)


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--source", default=None, metavar="SPEC",
                   help="one source only, as `vergence up --source` takes it (default: vga, sim and the demo)")
    p.add_argument("--workers", type=whole(1, 64), nargs="+", default=[1, 2], metavar="N",
                   help="worker counts (default 1 2)")
    p.add_argument("--rate", type=number(0, 1000, lo_open=True), default=None, metavar="HZ",
                   help="one rate only (default: a ramp)")
    p.add_argument("--seconds", type=number(0, 3600, lo_open=True), default=2.0,
                   help="length of each run (default 2 s)")
    p.add_argument("--heavy", action="store_true", help="also the heavy setting: 3840 wide, w=31, +-16 rows")
    p.add_argument("--faithful", action="store_true", help="the paper's network (no extension)")
    p.add_argument("--floor", action="store_true", help="also the messaging floor: CPU per 27 KB message of the "
                                                        "router and of one Python subscriber, at 1 kHz")
    p.add_argument("--json", action="store_true", help="one JSON object per run")
    p.add_argument("--subscriber", metavar="ENDPOINT", help=argparse.SUPPRESS)  # --floor's, in its own process


SHIFT = 12  # px: the synthetic pair's offset, which every command must carry


def synthetic_pair(width: int, height: int, shift: int = SHIFT, seed: int = 5) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.integers(0, 256, (height, width + 2 * shift), np.uint8), (5, 5), 1.5)
    return (np.ascontiguousarray(base[:, shift : shift + width]), np.ascontiguousarray(base[:, :width]))


@dataclasses.dataclass
class Setting:
    """One source to run: its name in the rows, its spec, the settings file every process gets, its pair for the
    in-process baseline, whether its commands must carry SHIFT px."""

    name: str
    source: str
    config: Path
    pair: tuple[np.ndarray, np.ndarray]
    shifted: bool = False


class Up:
    """`vergence up` as a child (its own process group, its log in the run's folder), stopped on close."""

    def __init__(self, workdir: Path, rig: str, setting: Setting, workers: int, rate: float):
        self.rig = rig
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.proc = Proc("up", vergence("up", "--listen", self.endpoint, "--rig", rig, "--config",
                                        str(setting.config), "--source", setting.source, "--workers",
                                        str(workers), "--rate", f"{rate:g}"),
                         log=workdir / f"up-{setting.name}-{workers}-{rate:g}.log")
        try:
            wait_listening(self.endpoint, 60, self.proc, logs=self.logs)
        except BaseException:
            self.close()
            raise

    def logs(self) -> str:
        return self.proc.tail(40)

    def close(self) -> None:
        self.proc.stop()


def _session(endpoint: str):
    import zenoh

    from services.runtime import session

    return zenoh.open(session.zenoh_config("peer", [endpoint]))


def in_process_ms(master, slave, params, n: int = 30) -> float:
    """Median time of vergence.match on the pair, in ms."""
    from vergence import match

    match(master, slave, params=params)
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        match(master, slave, params=params)
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts) * 1e3)


def executed_lags(states: list, first: int, last: int) -> dict[int, int]:
    """Capture -> command executed at the actuator, ns, per frame first..last: the first motor state naming a
    frame is the one published right after its command went to the motor (its t_ns minus the frame's capture
    time, no extra hop); the motor's periodic states name the same frame again, later."""
    out: dict[int, int] = {}
    for st in states:
        if first <= st.frame <= last and st.t_capture_ns > 0:
            lag = st.t_ns - st.t_capture_ns
            out[st.frame] = min(out.get(st.frame, lag), lag)
    return out


def _p(a: np.ndarray, q: float) -> float:
    return float(np.percentile(a, q)) if len(a) else float("nan")


def run_rate(up: Up, setting: Setting, rate: float, seconds: float) -> dict:
    """One run: the first decision, WARM_S, then `seconds` of decisions, commands and motor states."""
    from vergence.wire import keys
    from vergence.wire.messages import Command, Decision, MotorState

    got: dict[str, list[tuple[int, bytes]]] = {"decision": [], "command": [], "motor_state": []}
    lock = threading.Lock()

    def on(kind):
        def cb(sample):
            t = time.time_ns()
            with lock:
                got[kind].append((t, sample.payload.to_bytes()))
        return cb

    s = _session(up.endpoint)
    try:
        subs = [s.declare_subscriber(getattr(keys, kind)(up.rig), on(kind)) for kind in got]
        wait_for(lambda: len(got["decision"]) > 0, 90, "the first decision", logs=up.logs)
        time.sleep(WARM_S)
        t0 = time.time_ns()
        time.sleep(seconds + 0.3)  # and the last frames' decisions on their way
        for sub in subs:
            sub.undeclare()
    finally:
        s.close()
    t1 = t0 + round(seconds * 1e9)
    with lock:
        dec = [(t, Decision.from_bytes(b)) for t, b in got["decision"]]
        cmds = [(t, Command.from_bytes(b)) for t, b in got["command"]]
        states = [MotorState.from_bytes(b) for _, b in got["motor_state"]]
    dec = [(t, d) for t, d in dec if t0 <= d.t_capture_ns < t1]
    cmds = [(t, c) for t, c in cmds if t0 <= c.t_capture_ns < t1]
    lat = np.array([(t - d.t_capture_ns) / 1e6 for t, d in dec])
    red = np.array([(c.t_sent_ns - c.t_capture_ns) / 1e6 for _, c in cmds])
    frames = {d.frame for _, d in dec}
    act = np.array(sorted(executed_lags(states, min(frames, default=0), max(frames, default=-1)).values())) / 1e6
    ids = [c.frame for _, c in sorted(cmds, key=lambda tc: tc[1].t_sent_ns)]
    wrong = sum(b <= a for a, b in zip(ids, ids[1:]))
    if setting.shifted:
        wrong += sum(abs(c.magnitude_px - SHIFT) > 1.0 for _, c in cmds)
    asked = int(round(rate * seconds))
    undecided = (max(frames) - min(frames) + 1 - len(frames)) if frames else 0  # published ids with no decision
    return dict(rate_hz=rate, frames=asked, decided=len(dec), drops=max(0, asked - len(dec)), undecided=undecided,
                decided_share=len(dec) / asked, commands=len(cmds), wrong=wrong,
                behind_p99=_p(red, 99) * rate / 1e3, executed=len(act),
                actuator_p50_ms=_p(act, 50), actuator_p99_ms=_p(act, 99),
                p50_ms=_p(lat, 50), p99_ms=_p(lat, 99), max_ms=float(lat.max()) if len(lat) else float("nan"),
                throughput_hz=len(dec) / seconds)


def bench_setting(setting: Setting, args, workdir: Path, rates: list[float], emit, params,
                  p99_limit: float = float("inf")) -> list[dict]:
    """Runs at each rate in turn (the first always; a later one only while the previous one had no drop and
    p99 <= p99_limit ms), for each worker count: a fresh `vergence up` each."""
    base_ms = in_process_ms(*setting.pair, params, n=100 if setting.pair[0].shape[1] < 2000 else 3)
    rows = []
    for nw in args.workers:
        for rate in rates:
            up = Up(workdir, f"bench{os.getpid()}{setting.name}{nw}", setting, nw, rate)
            try:
                r = run_rate(up, setting, rate, args.seconds)
            finally:
                up.close()
            r.update(setting=setting.name, source=setting.source, width=setting.pair[0].shape[1],
                     window=params.window, vsearch=params.vsearch, workers=nw, match_ms=base_ms,
                     overhead=r["p50_ms"] / base_ms)
            rows.append(r)
            emit(r)
            if args.rate is None and rate > rates[0] and (r["drops"] > 0 or r["p99_ms"] > p99_limit):
                break
    return rows


def settings(args, workdir: Path) -> list[tuple[Setting, object, list[float]]]:
    """(setting, its network parameters, its rates) for the run: the sources asked for, and --heavy's."""
    from vergence.network.params import Params
    from vergence.io.sources import open_source

    def config(name: str, net: dict):
        params = Params.paper(**net) if args.faithful else Params(**net)
        cfg = workdir / f"{name}.toml"
        cfg.write_text("\n".join(["[network]"] + [f"{k} = {json.dumps(v)}"
                                                   for k, v in dataclasses.asdict(params).items()]) + "\n")
        return params, cfg

    def files(name: str, width: int, height: int) -> str:
        pair = synthetic_pair(width, height)
        for side, img in zip("lr", pair):
            cv2.imwrite(str(workdir / f"{name}-{side}.png"), img)
        return f"files:{workdir / f'{name}-l.png'},{workdir / f'{name}-r.png'}"

    def rendered(spec: str):
        src = open_source(spec)
        try:
            return src.read(src.start_pan_rad)
        finally:
            src.close()

    rates = [args.rate] if args.rate else RATES
    out = []
    params, cfg = config("net", {})
    if args.source:
        out.append((Setting("source", args.source, cfg, rendered(args.source)), params, rates))
    else:
        vga = files("vga", 640, 480)
        out += [(Setting("vga", vga, cfg, synthetic_pair(640, 480), shifted=True), params, rates),
                (Setting("sim", "sim", cfg, rendered("sim")), params, rates),
                (Setting("demo", DEMO, cfg, rendered(DEMO)), params, rates)]
    if args.heavy:
        hp, hcfg = config("heavy", {"window": 31, "vsearch": 16, "max_window": 0})
        out.append((Setting("heavy", files("heavy", 3840, 1080), hcfg, synthetic_pair(3840, 1080), shifted=True),
                    hp, [args.rate] if args.rate else HEAVY_RATES))
    return out


def floor_subscriber(endpoint: str) -> int:
    """--floor's subscriber (`vergence bench pipeline --subscriber ENDPOINT`, its own process): a callback
    that copies each payload of bench/floor, until SIGINT/SIGTERM. Its session is opened as the services'
    (session.open_session: what was imported is frozen out of the garbage collector's reach)."""
    from services.runtime import session

    stop = session.Stop()
    with session.open_session(session.zenoh_config("client", [endpoint])) as s:
        sub = s.declare_subscriber("bench/floor", lambda smp: smp.payload.to_bytes())
        stop.wait()
        sub.undeclare()
    return 0


def _idle(procs: list[Proc], span: float = 0.3) -> bool:
    """Whether the processes used no CPU tick (10 ms) during the next `span` seconds."""
    before = [p.cpu_s() for p in procs]
    time.sleep(span)
    return [p.cpu_s() for p in procs] == before


def messaging_floor(workdir: Path, n: int = 3000, size: int = 27_000) -> dict:
    """CPU time per message of a router and of one Python subscriber (a callback that copies the payload),
    for `size`-byte messages published at 1 kHz by this process: the cost every hop of the pipeline pays."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs = [Proc("floor-router", vergence("router", "--listen", endpoint), log=workdir / "floor-router.log")]
    try:
        wait_listening(endpoint, 30, procs[0])
        procs.append(Proc("floor-subscriber", vergence("bench", "pipeline", "--subscriber", endpoint),
                          log=workdir / "floor-subscriber.log"))
        s = _session(endpoint)
        try:
            pub = s.declare_publisher("bench/floor", express=True)
            wait_for(lambda: pub.matching_status.matching, 60, "the floor's subscriber", interval=0.05)
            wait_for(lambda: _idle(procs), 30, "the floor's processes to settle", interval=0)
            before = [p.cpu_s() for p in procs]
            payload = bytes(size)
            t0 = time.monotonic()
            for i in range(n):
                pub.put(payload)
                d = t0 + (i + 1) / 1000 - time.monotonic()
                if d > 0:
                    time.sleep(d)
            time.sleep(0.3)
            after = [p.cpu_s() for p in procs]
        finally:
            s.close()
    finally:
        stop_all(procs[::-1])
    return dict(setting="floor", size=size, messages=n, router_us=(after[0] - before[0]) / n * 1e6,
                subscriber_us=(after[1] - before[1]) / n * 1e6)


def summary(rows: list[dict]) -> list[str]:
    """Per setting and worker count: the highest rate held without drops, and its latency."""
    out = []
    for key in dict.fromkeys((r["setting"], r["workers"]) for r in rows):
        clean = [r for r in rows if (r["setting"], r["workers"]) == key and r["drops"] == 0]
        if clean:
            best = max(clean, key=lambda r: r["rate_hz"])
            out.append(f"{key[0]:6s} {key[1]} worker(s): held {best['rate_hz']:.0f} Hz without drops "
                       f"(p50 {best['p50_ms']:.2f} ms, p99 {best['p99_ms']:.2f} ms)")
        else:
            out.append(f"{key[0]:6s} {key[1]} worker(s): every rate tried dropped frames")
    return out


def run(args: argparse.Namespace) -> int:
    import logging

    if args.subscriber:
        return floor_subscriber(args.subscriber)
    logging.basicConfig(level=logging.WARNING)

    def emit(r: dict) -> None:
        if args.json:
            print(json.dumps(r), flush=True)
        else:
            print(f"{r['setting']:6s} {r['width']:5d}px w={r['window']:<2d} R={r['vsearch']:<2d} "
                  f"{r['workers']} worker(s) {r['rate_hz']:6.0f} Hz: {r['decided']:5d}/{r['frames']:<5d} decided "
                  f"({100 * r['decided_share']:5.1f} %) drops {r['drops']:4d} ({r['undecided']} undecided)  "
                  f"p50 {r['p50_ms']:6.2f} ms  p99 {r['p99_ms']:6.2f} ms  max {r['max_ms']:6.1f} ms  "
                  f"cmds {r['commands']:5d} wrong {r['wrong']} behind {r['behind_p99']:4.1f}  "
                  f"actuator p50 {r['actuator_p50_ms']:5.2f} p99 {r['actuator_p99_ms']:5.2f} ms  "
                  f"match {r['match_ms']:6.2f} ms  overhead x{r['overhead']:.2f}", flush=True)

    with tempfile.TemporaryDirectory(prefix="vergence-bench-") as d:
        work = Path(d)
        try:
            if args.floor:
                f = messaging_floor(work)
                print(json.dumps(f) if args.json else
                      f"floor  {f['size']} B messages at 1 kHz: router {f['router_us']:.0f} us CPU per message, "
                      f"a Python subscriber {f['subscriber_us']:.0f} us", flush=True)
            rows = []
            for setting, params, rates in settings(args, work):
                rows += bench_setting(setting, args, work, rates, emit, params)
            if not args.json:
                for line in summary(rows):
                    print(line, flush=True)
        except (RuntimeError, TimeoutError, KeyboardInterrupt, ValueError, OSError) as e:
            print(f"vergence bench pipeline: {e}", file=sys.stderr)
            for log in sorted(work.glob("*.log")):
                print(f"--- {log.name}\n{log.read_text(errors='replace')[-800:]}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    _p = argparse.ArgumentParser(prog="vergence bench pipeline")
    configure(_p)
    sys.exit(run(_p.parse_args()))
