"""`vergence sim`: the closed loop on the simulated rig in one process (the library only, no Zenoh).

With --motion SPEC the scene is a target moving in depth in front of the physical rig (--baseline,
--focal; vergence.sim.moving), and the output is a tracking run: pan, truth and error at each frame, the
RMS and maximum error after the first second. --camera-latency, --skew, --exposure and --jitter give the
cameras a real camera's timing (vergence.head.timing.CameraTiming); time stays virtual. A frame's t_s is its
master's exposure, its pan the slave's at the slave's exposure, its truth and error at t_s."""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import re
import sys

from vergence import Params
from vergence.head import depth
from vergence.config import ConfigError, load
from vergence.choices import ControlMode, Gimbal
from vergence.sim import Rig
from vergence.sim.faults import FAULT_KEYS, Faults
from vergence.sim.fixation import truth_at
from vergence.sim.loop import DELAY_S, closed_loop, frames_to_converge, tracking_error
from vergence.sim.moving import MovingRig
from vergence.head.timing import CameraTiming
from vergence.spec import parse

from services.runtime.args import number, whole, xy


def fixate_at_arg(text: str) -> tuple[int, tuple[int, int]]:
    """argparse type for --fixate-at FRAME:X,Y."""
    try:
        f, _, point = text.partition(":")
        x, y = xy(point, int)
        frame = int(f)
    except (ValueError, argparse.ArgumentTypeError):
        raise argparse.ArgumentTypeError(f"--fixate-at wants FRAME:X,Y (integers), got {text!r}") from None
    if frame < 0:
        raise argparse.ArgumentTypeError(f"--fixate-at: frame {frame} is negative")
    return frame, (x, y)


def camera_timing(args: argparse.Namespace) -> CameraTiming:
    """The cameras' timing from --camera-latency, --skew, --exposure, --jitter (ValueError naming the option)."""
    try:
        return CameraTiming(args.camera_latency, args.skew, args.exposure, args.jitter)
    except ValueError as e:
        name = re.split("[:=]", str(e), maxsplit=1)[0]
        flag = {"latency_s": "--camera-latency", "skew_s": "--skew", "exposure_s": "--exposure",
                "jitter_s": "--jitter"}.get(name, name)
        raise ValueError(f"{flag}{str(e)[len(name):]}") from None


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
    p.add_argument("--start-off", metavar="PX", type=number(-10_000, 10_000),
                   help="start the slave PX pixels past the converged pan instead (needs the ground truth)")
    p.add_argument("--noise", metavar="SIGMA", help="Gaussian sensor noise of both cameras")
    p.add_argument("--gain", help="slave = gain * I + offset (photometric difference)")
    p.add_argument("--offset")
    p.add_argument("--blur", metavar="SIGMA", help="defocus of the slave (Gaussian sigma, px)")
    p.add_argument("--vmis", metavar="PX", help="vertical misalignment of the slave, px (an extra tilt)")
    p.add_argument("--seed", help="seed of the generated scene and of the noise")
    p.add_argument("--gimbal", choices=tuple(Gimbal),
                   help="helmholtz: both cameras pan on one tilting "
                   "platform (default, the paper's rig); fick: each camera tilts on its own pan joint")
    p.add_argument("--fixate-at", type=fixate_at_arg, action="append", default=[], metavar="FRAME:X,Y",
                   help="from frame FRAME on, the fovea at (X, Y) of the master view (repeatable); the "
                   "re-convergence after each is reported")
    p.add_argument("--motion", metavar="SPEC",
                   help="a target moving in depth: still:z=Z | step:z0=Z0,z1=Z1,at=S | ramp:z0=Z0,z1=Z1,speed=M_S | "
                        "sine:z=Z,amp=A,hz=F | square:z0=Z0,z1=Z1,hz=F (metres, seconds)")
    p.add_argument("--baseline", type=number(0, 10, lo_open=True), default=None, metavar="M",
                   help="the rig's baseline in metres: the moving rig's (--motion), and depth_m's (default: "
                   "settings [rig] baseline_m, 0.06)")
    p.add_argument("--texture", metavar="FILE|flat",
                   help="--motion: an image as the target's texture (default procedural; flat: none)")
    p.add_argument("--mode", choices=tuple(ControlMode), help="the controller (default: [control] mode)")
    p.add_argument("--delay-ms", type=number(0, 10_000), default=None, metavar="MS",
                   help="read to command, virtual (default 5)")
    p.add_argument("--camera-latency", type=number(0, 1, note="seconds"), default=0.0, metavar="S",
                   help="the image is S old when read (exposure to read; default 0)")
    p.add_argument("--skew", type=number(-0.5, 0.5, note="seconds"), default=0.0, metavar="S",
                   help="the slave is exposed S after the master (negative: before; default 0)")
    p.add_argument("--exposure", type=number(0, 1, note="seconds"), default=0.0, metavar="S",
                   help="each view integrates the scene and the slave's motion over S (motion blur; default 0)")
    p.add_argument("--jitter", type=number(0, 1, note="seconds"), default=0.0, metavar="S",
                   help="exposure times off their schedule, standard deviation S (default 0)")
    p.add_argument("--frames", type=whole(0, 10_000_000), default=20,
                   help="frames to run after the starting one (default 20)")
    p.add_argument("--rate", type=number(0, 1000, lo_open=True), default=30.0,
                   help="frames per second of the virtual clock (default 30)")
    p.add_argument("--faults", metavar="SPEC", default="",
                   help="the simulator's lies (vergence/sim/faults.py): freeze=T0-T1, freeze_master=T0-T1, "
                        "black=T0-T1, reverse, slip=T0-T1, stall=T0-T1, backlash=DEG, focal_true=PX, "
                        "encoder_noise=DEG, joined by ':' (times in s from the first exposure)")
    p.add_argument("--faithful", action="store_true", help="the paper's network: every extension off")
    p.add_argument("--config", metavar="FILE", help="settings TOML: [network], [control], [actuator.motor]")
    p.add_argument("--json", action="store_true", help="one JSON line per frame, the starting state first")
    p.add_argument("--plot", metavar="FILE.png", help="write the pan trajectory and the first/last profiles")
    p.add_argument("--save", metavar="FILE.rrd", help="write the run as a Rerun recording: the views, the fovea "
                   "and match boxes, the profile, pan against truth (the [view] extra)")


