"""`vergence accuracy LEFT RIGHT DISP [--loop]`: the network's accuracy on any rectified pair with a ground-truth
disparity, drawn as the tests draw Middlebury's (vergence.tools.evaluate). No Zenoh."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tomllib

import vergence
from vergence.tools import evaluate
from vergence.config import ConfigError, from_dict
from vergence.io.images import read_image
from services.runtime.args import positive


def ints(text: str) -> list[int]:
    """argparse type for --seeds: 0,1,2."""
    try:
        out = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"want integers separated by commas, got {text!r}") from None
    return out


def gains(text: str) -> list[str]:
    """argparse type for --gains: names of evaluate.GAINS separated by commas."""
    out = [g.strip() for g in text.split(",")]
    bad = [g for g in out if g not in evaluate.GAINS]
    if bad:
        raise argparse.ArgumentTypeError(f"unknown gain(s) {', '.join(map(repr, bad))}; known: "
                                         f"{', '.join(evaluate.GAINS)}")
    return out


def count(text: str) -> int:
    """argparse type for --n: a whole number >= 1."""
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v < 1:
        raise argparse.ArgumentTypeError(f"want a whole number >= 1, got {text!r}")
    return v


def configure(p: argparse.ArgumentParser) -> None:
    p.description = (f"{p.description}. static (default): per gain and seed, n visible points "
                     f"{evaluate.STATIC_MARGIN} px from the border, the share answered confidently and the share of "
                     f"those within 1 px. --loop: the closed loop from 10-40 px off, the share converged within 1 px "
                     f"by frame {evaluate.LOOP_BY}, per gain, paired against equal gain.")
    p.add_argument("left", help="left image (the master)")
    p.add_argument("right", help="right image (the slave)")
    p.add_argument("disp", help="the left image's disparity in px: a .npz (arr_0; inf, NaN or <= 0 = unknown) "
                   "or an image (its value / --dscale; 0 = unknown)")
    p.add_argument("--dscale", type=positive, default=1.0, metavar="S",
                   help="an image disparity's value per pixel of disparity (Middlebury 2003: 4; default 1)")
    p.add_argument("--loop", action="store_true", help="the closed loop instead of the static accuracy")
    p.add_argument("--seeds", type=ints, default=None, metavar="S,...",
                   help=f"draws (default {','.join(map(str, evaluate.STATIC_SEEDS))}; with --loop "
                   f"{','.join(map(str, evaluate.LOOP_SEEDS))})")
    p.add_argument("--n", type=count, default=None,
                   help=f"points per seed (default {evaluate.STATIC_N}; with --loop {evaluate.LOOP_N})")
    p.add_argument("--gains", type=gains, default=list(evaluate.GAINS), metavar="G,...",
                   help="the slave image as is (equal), 1.3 I + 20 (bright), 0.7 I - 15 (dark); default all three")
    p.add_argument("--faithful", action="store_true", help="the paper's network: every extension off")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a network parameter (Params field, as in the settings' [network] table), repeatable: "
                   "--set clip_fallback=false")
    p.add_argument("--json", action="store_true", help="one JSON object with every figure, at the end")


def _value(text: str):
    """A --set value as TOML reads it (false, 3, 0.5, "affine"); a bare word is a string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def params_from(faithful: bool, sets: list[str]) -> vergence.Params:
    """Params (the paper's with faithful) with the --set KEY=VALUE changes, checked as the settings file's
    [network] table is (vergence.config.from_dict): ConfigError naming the field."""
    base = vergence.FAITHFUL if faithful else vergence.Params()
    if not sets:
        return base
    changes = {}
    for kv in sets:
        key, eq, text = kv.partition("=")
        if not eq or not key.strip():
            raise ConfigError(f"--set wants KEY=VALUE, got {kv!r}")
        changes[key.strip()] = _value(text.strip())
    try:
        return from_dict({**dataclasses.asdict(base), **changes}, vergence.Params)
    except ConfigError as e:
        raise ConfigError(f"--set {str(e).removeprefix('settings: ')}") from None


def run(args: argparse.Namespace) -> int:
    try:
        params = params_from(args.faithful, args.set)
        left, right = read_image(args.left), read_image(args.right)
        disp = evaluate.load_disparity(args.disp, args.dscale)
        if left.shape != right.shape or left.shape != disp.shape:
            raise ValueError(f"sizes differ: {args.left} is {left.shape[1]} x {left.shape[0]}, {args.right} "
                             f"{right.shape[1]} x {right.shape[0]}, {args.disp} {disp.shape[1]} x {disp.shape[0]}")
        what = evaluate.loop if args.loop else evaluate.static
        seeds = args.seeds or list(evaluate.LOOP_SEEDS if args.loop else evaluate.STATIC_SEEDS)
        n = args.n or (evaluate.LOOP_N if args.loop else evaluate.STATIC_N)
        each = None if args.json else (lambda g: print(g.line(), flush=True))
        figures = what(left, right, disp, params, seeds=seeds, n=n, gains=args.gains, each=each)
    except (ValueError, ConfigError) as e:
        print(f"vergence accuracy: {e}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({"mode": "loop" if args.loop else "static", "seeds": seeds, "n": n,
                          "gains": [g.to_dict() for g in figures]}))
    return 0
