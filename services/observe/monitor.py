"""`vergence monitor [--rig NAME] [--png FILE] [--timeout S] [--once]`: a read-only live view of a running rig.

Subscribes (zenoh callbacks only: the network threads never wait on the screen) to vergence/<rig>/frame,
profile, command, motor_state and status/**, and to the liveliness tokens vergence/<rig>/alive/**; feeds
them to vergence.observe.monitor.Monitor, which counts and skips malformed messages. The main thread redraws the
screen (ANSI, vergence.observe.screen.render_text) every --refresh seconds. It publishes only its status (through
services.runtime.node.Node: vergence/<rig>/status/monitor/<id>) and declares no token, but its subscription
to the profile key is what makes the reducer publish profiles (it encodes them only while someone subscribes).

    --once         wait for a profile (at most --timeout s, default 10), print one screen, exit
                   (exit code 1 when no profile came)
    --png FILE     collect --history s of pan history, wait for the next profile, write the paper's figure 5
                   (layer 4 against k, winner and centre marked) with the pan history as a PNG, exit
    --timeout S    live view: exit after S s (default: run until Ctrl-C)
    --wait S       give up (exit 1, one line) when no router answers within S s (default 5, or --timeout if
                   shorter); --timeout counts from the start, the wait for the router included
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
import threading
import time

import zenoh

from vergence.wire import keys
from vergence.config import load
from vergence.observe.monitor import Monitor
from vergence.observe.screen import render_text
from vergence.observe.plots import monitor_png

from services.runtime import session
from services.runtime.args import number
from services.runtime.node import Node

log = logging.getLogger("vergence.monitor")
# the keys the monitor watches under vergence/<rig>/: not the correlations (their shards come from the frames'
# plans) nor the previews, so a monitor costs the rig little
WATCHED = (keys.frame, keys.profile, keys.command, keys.motor_state, keys.statuses)


def _columns(out) -> int:
    """The terminal's width now, asked of the terminal itself (it follows a resize; an inherited COLUMNS does
    not), else shutil's answer (COLUMNS, then 100)."""
    try:
        return os.get_terminal_size(out.fileno()).columns
    except (OSError, ValueError, AttributeError):
        return shutil.get_terminal_size((100, 40)).columns


def configure(p: argparse.ArgumentParser) -> None:
    session.add_options(p)
    p.add_argument("--png", metavar="FILE", help="write a PNG of the next profile with the pan history, then exit")
    p.add_argument("--size", default="960x720", metavar="WxH", help="PNG size in pixels (default 960x720)")
    p.add_argument("--history", type=number(0, 3600, lo_open=True), default=2.0, metavar="S",
                   help="--png: seconds of pan history collected before the profile is taken (default 2)")
    p.add_argument("--once", action="store_true", help="print one screen once a profile came, then exit")
    p.add_argument("--timeout", type=number(0, None, lo_open=True), default=None, metavar="S",
                   help="exit after S seconds (--once/--png: give up waiting after S s, default 10)")
    session.add_wait(p)
    p.add_argument("--refresh", type=number(0, 60, lo_open=True), default=0.5, metavar="S",
                   help="screen refresh period (default 0.5)")
    p.add_argument("--window", type=number(0, 3600, lo_open=True), default=5.0, metavar="S",
                   help="rates and latency percentiles over the last S seconds (default 5)")
    p.add_argument("--color", choices=["auto", "always", "never"], default="auto",
                   help="ANSI colours and screen redraws (auto: when stdout is a terminal)")