def _setup(args: argparse.Namespace):
    """The settings, the network's parameters, the control, the delay, the camera timing, the rig, the baseline
    and the fixations the options ask for; ValueError or ConfigError when they do not go together."""
    settings = load(args.config)
    params = Params.paper(window=settings.network.window) if args.faithful else settings.network
    static = dict(left=args.left, right=args.right, disparity=args.disparity, dscale=args.dscale,
                  fixate=args.fixate, gain=args.gain, offset=args.offset, blur=args.blur, vmis=args.vmis,
                  gimbal=args.gimbal)
    control = settings.control if args.mode is None else dataclasses.replace(settings.control, mode=args.mode)
    delay = DELAY_S if args.delay_ms is None else args.delay_ms / 1000.0
    timing = camera_timing(args)
    faults = Faults.take(parse(args.faults, FAULT_KEYS, "--faults"))
    rig = _rig(args, static)
    told = rig.focal_px  # the focal length the settings say; focal_true renders the images at another
    if faults.focal_true is not None:
        rig = _rig(argparse.Namespace(**{**vars(args), "focal": str(faults.focal_true)}), static)
    if args.frames < 0 or not args.rate > 0:
        raise ValueError(f"--frames must be >= 0 and --rate > 0, got {args.frames} and {args.rate}")
    if args.start_off is not None:
        if args.start_pan is not None:
            raise ValueError("give --start-pan or --start-off, not both")
        if not math.isfinite(rig.truth_pan_rad):
            raise ValueError("--start-off needs the ground truth: --disparity FILE "
                             "(or the generated scene)")
        rig.start_pan_rad = rig.pan_off_truth(args.start_off)
    baseline = args.baseline if args.baseline is not None else (
        rig.head.baseline_m if args.motion is not None else settings.geometry.baseline_m)
    if not (math.isfinite(baseline) and baseline > 0):
        raise ValueError(f"--baseline {baseline}: must be a positive number of metres")
    fixations = _fixations(args, rig)
    return settings, params, control, delay, timing, rig, baseline, fixations, faults, told


