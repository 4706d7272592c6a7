"""`vergence bench pipeline [--workers N ...] [--rate HZ] [--frames N] [--heavy] [--json]`.

Measures the distributed pipeline as deployed: a router, N workers, the reducer and the capture run as real
processes on this machine, as `vergence up` runs them (peers linked directly; --client: clients of the
router, every message through it, as from other nodes); the capture publishes a synthetic textured pair (the
slave sees the scene 12 px further left, so every frame yields a command) at a fixed rate, and this process
subscribes to the commands.
Reported per run: capture-to-command latency p50/p99/max (the command's arrival here minus the frame's
t_capture_ns: one more hop than the actuator sees), throughput, frames dropped (published frames without a
command), beside the in-process vergence.match time on the same images (overhead = p50 / match).
Without --rate: 100 Hz, then 250, 500, 1000, 1500, 2000 Hz until a run drops frames
(the highest rate held without drops is the last clean one). --heavy adds the heavy setting (3840 x 1080,
w = 31, vertical search +-16) at a few Hz, where sharding pays. --floor: the CPU per message (psutil) of a
router and of a subscriber process (`vergence bench pipeline --subscriber ENDPOINT`). Processes start and
stop through services/ops/launch.py, each logging into a file of the run's temporary folder (shown on failure).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from services.runtime.args import number, whole
from services.ops.launch import Proc, free_port, stop_all, vergence, wait_for, wait_listening

RATES = [100, 250, 500, 1000, 1500, 2000]
HEAVY_RATES = [10, 25, 50, 100]
WARM_FRAMES = 20  # the first frames of a fresh capture process are slow (imports, first messages)


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workers", type=whole(1, 64), nargs="+", default=[1, 2], metavar="N",
                   help="worker counts (default 1 2)")
    p.add_argument("--rate", type=number(0, 1000, lo_open=True), default=None, metavar="HZ",
                   help="one rate only (default: a ramp)")
    p.add_argument("--seconds", type=number(0, 3600, lo_open=True), default=2.0,
                   help="length of each run (default 2 s)")
    p.add_argument("--heavy", action="store_true", help="also the heavy setting: 3840 wide, w=31, +-16 rows")
    p.add_argument("--faithful", action="store_true", help="the paper's network (no extension)")
    p.add_argument("--client", action="store_true", help="pipeline processes as clients of the router (every "
                                                         "message through it, as from other nodes) instead of "
                                                         "peers linked directly, as `vergence up` runs them")
    p.add_argument("--floor", action="store_true", help="also the messaging floor: CPU per 27 KB message of the "
                                                        "router and of one Python subscriber, at 1 kHz")
    p.add_argument("--actuator", action="store_true", help="also run the sim actuator (commands close the loop "
                                                           "through motor_state, as in `vergence up`)")
    p.add_argument("--json", action="store_true", help="one JSON object per run")
    p.add_argument("--subscriber", metavar="ENDPOINT", help=argparse.SUPPRESS)  # --floor's, in its own process


SHIFT = 12  # px: the synthetic pair's offset, which every command must carry


def synthetic_pair(width: int, height: int, shift: int = SHIFT, seed: int = 5) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.integers(0, 256, (height, width + 2 * shift), np.uint8), (5, 5), 1.5)
    return (np.ascontiguousarray(base[:, shift : shift + width]), np.ascontiguousarray(base[:, :width]))


class Cluster:
    """A router, a reducer and N workers (and the sim actuator) as child processes, stopped on close."""

    def __init__(self, workdir: Path, rig: str, config: str, workers: int, client: bool = False,
                 actuator: bool = False):
        self.dir, self.rig, self.config = workdir, rig, config
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.procs: list[Proc] = []
        self.extra = [] if client else ["--mode", "peer", "--listen", "tcp/127.0.0.1:0"]  # as `vergence up`
        self.members = ["reducer"] + (["actuator"] if actuator else [])  # besides the workers
        try:
            router = self.spawn("router", "router", "--listen", self.endpoint, member=False)
            wait_listening(self.endpoint, 30, router, logs=self.logs)
            if actuator:
                self.spawn("actuator", "actuator", "--driver", "sim")
            for i in range(workers):
                self.spawn(f"worker{i}", "worker", "--name", f"b{i}")
            self.spawn("reducer", "reducer")
        except BaseException:
            self.close()
            raise

    def spawn(self, name: str, *args: str, member: bool = True) -> Proc:
        argv = vergence(*args)
        if member:
            argv += ["--connect", self.endpoint, "--rig", self.rig, "--config", self.config] + self.extra
        p = Proc(name, argv, log=self.dir / f"{name}.log", append=True)
        self.procs.append(p)
        return p

    def logs(self) -> str:
        return "\n".join(p.tail(10) for p in self.procs)

    def close(self) -> None:
        for p in self.procs:  # all at once, then each in turn, the router last
            p.signal_group(signal.SIGINT)
        stop_all(self.procs[::-1])


def _session(endpoint: str):
    import zenoh

    from services.runtime import session

    return zenoh.open(session.zenoh_config("client", [endpoint]))


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


def run_rate(cl: Cluster, s, source: str, rate: float, frames: int) -> dict:
    """One capture run at `rate`: WARM_FRAMES frames to start the capture (not counted), then `frames`
    frames; the latency of the commands that came back for those."""
    from vergence import keys
    from vergence.messages import Command, MotorState

    warm = min(WARM_FRAMES, max(2, frames // 5))
    got: list[tuple[int, bytes]] = []
    lock = threading.Lock()

    def on_cmd(sample):
        t = time.time_ns()
        with lock:
            got.append((t, sample.payload.to_bytes()))

    states: list[bytes] = []
    sub = s.declare_subscriber(keys.command(cl.rig), on_cmd)
    sub_state = s.declare_subscriber(keys.motor_state(cl.rig),
                                     lambda smp: states.append(smp.payload.to_bytes()))
    try:
        cap = cl.spawn("capture", "capture", "--source", source, "--rate", str(rate), "--frames",
                       str(frames + warm))
        try:
            cap.wait(frames / rate * 3 + 30)
        except TimeoutError:
            cap.stop()
        time.sleep(0.3)  # the last frames' commands on their way
    finally:
        sub.undeclare()
        sub_state.undeclare()
    executed = executed_lags([MotorState.from_bytes(b) for b in states], warm + 1, frames + warm)
    act = np.array(sorted(executed.values())) / 1e6 if executed else np.array([np.nan])
    cmds = [(t, c) for t, c in ((t, Command.from_bytes(b)) for t, b in got) if warm < c.frame <= frames + warm]
    lat = np.array([(t - c.t_capture_ns) / 1e6 for t, c in cmds]) if cmds else np.array([np.nan])
    red = np.array([(c.t_sent_ns - c.t_capture_ns) / 1e6 for _, c in cmds]) if cmds else np.array([np.nan])
    caps = sorted(c.t_capture_ns for _, c in cmds)
    span = (caps[-1] - caps[0]) / 1e9 if len(caps) > 1 else float("nan")
    have = {c.frame for _, c in cmds}
    # a wrong command: one whose offset is not the pair's (SHIFT px), or older than one sent before it
    ids = [c.frame for _, c in sorted(cmds, key=lambda tc: tc[1].t_sent_ns)]
    wrong = sum(abs(c.magnitude_px - SHIFT) > 1.0 for _, c in cmds) + sum(b <= a for a, b in zip(ids, ids[1:]))
    lost = [i for i in range(warm + 1, warm + frames + 1) if i not in have]
    return dict(rate_hz=rate, frames=frames, commands=len(have), drops=len(lost), lost_first=lost[:12], wrong=wrong,
                behind_p99=float(np.percentile(red, 99)) * rate / 1e3, executed=len(executed),
                actuator_p50_ms=float(np.percentile(act, 50)), actuator_p99_ms=float(np.percentile(act, 99)),
                p50_ms=float(np.percentile(lat, 50)), p99_ms=float(np.percentile(lat, 99)),
                max_ms=float(lat.max()), reducer_p99_ms=float(np.percentile(red, 99)),
                throughput_hz=(len(caps) - 1) / span if span == span and span > 0 else float("nan"))


def bench_setting(name: str, width: int, height: int, net: dict, args, workdir: Path, rates: list[float],
                  emit, p99_limit: float = float("inf")) -> list[dict]:
    """Runs at each rate in turn (the first always; a later one only while the previous one had no drop and
    p99 <= p99_limit ms), for each worker count."""
    from vergence import keys
    from vergence.params import Params

    master, slave = synthetic_pair(width, height)
    lp, rp = workdir / f"{name}-l.png", workdir / f"{name}-r.png"
    cv2.imwrite(str(lp), master)
    cv2.imwrite(str(rp), slave)
    params = Params.paper(**net) if args.faithful else Params(**net)
    cfg = workdir / f"{name}.toml"
    lines = ["[network]"] + [f"{k} = {json.dumps(v)}" for k, v in dataclasses.asdict(params).items()]
    cfg.write_text("\n".join(lines + ["[capture]", "preview_hz = 0"]) + "\n")
    base_ms = in_process_ms(master, slave, params, n=30 if width < 2000 else 3)
    rows = []
    for nw in args.workers:
        cl = Cluster(workdir, f"bench{os.getpid()}{name}{nw}", str(cfg), nw, args.client, args.actuator)
        try:
            s = _session(cl.endpoint)
            try:
                for role, n in [("worker", nw)] + [(m, 1) for m in cl.members]:
                    try:
                        wait_for(lambda r=role, n=n: len(list(s.liveliness().get(keys.alives(cl.rig, r),
                                                                                  timeout=0.5))) >= n,
                                 60, f"{n} {role}(s)", interval=0.05)
                    except TimeoutError:
                        raise RuntimeError(f"{n} {role}(s) did not come up; see the logs in {workdir}") from None
                for rate in rates:
                    frames = max(10, int(rate * args.seconds))
                    r = run_rate(cl, s, f"files:{lp},{rp}", rate, frames)
                    r.update(setting=name, width=width, window=params.window, vsearch=params.vsearch, workers=nw,
                             match_ms=base_ms, overhead=r["p50_ms"] / base_ms)
                    rows.append(r)
                    emit(r)
                    if args.rate is None and rate > rates[0] and (r["drops"] > 0 or r["p99_ms"] > p99_limit):
                        break
            finally:
                s.close()
        finally:
            cl.close()
    return rows


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
                  f"{r['workers']} worker(s) {r['rate_hz']:6.0f} Hz: {r['commands']:5d}/{r['frames']:<5d} cmds "
                  f"drops {r['drops']:4d} wrong {r['wrong']} behind {r['behind_p99']:4.1f}  "
                  f"p50 {r['p50_ms']:6.2f} ms  p99 {r['p99_ms']:6.2f} ms  "
                  f"max {r['max_ms']:6.1f} ms  actuator p50 {r['actuator_p50_ms']:5.2f} "
                  f"p99 {r['actuator_p99_ms']:5.2f} ms  "
                  f"thr {r['throughput_hz']:7.1f} Hz  match {r['match_ms']:6.2f} ms  "
                  f"overhead x{r['overhead']:.2f}", flush=True)

    with tempfile.TemporaryDirectory(prefix="vergence-bench-") as d:
        work = Path(d)
        rates = [args.rate] if args.rate else RATES
        try:
            if args.floor:
                f = messaging_floor(work)
                print(json.dumps(f) if args.json else
                      f"floor  {f['size']} B messages at 1 kHz: router {f['router_us']:.0f} us CPU per message, "
                      f"a Python subscriber {f['subscriber_us']:.0f} us", flush=True)
            rows = bench_setting("vga", 640, 480, {"window": 15, "max_window": 0}, args, work, rates, emit)
            if args.heavy:
                hr = [args.rate] if args.rate else HEAVY_RATES
                rows += bench_setting("heavy", 3840, 1080, {"window": 31, "vsearch": 16, "max_window": 0}, args,
                                      work, hr, emit)
            if not args.json:
                for line in summary(rows):
                    print(line, flush=True)
        except (RuntimeError, TimeoutError, KeyboardInterrupt) as e:
            print(f"vergence bench pipeline: {e}", file=sys.stderr)
            for log in sorted(work.glob("*.log")):
                print(f"--- {log.name}\n{log.read_text(errors='replace')[-800:]}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    _p = argparse.ArgumentParser(prog="vergence bench pipeline")
    configure(_p)
    sys.exit(run(_p.parse_args()))
