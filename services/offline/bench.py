"""`vergence bench kernel|match|messages|pipeline|tracking|faults|ros2|start`: benchmarks that print ratios against
baselines run alongside (tracking: the p controller is the predictive one's baseline, in the same virtual-time
runs; start: the later starts are the first's)."""

from __future__ import annotations

import argparse
import importlib
import json
import sys

from services.runtime.args import number, whole


def configure(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="bench", metavar="WHAT", required=True)
    k = sub.add_parser("kernel", help="correlate vs cv2.matchTemplate vs plain numpy, interleaved")
    k.add_argument("--json", action="store_true", help="one JSON object per case")
    k.add_argument("--repeats", type=whole(1, 1_000_000), default=7, help="interleaved rounds per case (default 7)")
    k.add_argument("--quick", action="store_true", help="only the 640 and 3840 extremes")
    m = sub.add_parser("match", help="vergence.match for one point of a 640 x 480 pair")
    m.add_argument("--json", action="store_true")
    m.add_argument("--repeats", type=whole(1, 1_000_000), default=400)
    g = sub.add_parser("messages", help="decode and encode time per message kind vs a bare msgpack parse")
    g.add_argument("--json", action="store_true", help="one JSON object per kind")
    g.add_argument("--repeats", type=whole(1, 1_000_000), default=9)
    t = sub.add_parser("tracking", help="tracking error on a target moving in depth (simulated, virtual time): "
                                        "sine 0.25-2 Hz x 30/60/120 Hz x p/predictive, and a step")
    t.add_argument("--json", action="store_true", help="one JSON object per row")
    t.add_argument("--seconds", type=number(0, 3600, lo_open=True), default=5.0,
                   help="length of each sine run (default 5)")
    t.add_argument("--seed", type=whole(0, 2**32 - 1), default=0, help="seed of the scene's textures (default 0)")
    t.add_argument("--rates", default=None, help="camera rates, Hz (default 30,60,120; --camera: 30,60)")
    t.add_argument("--hz", default=None, help="sine frequencies (default 0.25,0.5,1,2; --camera: 0.5,1)")
    t.add_argument("--camera", action="store_true",
                   help="the camera's timing instead: the image 0/33/66/100 ms old when read (--latencies) x the "
                        "rates (default 30,60) x sine 0.5/1 Hz x {-, skew 8 ms, exposure 8 ms} x predictive/p, the "
                        "slave starting parallel (as vergence sim --camera-latency runs it)")
    t.add_argument("--latencies", default="0,0.033,0.066,0.1", help="--camera: seconds (default 0,0.033,0.066,0.1)")
    f = sub.add_parser("faults", help="the simulator's lies (frozen, slipping, reversed, stalled, black cameras and "
                                      "motors) against the loop's doubt: time to name each, excursion, recovery, and "
                                      "false faults on clean runs (simulated, virtual time)")
    f.add_argument("--json", action="store_true", help="one JSON object per row")
    f.add_argument("--seeds", default="0", help="the scenes' textures and noise (default 0; e.g. 0,1,2)")
    f.add_argument("--rates", default="30,60", help="camera rates, Hz (default 30,60)")
    f.add_argument("--latencies", default="0,0.066", help="the images' age when read, s (default 0,0.066)")
    try:
        importlib.import_module("services.offline.bench_pipeline").configure(
            sub.add_parser("pipeline", help="capture-to-command latency and throughput over Zenoh"))
    except ModuleNotFoundError:
        pass
    importlib.import_module("services.offline.bench_ros2").configure(
        sub.add_parser("ros2", help="the latency the ROS 2 bridge and source add (the [ros2] extra)"))
    importlib.import_module("services.offline.bench_start").configure(
        sub.add_parser("start", help="`vergence up`'s first start (it compiles) against the later ones: the "
                                     "seconds to the first decision and to the slave following"))


