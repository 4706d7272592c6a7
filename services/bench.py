"""`vergence bench kernel|match|pipeline`: benchmarks that print ratios against baselines run alongside."""

from __future__ import annotations

import argparse
import importlib
import json
import sys


def configure(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="bench", metavar="WHAT", required=True)
    k = sub.add_parser("kernel", help="correlate vs cv2.matchTemplate vs plain numpy, interleaved")
    k.add_argument("--json", action="store_true", help="one JSON object per case")
    k.add_argument("--repeats", type=int, default=7, help="interleaved rounds per case (default 7)")
    k.add_argument("--quick", action="store_true", help="only the 640 and 3840 extremes")
    m = sub.add_parser("match", help="vergence.match for one point of a 640 x 480 pair")
    m.add_argument("--json", action="store_true")
    m.add_argument("--repeats", type=int, default=400)
    try:
        importlib.import_module("services.bench_pipeline").configure(
            sub.add_parser("pipeline", help="capture-to-command latency and throughput over Zenoh"))
    except ModuleNotFoundError:
        pass


def _kernel(args) -> int:
    from vergence.bench import CASES, KernelCase, bench_kernel

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
    from vergence.bench import bench_match

    r = bench_match(args.repeats)
    if args.json:
        print(json.dumps(r))
    else:
        for k, v in r.items():
            print(f"{k:22s} {v:8.3f}")
        print("medians in ms, one point of a 640 x 480 pair, interleaved; match = features + kernel + decision "
              "(+ left-right check)")
    return 0


def run(args: argparse.Namespace) -> int:
    if args.bench == "kernel":
        return _kernel(args)
    if args.bench == "match":
        return _match(args)
    return importlib.import_module("services.bench_pipeline").run(args)


if __name__ == "__main__":
    sys.exit(0)
