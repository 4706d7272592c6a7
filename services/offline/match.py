"""`vergence match MASTER SLAVE [--at X,Y ...]`: the network on an image pair, one decision per point."""

from __future__ import annotations

import argparse
import json
import sys


from vergence import BorderError, Params, match
from vergence.head import depth
from vergence.config import ConfigError, load
from vergence.choices import Side
from vergence.io.images import read_image

from services.runtime.args import pixel, positive, whole


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("master", help="master (fixed camera) image file")
    p.add_argument("slave", help="slave (panning camera) image file")
    p.add_argument("--at", type=pixel, action="append", metavar="X,Y",
                   help="fovea centre in the master image, repeatable (default: the image centre)")
    p.add_argument("--window", type=whole(1, 501), default=None, help="fovea side w in pixels, odd "
                   "(default: the settings' [network] window, 15)")
    p.add_argument("--vsearch", type=whole(0, 100), default=None, help="rows R searched above and below "
                   "(default: the settings' [network] vsearch, 6; 0 with --faithful)")
    p.add_argument("--faithful", action="store_true", help="the paper's network: every extension off")
    p.add_argument("--config", metavar="FILE", help="settings TOML; its [network] table sets the parameters")
    p.add_argument("--json", action="store_true", help="one JSON object per point")
    p.add_argument("--baseline", type=positive, default=None, metavar="B",
                   help="baseline in metres: with --focal, print each point's depth Z = b f / disparity")
    p.add_argument("--focal", type=positive, default=None, metavar="F", help="focal length in pixels (with --baseline)")
    p.add_argument("--master-is", dest="master_side", choices=tuple(Side), default="left",
                   help="which camera MASTER is, for the disparity's sign (default left: disparity = -offset)")


def run(args: argparse.Namespace) -> int:
    if (args.baseline is None) != (args.focal is None):
        print("vergence match: --baseline and --focal go together (metres, pixels)", file=sys.stderr)
        return 2
    try:
        base = load(args.config).network
        if args.faithful:
            base = Params.paper(window=base.window)
        params = base.override(window=args.window, vsearch=args.vsearch)
        master, slave = read_image(args.master), read_image(args.slave)
        if master.shape != slave.shape:
            raise ValueError(f"images differ in size: {args.master} is {master.shape[1]} x {master.shape[0]}, "
                             f"{args.slave} is {slave.shape[1]} x {slave.shape[0]}")
        results = [match(master, slave, at, params) for at in (args.at or [None])]
    except (ValueError, BorderError, ConfigError, TypeError) as e:
        print(f"vergence match: {e}", file=sys.stderr)
        return 2
    for m in results:
        d = m.decision
        z = depth.pair_depth(m, args.baseline, args.focal, args.master_side) if args.baseline is not None else None
        if args.json:
            print(json.dumps({**m.to_dict(), **(z or {})}))
        else:
            side = {-1: "left", 0: "centre", 1: "right"}[d.direction]
            zs = ""
            if z is not None:
                zs = (f", depth {z['depth_m']:.4f} +- {z['depth_sigma_m']:.4f} m" if z["depth_m"] is not None
                      else ", no depth")
            print(f"({m.x}, {m.y}) w={m.window}: k*={d.k} (k_c={d.k_centre}) offset {d.offset_px:+.2f} px "
                  f"{side} {d.magnitude} px, v={d.v:+d}, confidence {d.confidence:.3f}"
                  f"{'' if d.confident else ' (abstains)'}{zs}")
    return 0