def _kernel(args) -> int:
    from vergence.tools.bench import CASES, KernelCase, bench_kernel

    cases = [KernelCase(640, 15, 1), KernelCase(3840, 31, 33)] if args.quick else CASES
    if not args.json:
        print(f"{'case':22s} {'correlate':>10s} {'opencv':>10s} {'numpy':>10s}   {'/opencv':>8s} {'/numpy':>8s}")

    def show(r):
        if args.json:
            print(json.dumps(r), flush=True)
            return
        npy = f"{r['numpy_ms']:10.3f}" if r["numpy_ms"] is not None else f"{'-':>10s}"
        rn = f"{r['ratio_vs_numpy']:8.3f}" if r["ratio_vs_numpy"] is not None else f"{'-':>8s}"
        print(f"{r['case']:22s} {r['correlate_ms']:10.3f} {r['opencv_ms']:10.3f} {npy}   "
              f"{r['ratio_vs_opencv']:8.3f} {rn}", flush=True)

    bench_kernel(cases, repeats=args.repeats, progress=show)
    if not args.json:
        import cv2
        print(f"medians in ms per call, interleaved; correlate on one thread, OpenCV on its default "
              f"{cv2.getNumThreads()}; ratios are correlate / baseline (lower is better); numpy '-' when one call "
              "takes over 2 s")
    return 0


def _match(args) -> int:
    from vergence.tools.bench import bench_match

    r = bench_match(args.repeats)
    if args.json:
        print(json.dumps(r))
    else:
        for k, v in r.items():
            print(f"{k:22s} {v:8.3f}")
        print("medians in ms, one point of a 640 x 480 pair, interleaved; match = features + kernel + decision "
              "(+ left-right check)")
    return 0


def _messages(args) -> int:
    from vergence.tools.bench import bench_messages

    for r in bench_messages(args.repeats):
        if args.json:
            print(json.dumps(r))
        else:
            print(f"{r['kind']:9s} {r['bytes']:6d} B  decode {r['decode_us']:6.2f} us  (msgpack.unpackb "
                  f"{r['msgpack_us']:6.2f} us, x{r['vs_msgpack']:.2f})  encode {r['encode_us']:5.2f} us")
    if not args.json:
        print("medians in us at 640 x 480, w = 15, R = 6; decode = Class.from_bytes (msgspec, type and value checks), "
              "its baseline a bare msgpack parse to a dict")
    return 0


def _fmt(v, spec: str) -> str:
    """v in spec, or "-" as wide where there is no value."""
    return format(v, spec) if v is not None else format("-", spec.split(".")[0].rstrip("fds") + "s")


def _numbers(text: str) -> tuple[float, ...]:
    return tuple(float(x) for x in text.split(","))


def _tracking(args) -> int:
    from vergence.tools.bench import bench_tracking

    try:
        rates = _numbers(args.rates or ("30,60" if args.camera else "30,60,120"))
        hzs = _numbers(args.hz or ("0.5,1" if args.camera else "0.25,0.5,1,2"))
        latencies = _numbers(args.latencies)
        if not (args.seconds > 1 and all(r > 0 for r in rates) and all(h >= 0 for h in hzs)
                and all(0 <= v <= 1 for v in latencies)):
            raise ValueError
    except ValueError:
        print("vergence bench tracking: --rates, --hz and --latencies are comma-separated numbers (rates > 0, "
              "latencies 0 to 1 s), --seconds > 1", file=sys.stderr)
        return 2
    if args.camera:
        return _camera(args, latencies, rates, hzs)
    if not args.json:
        print(f"{'motion':28s} {'Hz':>5s} {'mode':>10s} {'RMS px':>7s} {'max px':>7s} {'RMS deg':>8s} "
              f"{'max deg':>8s} {'settle':>6s} {'over px':>7s}")

    def show(r):
        if args.json:
            print(json.dumps(r), flush=True)
            return
        print(f"{r['motion']:28s} {r['rate_hz']:5.0f} {r['mode']:>10s} {_fmt(r['rms_px'], '7.2f')} "
              f"{_fmt(r['max_px'], '7.2f')} {_fmt(r['rms_deg'], '8.3f')} {_fmt(r['max_deg'], '8.3f')} "
              f"{_fmt(r.get('settle_frames'), '6d') if 'settle_frames' in r else ' ' * 6} "
              f"{_fmt(r.get('overshoot_px'), '7.2f') if 'overshoot_px' in r else ''}", flush=True)

    bench_tracking(hzs, rates, seconds=args.seconds, seed=args.seed, progress=show)
    if not args.json:
        print(f"b = 0.06 m, f = 500 px, 640 x 480, seed {args.seed}; sine: z = 0.8 m, amp = 0.3 m, {args.seconds:g} s "
              "from a converged start, error after the first second; step: frames from the step to within 1 px "
              "for good, overshoot past the new truth, error after settling. Virtual time, 5 ms capture to "
              "command, the default simulated servo")
    return 0


