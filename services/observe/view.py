"""`vergence view [--rig R] [--save FILE.rrd] [--web [--port P]] [--spawn]`: the rig's cockpit in Rerun.

Subscribes (callbacks only queue the samples; the main thread decodes and logs them) to vergence/<rig>/
preview, frame, decision, profile, command, motor_state, status/** and the liveliness tokens alive/**, and
logs them to Rerun on two timelines, `frame` (the frame id) and `capture` (its capture time). It publishes
only its status (services.runtime.node.Node: vergence/<rig>/status/view/<id>) and declares no token; its
subscription to the profile key is what makes the reducer publish profiles (as for `vergence monitor`).

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
import logging
import os
import sys
import threading

from vergence.wire import keys

from services.observe.cockpit import ENTITIES, WATCHED, Cockpit
from services.observe.playback import log_sim_step, parse_target, view_recording
from services.observe.rerun_sdk import APP_ID, INSTALL_HINT, MissingExtra, analytics_off, blueprint, import_rerun
from services.observe.sinks import SaveWatch, host_address, start
from services.observe.web import ASSETS, csp, serve_offline, viewer_assets
from services.runtime.args import PORT, number, whole
from services.runtime.node import Node

# the names the other modules and the tests take from here (`from services.observe import view`)
__all__ = ["APP_ID", "ASSETS", "ENTITIES", "INSTALL_HINT", "WATCHED", "Cockpit", "MissingExtra", "SaveWatch",
           "analytics_off", "blueprint", "configure", "csp", "host_address", "import_rerun", "log_sim_step", "main",
           "parse_target", "run", "serve_offline", "start", "view_recording", "viewer_assets"]

log = logging.getLogger("vergence.view")


# -- the process ---------------------------------------------------------------------------------------------

def configure(p: argparse.ArgumentParser) -> None:
    from services.runtime import session

    session.add_options(p)
    p.add_argument("--save", metavar="FILE.rrd", help="write a Rerun recording")
    p.add_argument("--web", action="store_true", help="serve the web viewer (shipped in the wheel, offline)")
    p.add_argument("--port", type=PORT, default=9090, metavar="P", help="--web: the viewer's HTTP port (default 9090)")
    p.add_argument("--grpc-port", type=PORT, default=9876, metavar="P",
                   help="--web: the port the viewer fetches the data from (default 9876)")
    p.add_argument("--bind", default="0.0.0.0", metavar="IP",
                   help="--web: the address to serve on (default 0.0.0.0: other machines; 127.0.0.1: this one)")
    p.add_argument("--spawn", action="store_true", help="open the native viewer (needs a display); the default "
                                                         "when neither --save nor --web is given")
    p.add_argument("--timeout", type=number(0, None, lo_open=True), default=None, metavar="S",
                   help="exit S seconds after the start, the wait for a router included")
    session.add_wait(p)
    p.add_argument("--nice", type=whole(-20, 19), default=10, metavar="N",
                   help="run at this niceness, so that the loop's processes come first on a busy CPU (default 10)")


class _Inbox:
    """The samples of the zenoh threads, queued for the main thread (which decodes and logs them)."""

    def __init__(self, prefix: str, maxlen: int = 20000):
        self.prefix = prefix  # what the callbacks strip: the cockpit takes the rest of the key
        self.queue: collections.deque = collections.deque(maxlen=maxlen)
        self.ready = threading.Event()
        self.full = 0  # samples pushed out of a full inbox (the viewer fell behind)

    def on_sample(self, sample) -> None:
        import time

        if len(self.queue) == self.queue.maxlen:
            self.full += 1
        self.queue.append((str(sample.key_expr)[len(self.prefix):], sample.payload.to_bytes(), time.time_ns()))
        self.ready.set()

    def on_alive(self, sample) -> None:
        import time

        import zenoh

        self.queue.append((str(sample.key_expr)[len(self.prefix):], sample.kind == zenoh.SampleKind.PUT,
                           time.time_ns()))
        self.ready.set()


def _open_rerun(rig: str, save, web, port, grpc_port, spawn, bind):
    """The rerun module and the web viewer's URL (None when not serving), or an exit code (2) once said why."""
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
    return rr, url


