"""`vergence sim`: the closed loop on the simulated rig in one process (the library only, no Zenoh).

With --motion SPEC the scene is a target moving in depth in front of the physical rig (--baseline,
--focal; vergence.sim.moving), and the output is a tracking run: pan, truth and error at each frame, the
RMS and maximum error after the first second."""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import sys

from vergence import Params
from vergence.config import ConfigError, load
from vergence.sim import Rig
from vergence.sim.loop import DELAY_S, closed_loop, frames_to_converge, tracking_error
from vergence.sim.moving import MovingRig


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--left",
                   help="LEFT image of a rectified pair (the master's scene); default: the generated one")
    p.add_argument("--right", help="RIGHT image (the slave's scene)")
    p.add_argument("--disparity", help="ground-truth disparity of LEFT (an image; value / --dscale = px)")
    p.add_argument("--dscale", help="scale of --disparity (Middlebury: 4, 8 or 16)")
    p.add_argument("--fixate", metavar="X,Y", help="fixation pixel of LEFT (default: its centre)")
    p.add_argument("--focal", metavar="F", help="focal length in pixels (default 0.8 x width)")
    p.add_argument("--size", metavar="WxH",
                   help="size of the rendered views (default: the pair's; generated: 640x480)")
    p.add_argument("--start-pan", metavar="DEG", help="the slave's starting pan in degrees (default 0)")
    p.add_argument("--start-off", metavar="PX", type=float,
                   help="start the slave PX pixels past the converged pan instead (needs the ground truth)")
    p.add_argument("--noise", metavar="SIGMA", help="Gaussian sensor noise of both cameras")
    p.add_argument("--gain", help="slave = gain * I + offset (photometric difference)")
    p.add_argument("--offset")
    p.add_argument("--blur", metavar="SIGMA", help="defocus of the slave (Gaussian sigma, px)")
    p.add_argument("--vmis", metavar="PX", help="vertical misalignment of the slave, px (an extra tilt)")
    p.add_argument("--seed", help="seed of the generated scene and of the noise")
    p.add_argument("--gimbal", choices=("helmholtz", "fick"),
                   help="helmholtz: both cameras pan on one tilting "
                   "platform (default, the paper's rig); fick: each camera tilts on its own pan joint")
    p.add_argument("--motion", metavar="SPEC",
                   help="a target moving in depth: still:z=Z | step:z0=Z0,z1=Z1,at=S | ramp:z0=Z0,z1=Z1,speed=M_S | "
                        "sine:z=Z,amp=A,hz=F (metres, seconds)")
    p.add_argument("--baseline", metavar="M", help="--motion: the rig's baseline in metres (default 0.06)")
    p.add_argument("--texture", metavar="FILE|flat",
                   help="--motion: an image as the target's texture (default procedural; flat: none)")
    p.add_argument("--mode", choices=("p", "predictive"), help="the controller (default: [control] mode)")
    p.add_argument("--delay-ms", type=float, default=None, metavar="MS",
                   help="capture to command, virtual (default 5)")
    p.add_argument("--frames", type=int, default=20, help="frames to run after the starting one (default 20)")
    p.add_argument("--rate", type=float, default=30.0,
                   help="frames per second of the virtual clock (default 30)")
    p.add_argument("--faithful", action="store_true", help="the paper's network: every extension off")
    p.add_argument("--config", metavar="FILE", help="settings TOML: [network], [control], [actuator.motor]")
    p.add_argument("--json", action="store_true", help="one JSON line per frame, the starting state first")
    p.add_argument("--plot", metavar="FILE.png", help="write the pan trajectory and the first/last profiles")