def _faults(args) -> int:
    from vergence.tools.faults import bench_faults

    try:
        rates, latencies = _numbers(args.rates), _numbers(args.latencies)
        seeds = tuple(int(v) for v in args.seeds.split(","))
        if not rates or min(rates) <= 0 or min(latencies, default=0) < 0 or min(seeds, default=0) < 0:
            raise ValueError
    except ValueError:
        print("vergence bench faults: --rates, --latencies and --seeds are comma-separated numbers (rates > 0, "
              "latencies >= 0, seeds whole >= 0)", file=sys.stderr)
        return 2

    def show(r):
        if args.json:
            print(json.dumps(r), flush=True)
            return
        head = f"{r['lie']:14s} {r['scene']:7s} {r['rate_hz']:4.0f} Hz {r['latency_ms']:3d} ms seed {r['seed']}  "
        if r["lie"] == "focal_true":
            body = (f"focal named after {_fmt(r.get('focal_named_s'), '5.2f')} s  ratio "
                    f"{_fmt(r.get('focal_ratio'), '5.3f')}  later steps' overshoot "
                    f"{_fmt(r.get('overshoot_px'), '5.1f')} px")
        elif r["lie"] == "backlash":
            body = f"RMS / the clean runs' (4 lattice shifts) {_fmt(r.get('rms_vs_clean'), '5.2f')}"
        else:
            body = (f"fault {_fmt(r.get('fault'), '14s')} after {_fmt(r.get('diagnosed_s'), '5.3f')} s  excursion "
                    f"{_fmt(r.get('excursion_deg'), '5.2f')} deg {_fmt(r.get('excursion_px'), '6.1f')} px  commands "
                    f"{_fmt(r.get('commands_in_fault'), '3d')}  back {_fmt(r.get('recovered_s'), '5.2f')} s")
        print(f"{head}{body}  RMS {r['rms_px']:5.2f} px  false {r['false_fault_frames']}", flush=True)

    bench_faults(rates, latencies, seeds, progress=show)
    return 0


def _camera(args, latencies, rates, hzs) -> int:
    from vergence.tools.bench import bench_camera

    if not args.json:
        print(f"{'motion':24s} {'latency':>7s} {'Hz':>4s} {'variant':>13s} {'mode':>10s} {'RMS px':>7s} "
              f"{'max px':>7s}")

    def show(r):
        if args.json:
            print(json.dumps(r), flush=True)
            return
        print(f"{r['motion']:24s} {r['latency_ms']:5.0f} ms {r['rate_hz']:4.0f} {r['variant']:>13s} {r['mode']:>10s} "
              f"{r['rms_px']:7.2f} {r['max_px']:7.2f}", flush=True)

    bench_camera(latencies, rates, hzs, seconds=args.seconds, seed=args.seed, progress=show)
    if not args.json:
        print(f"b = 0.06 m, f = 500 px, 640 x 480, seed {args.seed}; sine: z = 0.8 m, amp = 0.3 m, the slave starting "
              f"parallel, error from the first second to {args.seconds:g} s at the master's exposures; the image "
              "'latency' old when read, 5 ms read to command, the motor reporting at 50 Hz; p is the predictive "
              "controller's baseline")
    return 0


def run(args: argparse.Namespace) -> int:
    if args.bench == "messages":
        return _messages(args)
    if args.bench == "tracking":
        return _tracking(args)
    if args.bench == "faults":
        return _faults(args)
    if args.bench == "kernel":
        return _kernel(args)
    if args.bench == "match":
        return _match(args)
    if args.bench == "ros2":
        return importlib.import_module("services.offline.bench_ros2").run(args)
    if args.bench == "start":
        return importlib.import_module("services.offline.bench_start").run(args)
    return importlib.import_module("services.offline.bench_pipeline").run(args)