def _rig(args: argparse.Namespace, static: dict):
    """The moving rig of --motion, else the static one of the scene's options."""
    if args.motion is not None:
        given = sorted(k for k, v in static.items() if v is not None)
        if given:
            raise ValueError(f"--{given[0]} does not go with --motion (the moving scene is generated)")
        return MovingRig.from_options(motion=args.motion, baseline=args.baseline, focal=args.focal,
                                      size=args.size, noise=args.noise, seed=args.seed, pan=args.start_pan,
                                      texture=args.texture)
    if args.texture is not None:
        raise ValueError("--texture goes with --motion")
    return Rig.from_options(focal=args.focal, size=args.size, noise=args.noise, pan=args.start_pan,
                            seed=args.seed, **static)


def _fixations(args: argparse.Namespace, rig) -> dict:
    """--fixate-at as {frame: (x, y)}, each inside the view and no later than the last frame."""
    fixations = dict(args.fixate_at)
    if fixations and args.motion is not None:
        raise ValueError("--fixate-at does not go with --motion (the moving target is on the master's axis)")
    for f, (x, y) in fixations.items():
        if not (0 <= x < rig.size[0] and 0 <= y < rig.size[1]):
            raise ValueError(f"--fixate-at {f}:{x},{y}: outside the {rig.size[0]} x {rig.size[1]} view")
        if f > args.frames:
            raise ValueError(f"--fixate-at {f}:{x},{y}: after the last frame (--frames {args.frames}); "
                             f"run at least --frames {f}")
    return fixations