class Watch:
    """The monitor's subscriptions on an open session, feeding `model` from zenoh's callback threads."""

    def __init__(self, node: Node, rig: str, model: Monitor):
        self.model = model
        self.profiles = threading.Condition()
        self.n_profiles = 0
        # the node undeclares them at exit
        self.subs = [node.subscriber(k(rig), self._on_sample) for k in WATCHED]
        self.subs.append(node.liveliness_subscriber(keys.alives(rig), self._on_alive, history=True))

    def _on_sample(self, sample) -> None:
        try:
            k = keys.parse(str(sample.key_expr))
            msg = self.model.feed(str(sample.key_expr), sample.payload.to_bytes())
        except Exception as e:  # never let a message kill the callback thread; the model counts its own
            log.warning("sample on %s not handled: %s", sample.key_expr, e)
            return
        if msg is not None and k is not None and k.kind == keys.PROFILE:
            with self.profiles:
                self.n_profiles += 1
                self.profiles.notify_all()

    def _on_alive(self, sample) -> None:
        self.model.liveliness(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

    def wait_profile(self, after: int, deadline: float, stop: session.Stop) -> bool:
        """Wait until more than `after` profiles arrived (monotonic deadline); False on timeout or stop."""
        with self.profiles:
            while self.n_profiles <= after:
                left = deadline - time.monotonic()
                if left <= 0 or stop.is_set():
                    return False
                self.profiles.wait(min(left, 0.1))
        return True

def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w < 160 or h < 120:
            raise ValueError
    except ValueError:
        raise SystemExit(f"vergence monitor: --size wants WxH of at least 160x120, got {text!r}") from None
    return w, h


def main(rig: str, conf: zenoh.Config, stop: session.Stop, args: argparse.Namespace, out=sys.stdout) -> int:
    t0 = time.monotonic()  # --timeout counts from here, the wait for a router included
    model = Monitor(rig, window_s=args.window)
    node = Node("monitor", rig, conf, stop, log=log,
                timeout=args.wait if args.timeout is None else min(args.wait, args.timeout))
    try:
        node.__enter__()
    except ConnectionError as e:
        print(f"vergence monitor: {e}", file=sys.stderr)
        return 1
    try:
        watch = Watch(node, rig, model)
        if args.png:
            return _png(watch, model, args, stop, t0)
        if args.once:
            return _once(watch, model, args, stop, out, t0)
        return _live(node, model, args, stop, out, t0)
    finally:
        node.__exit__(None, None, None)


def _color(args: argparse.Namespace, out) -> bool:
    return args.color == "always" or (args.color == "auto" and out.isatty())


def _once(watch: Watch, model: Monitor, args: argparse.Namespace, stop: session.Stop, out, t0: float) -> int:
    """--once: wait for a profile, print one screen; 1 when no profile came."""
    wait = args.timeout if args.timeout is not None else 10.0
    got = watch.wait_profile(0, t0 + wait, stop)
    # a second of rates and latencies beyond the first profile (bounded by the timeout)
    stop.wait(max(0.0, min(1.0, t0 + wait - time.monotonic())))
    cols = _columns(out) if out.isatty() else 100
    print(render_text(model.snapshot(), width=cols, color=_color(args, out)), file=out, flush=True)
    if not got:
        print(f"vergence monitor: no profile on {keys.profile(model.rig)} within {wait:g} s "
              f"(is a reducer running with workers and a capture on this router?)", file=sys.stderr)
    return 0 if got else 1


def _live(node: Node, model: Monitor, args: argparse.Namespace, stop: session.Stop, out, t0: float) -> int:
    """The live view: the screen every --refresh s until stopped or --timeout; the node's status between."""
    tty, color = out.isatty(), _color(args, out)
    end = t0 + args.timeout if args.timeout is not None else None
    while not stop.wait(args.refresh if end is None else max(0.0, min(args.refresh, end - time.monotonic()))):
        cols = _columns(out) if tty else 100
        text = render_text(model.snapshot(), width=cols, color=color)
        if color:
            out.write("\x1b[H\x1b[2J" + text + "\n")
        else:
            out.write(text + "\n\n")
        out.flush()
        node.tick()
        if end is not None and time.monotonic() >= end:
            break
    return 0


def _png(watch: Watch, model: Monitor, args: argparse.Namespace, stop: session.Stop, t0: float) -> int:
    w, h = _size(args.size)
    wait = args.timeout if args.timeout is not None else 10.0
    stop.wait(max(0.0, min(args.history, wait)))  # the recent pan history
    if not watch.wait_profile(watch.n_profiles, t0 + wait, stop):
        print(f"vergence monitor: no profile on {keys.profile(model.rig)} within {wait:g} s; no PNG written",
              file=sys.stderr)
        return 1
    snap = model.snapshot()
    data = monitor_png(snap, w, h)
    try:
        with open(args.png, "wb") as f:
            f.write(data)
    except OSError as e:
        print(f"vergence monitor: cannot write {args.png!r}: {e.strerror}", file=sys.stderr)
        return 2
    print(f"wrote {args.png} ({w} x {h}): profile of frame {snap.profile.frame}, winner k*={snap.profile.k}, "
          f"{len(snap.pan_history)} pan states", file=sys.stderr)
    return 0


def run(args: argparse.Namespace) -> int:
    logging.getLogger().setLevel(logging.WARNING)
    settings = load(args.config)
    if args.png:
        _size(args.size)
    stop = session.Stop()
    return main(args.rig or settings.rig, session.config_from_args(args), stop, args)