def _open_node(rr, rig: str, conf, stop, timeout: float | None):
    """The view's node (services.runtime.node: the session, and the status it publishes), entered; or an exit
    code once said why (1: no router within timeout, 2: a bad config)."""
    node = Node("view", rig, conf, stop, log=log, timeout=timeout)
    try:
        return node.__enter__()
    except SystemExit:  # Ctrl-C before a router answered
        rr.disconnect()
        raise
    except ConnectionError as e:  # no router within --wait
        print(f"vergence view: {e}", file=sys.stderr)
        rr.disconnect()
        return 1
    except Exception as e:  # a bad endpoint or config
        print(f"vergence view: cannot open a zenoh session: {e}", file=sys.stderr)
        rr.disconnect()
        return 2


def _drain(cockpit: Cockpit, inbox: _Inbox) -> None:
    """Log what the inbox holds; no message may end the cockpit."""
    while inbox.queue:
        rest, payload, t_ns = inbox.queue.popleft()
        try:
            if isinstance(payload, bool):
                cockpit.alive(rest, payload, t_ns)
            else:
                cockpit.feed(rest, payload, t_ns)
        except Exception as e:  # no message may end the cockpit
            cockpit.bad["error"] += 1
            log.warning("message on %s not logged: %s", rest, e)


def _loop(node: Node, cockpit: Cockpit, inbox: _Inbox, watch: SaveWatch, stop, end: float | None) -> None:
    """Log the samples as they come until stopped, past `end` (monotonic), or --save can no longer be written."""
    import time

    while not stop.is_set() and (end is None or time.monotonic() < end):
        inbox.ready.wait(0.1)
        inbox.ready.clear()
        if watch.fault():  # --save can no longer be written: say it once, stop (exit 1)
            print(f"vergence view: {watch.fault()}; stopped", file=sys.stderr)
            break
        _drain(cockpit, inbox)
        node.tick()


def main(rig: str, conf, stop, *, save: str | None = None, web: bool = False, port: int = 9090,
         grpc_port: int = 9876, spawn: bool = False, bind: str = "0.0.0.0", timeout: float | None = None,
         nice: int = 10, wait: float = 5.0) -> int:
    import time

    t0 = time.monotonic()  # --timeout counts from here

    if nice:
        try:  # before rerun's and zenoh's threads start: they inherit it
            os.nice(nice)
        except OSError:
            pass
    opened = _open_rerun(rig, save, web, port, grpc_port, spawn, bind)
    if isinstance(opened, int):
        return opened
    rr, url = opened
    cockpit = Cockpit(rr)
    inbox = _Inbox(keys.prefix(rig))
    end = t0 + timeout if timeout is not None else None
    # no router within --wait (or --timeout, if shorter): one line, exit 1
    node = _open_node(rr, rig, conf, stop, wait if timeout is None else min(wait, max(0.0, end - time.monotonic())))
    if isinstance(node, int):
        return node
    try:
        # frames (30 KB each at 640 px) too, for what decisions may not carry: the fovea's point (older reducers)
        # and the simulator's truth; the node undeclares the subscriptions at exit, then closes the session
        for k in WATCHED:
            node.subscriber(k(rig), inbox.on_sample)
        node.liveliness_subscriber(keys.alives(rig), inbox.on_alive, history=True)
        log.info("view: rig %s -> %s", rig, ", ".join(x for x in (save and f"file {save}", url, spawn and "viewer")
                                                       if x))
        watch = SaveWatch(save)
        _loop(node, cockpit, inbox, watch, stop, end)
    finally:
        node.__exit__(None, None, None)
    while inbox.queue:  # what arrived before the subscriptions closed
        rest, payload, t_ns = inbox.queue.popleft()
        (cockpit.alive if isinstance(payload, bool) else cockpit.feed)(rest, payload, t_ns)
    rr.disconnect()  # flushes the file
    log.info("view exits: logged %s, bad %s, dropped %d (behind)", dict(cockpit.counts), dict(cockpit.bad),
             inbox.full)
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
                grpc_port=args.grpc_port, spawn=spawn, bind=args.bind, timeout=args.timeout, nice=args.nice,
                wait=args.wait)