def run(args: argparse.Namespace) -> int:
    try:
        settings, params, control, delay, timing, rig, baseline, fixations, faults, told = _setup(args)
    except (ValueError, ConfigError) as e:
        print(f"vergence sim: {e}", file=sys.stderr)
        return 2
    steps = []
    # the fovea, and its truth: (converged slave pan, disparity), NaN where unknown (a moving rig: per frame)
    at, truth = (rig.size[0] // 2, rig.size[1] // 2), None
    saving = _start_save(args.save, rig) if args.save else None
    if args.save and saving is None:
        return 2
    segments = []  # (first frame, (x, y)) of each fixation
    try:
        run_ = closed_loop(rig, args.frames, params, control, settings.actuator.motor, args.rate, delay,
                           fixations=fixations, timing=timing, state_hz=settings.actuator.state_hz,
                           seed=int(args.seed or 0), faults=faults, focal_px=told)
        first = next(run_)
    except ValueError as e:
        print(f"vergence sim: {e}", file=sys.stderr)
        return 2
    for s in itertools.chain([first], run_):
        if s.frame in fixations or s.frame == 0:
            if s.frame in fixations:
                at, truth = fixations[s.frame], truth_at(rig, *fixations[s.frame])
            segments.append((s.frame, at))
        pan = math.radians(s.pan_deg)
        if truth is not None:  # a fixation away from the centre: the truth of that point
            s = dataclasses.replace(s, truth_pan_deg=math.degrees(truth[0]),
                                    error_px=rig.focal_px * math.tan(pan - truth[0]))
        steps.append(s)
        if saving:
            saving(s, args.rate)
        _print_step(args, s, rig, at, truth, baseline)
    if saving:
        saving.rr.disconnect()  # flushes the file
        print(f"wrote {args.save} ({len(steps)} frames): `rerun {args.save}` shows it", file=sys.stderr)
    _summary(args, steps, segments, rig, timing, control)
    return 0


def _print_step(args: argparse.Namespace, s, rig, at: tuple[int, int], truth, baseline: float) -> None:
    """One frame's line (or JSON row with --json): the pan, the error, the decision and the fixated depth."""
    pan = math.radians(s.pan_deg)
    dep = depth.fixated_depth(x=at[0], y=at[1], width=rig.size[0], height=rig.size[1], focal_px=rig.focal_px,
                              slave_pan_rad=pan, offset_px=s.offset_px, v_shift=s.v, confident=s.confident,
                              sigma_d_px=depth.disparity_sigma(s.scores, s.k, s.window), baseline_m=baseline,
                              master_pan_rad=rig.master_pan_rad, tilt_rad=rig.tilt_rad, gimbal=rig.gimbal)
    if args.motion is not None:
        truth_z = rig.motion.z(s.t_s)
    else:
        truth_z = depth.depth_from_disparity(rig.disparity if truth is None else truth[1], baseline, rig.focal_px)
    if args.json:
        row = s.to_dict()
        row.update(x=at[0], y=at[1], converged=dep.converged,
                   depth_m=dep.depth_m if math.isfinite(dep.depth_m) else None,
                   depth_sigma_m=dep.depth_sigma_m if math.isfinite(dep.depth_sigma_m) else None,
                   truth_depth_m=truth_z if math.isfinite(truth_z) else None)
        print(json.dumps(row), flush=True)
    else:
        tgt = "-" if s.target_deg is None else f"{s.target_deg:+8.3f}"
        z = f"{dep.depth_m:.4f} +- {dep.depth_sigma_m:.4f} m" if math.isfinite(dep.depth_m) else "-"
        print(f"frame {s.frame:3d}  ({at[0]}, {at[1]})  pan {s.pan_deg:+8.3f} deg  error {s.error_px:+8.2f} px  "
              f"offset {s.offset_px:+8.2f} px  {'confident' if s.confident else 'abstains '}  "
              f"w={s.window}  target {tgt}  depth {z}", flush=True)


def _summary(args: argparse.Namespace, steps: list, segments: list, rig, timing, control) -> None:
    """The plot (--plot), and the tracking error (--motion) or each fixation's convergence."""
    moving = args.motion is not None
    skip = int(round(args.rate)) if len(steps) > args.rate else 0  # the statistics after the first second
    if args.plot:
        from vergence.observe.plots import plot_run, plot_tracking

        if moving:
            late = f", image {timing.latency_s * 1e3:g} ms old" if timing.latency_s else ""
            plot_tracking(steps, args.plot, f"{rig.motion.spec}, {args.rate:g} Hz{late}, {control.mode}, "
                          f"b={rig.head.baseline_m:g} m, f={rig.focal_px:g} px", first=skip)
        else:
            plot_run(steps, args.plot, math.degrees(rig.one_px_rad))
    if moving and not args.json:
        e = tracking_error(steps, first=skip)
        print(f"from frame {skip} ({e['frames']} frames): RMS {e['rms_px']:.2f} px ({e['rms_deg']:.3f} deg), "
              f"max {e['max_px']:.2f} px ({e['max_deg']:.3f} deg)")
        own = [s.camera_error_px for s in steps if s.frame >= skip and math.isfinite(s.camera_error_px)]
        if args.faults and own:  # (backlash, a slip, a reversed camera leave the camera elsewhere than the shaft)
            rms = math.sqrt(sum(x * x for x in own) / len(own))
            print(f"the slave camera's own, as the lies leave it: RMS {rms:.2f} px, max {max(map(abs, own)):.2f} px")
    elif not args.json:
        _convergence(steps, segments)


def _convergence(steps: list, segments: list) -> None:
    """Each fixation's converged pan and from which frame on the pan is within 1 px of it."""
    for i, (first, (x, y)) in enumerate(segments):
        end = segments[i + 1][0] if i + 1 < len(segments) else len(steps)
        seg = steps[first:end]
        n = frames_to_converge(seg)
        where = "" if len(segments) == 1 else f"fixation ({x}, {y}) from frame {first}: "
        if not seg or not math.isfinite(seg[0].truth_pan_deg):
            last = seg[-1] if seg else None
            print(where + "no ground truth (give --disparity FILE --dscale S); "
                  + (f"last offset {last.offset_px:+.2f} px at pan {last.pan_deg:+.3f} deg" if last
                     else "no frame"))
        else:
            print(where + f"converged pan {seg[0].truth_pan_deg:+.3f} deg; "
                  + ("within 1 px from frame %d on (%d frames after the fixation)" % (n, n - first)
                     if n is not None else "not within 1 px at the end"))


def _start_save(path: str, rig: Rig):
    """A function logging each Step to the Rerun recording `path` (None after printing why not). The views
    come from a copy of the rig taken before the loop: it renders the same pans in the same order, so its
    images (noise included) are the ones the network saw."""
    import copy

    from services.observe import view

    try:
        rr = view.import_rerun()
        rr.init(view.APP_ID + "-sim", spawn=False)
        rr.save(path, default_blueprint=view.blueprint(rr))
    except (view.MissingExtra, OSError, RuntimeError) as e:
        print(f"vergence sim: {e}", file=sys.stderr)
        return None
    twin = copy.deepcopy(rig)

    def log_step(s, rate_hz: float) -> None:
        master, slave = twin.render(math.radians(s.pan_deg))
        view.log_sim_step(rr, s, master, slave, (master.shape[1] // 2, master.shape[0] // 2), rate_hz)

    log_step.rr = rr
    return log_step