def run(args: argparse.Namespace) -> int:
    try:
        settings = load(args.config)
        params = Params.paper(window=settings.network.window) if args.faithful else settings.network
        static = dict(left=args.left, right=args.right, disparity=args.disparity, dscale=args.dscale,
                      fixate=args.fixate, gain=args.gain, offset=args.offset, blur=args.blur, vmis=args.vmis,
                      gimbal=args.gimbal)
        control = settings.control if args.mode is None else dataclasses.replace(settings.control, mode=args.mode)
        delay = DELAY_S if args.delay_ms is None else args.delay_ms / 1000.0
        if args.motion is not None:
            given = sorted(k for k, v in static.items() if v is not None)
            if given:
                raise ValueError(f"--{given[0]} does not go with --motion (the moving scene is generated)")
            rig = MovingRig.from_options(motion=args.motion, baseline=args.baseline, focal=args.focal,
                                         size=args.size, noise=args.noise, seed=args.seed, pan=args.start_pan,
                                         texture=args.texture)
        elif args.baseline is not None or args.texture is not None:
            raise ValueError("--baseline and --texture go with --motion")
        else:
            rig = Rig.from_options(focal=args.focal, size=args.size, noise=args.noise, pan=args.start_pan,
                                   seed=args.seed, **static)
        if args.frames < 0 or not args.rate > 0:
            raise ValueError(f"--frames must be >= 0 and --rate > 0, got {args.frames} and {args.rate}")
        if args.start_off is not None:
            if args.start_pan is not None:
                raise ValueError("give --start-pan or --start-off, not both")
            if not math.isfinite(rig.truth_pan_rad):
                raise ValueError("--start-off needs the ground truth: --disparity FILE "
                                 "(or the generated scene)")
            rig.start_pan_rad = rig.pan_off_truth(args.start_off)
    except (ValueError, ConfigError) as e:
        print(f"vergence sim: {e}", file=sys.stderr)
        return 2
    steps = []
    try:
        run_ = closed_loop(rig, args.frames, params, control, settings.actuator.motor, args.rate, delay)
        first = next(run_)
    except ValueError as e:
        print(f"vergence sim: {e}", file=sys.stderr)
        return 2
    for s in itertools.chain([first], run_):
        steps.append(s)
        if args.json:
            print(json.dumps(s.to_dict()), flush=True)
        else:
            tgt = "-" if s.target_deg is None else f"{s.target_deg:+8.3f}"
            print(f"frame {s.frame:3d}  pan {s.pan_deg:+8.3f} deg  error {s.error_px:+8.2f} px  "
                  f"offset {s.offset_px:+8.2f} px  {'confident' if s.confident else 'abstains '}  "
                  f"w={s.window}  target {tgt}", flush=True)
    moving = args.motion is not None
    skip = int(round(args.rate)) if len(steps) > args.rate else 0  # the statistics after the first second
    if args.plot:
        from vergence.sim.plot import plot_run, plot_tracking

        if moving:
            plot_tracking(steps, args.plot, f"{rig.motion.spec}, {args.rate:g} Hz, {control.mode}, "
                          f"b={rig.head.baseline_m:g} m, f={rig.focal_px:g} px", first=skip)
        else:
            plot_run(steps, args.plot, math.degrees(rig.one_px_rad))
    if moving and not args.json:
        e = tracking_error(steps, first=skip)
        print(f"from frame {skip} ({e['frames']} frames): RMS {e['rms_px']:.2f} px ({e['rms_deg']:.3f} deg), "
              f"max {e['max_px']:.2f} px ({e['max_deg']:.3f} deg)")
    elif not args.json:
        n = frames_to_converge(steps)
        if not math.isfinite(rig.truth_pan_rad):
            last = steps[-1] if steps else None
            print("no ground truth (give --disparity FILE --dscale S); "
                  + (f"last offset {last.offset_px:+.2f} px at pan {last.pan_deg:+.3f} deg" if last
                     else "no frame"))
        else:
            print(f"converged pan {math.degrees(rig.truth_pan_rad):+.3f} deg; "
                  + ("within 1 px from frame %d on" % n if n is not None else "not within 1 px at the end"))
    return 0
