"""`vergence up [--workers N] [--source SPEC] [--driver sim] [--listen ENDPOINT] [--ros2]`: the whole pipeline here.

Starts, as child processes: a Zenoh router listening on ENDPOINT (default tcp/127.0.0.1:7447), the actuator,
N workers, the reducer and the capture. These are Zenoh peers: each connects to the router, learns the others
from it and links to them directly on 127.0.0.1, so a frame crosses one link per stage and the router carries
no data between them (it serves the clients: `vergence monitor`, workers on other nodes). With no arguments it
runs the simulated rig.

Supervised: a child that exits (the router too) is started again after a back-off (0.2 s, doubled at each
quick death up to 5 s, back to 0.2 s once it has run 10 s), with one log line per restart and the counts;
the reducer and the capture, slow to start, each have a standby (a second process that has imported and
warmed up and waits in session.open_session) that takes over the moment its child dies. A child that exits
with 2 at its first start (bad options or settings) stops everything instead.

SIGINT (Ctrl-C) or SIGTERM ends the supervision and stops the standbys, then the children in order (capture
first, router last), each with SIGINT, then SIGTERM and SIGKILL after grace times (services/launch.py);
children also get SIGTERM if `up` itself dies (Linux parent-death signal), so nothing is left behind.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time

from vergence.config import load

from . import session
from .launch import GRACE_S, Proc, accepts, vergence, wait_listening

log = logging.getLogger("vergence.up")
POLL_S = 0.05  # how often dead children are looked for
BACKOFF_S = (0.2, 5.0)  # the wait before a restart: first, then doubled up to the second ...
STABLE_S = 10.0  # ... and back to the first once the child has run this long
STATUS_S = 60.0  # a line with the restart counts this often
ROUTER_START_S = 10.0  # the router has this long to listen before anything else starts
STANDBY_DELAY_S = 5.0  # a standby is started this long after its child (not to slow the child's own start)


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workers", "-n", type=int, default=2, help="number of worker processes (default 2)")
    p.add_argument("--source", default=None, metavar="SPEC", help="capture source (default: settings, sim)")
    p.add_argument("--driver", default=None, help="actuator driver (default: settings, sim)")
    p.add_argument("--port", default=None, metavar="URL", help="actuator serial port (real drivers)")
    p.add_argument("--rate", type=float, default=None, metavar="HZ", help="capture rate (default: settings, 30)")
    p.add_argument("--listen", "-l", default=session.DEFAULT_ROUTER, metavar="ENDPOINT",
                   help=f"the embedded router's endpoint, the one every child connects to (default "
                        f"{session.DEFAULT_ROUTER})")
    p.add_argument("--no-actuator", action="store_true", help="do not start the actuator (a real one runs "
                                                                "elsewhere)")
    p.add_argument("--rig", default=None, help="rig name, the key prefix vergence/<rig>/ (default: head)")
    p.add_argument("--config", metavar="FILE", help="vergence settings (TOML), passed to every child")
    p.add_argument("--ros2", action="store_true", help="start `vergence ros2` too: the rig's topics as a ROS 2 node "
                                                        "(the [ros2] extra; docs/ROS2.md)")
    p.add_argument("--no-standby", action="store_true",
                   help="no standby reducer and capture (each a second process, ready to take over at once if "
                        "the first dies; the capture has none with cameras, which one process holds)")


def commands(args: argparse.Namespace, rig: str) -> list[tuple[str, list[str]]]:
    """(name, argv) of every child, in start order: router, actuator, workers, reducer, capture."""
    base = vergence()
    common = ["--mode", "peer", "--connect", args.listen, "--listen", "tcp/127.0.0.1:0", "--rig", rig]
    common += ["--config", args.config] if args.config else []
    out = [("router", base + ["router", "--listen", args.listen])]
    if not args.no_actuator:
        act = base + ["actuator"] + common
        if args.driver:
            act += ["--driver", args.driver]
        if args.port:
            act += ["--port", args.port]
        out.append(("actuator", act))
    for i in range(args.workers):
        out.append((f"worker{i + 1}", base + ["worker", "--name", f"w{i + 1}"] + common))
    out.append(("reducer", base + ["reducer"] + common))
    if args.ros2:
        out.append(("ros2", base + ["ros2"] + common))
    cap = base + ["capture"] + common
    if args.source:
        cap += ["--source", args.source]
    if args.rate is not None:
        cap += ["--rate", str(args.rate)]
    out.append(("capture", cap))
    return out


class Standby:
    """A second copy of a child, started ahead: it has imported and warmed up, and waits in
    session.open_session for a byte on its pipe (then it is the child) or its end (then it leaves)."""

    def __init__(self, name: str, argv: list[str]):
        self.name = name  # the child's
        ready_r, ready_w = os.pipe()
        go_r, go_w = os.pipe()
        env = dict(os.environ, **{session.STANDBY_ENV: f"{ready_w},{go_r}"})
        self.p = Proc(f"the standby of {name}", argv, env=env, die_with_parent=True, pass_fds=(ready_w, go_r))
        os.close(ready_w)
        os.close(go_r)
        os.set_blocking(ready_r, False)
        self._ready_r, self._go_w = ready_r, go_w
        self.ready = False

    def poll_ready(self) -> bool:
        """True the first time the standby says it is ready."""
        if self.ready or self._ready_r < 0:
            return False
        try:
            got = os.read(self._ready_r, 1)
        except BlockingIOError:
            return False
        os.close(self._ready_r)
        self._ready_r = -1
        self.ready = bool(got)
        return self.ready

    def go(self) -> Proc:
        """Let it open its session: from now on it is the child."""
        try:
            os.write(self._go_w, b"g")
        except OSError:
            pass
        self.close()
        self.p.name = self.name
        return self.p

    def close(self) -> None:
        """Close up's ends of the pipes (a standby still waiting leaves)."""
        for fd in (self._ready_r, self._go_w):
            if fd >= 0:
                os.close(fd)
        self._ready_r = self._go_w = -1


class Child:
    """One supervised child: its command, the running process, its restarts, its back-off and, for the
    children on the decisions' path that are slow to start (reducer, capture), a standby."""

    def __init__(self, name: str, argv: list[str], standby: bool = False):
        self.name, self.argv = name, argv
        self.p: Proc | None = None
        self.started = 0.0  # time.monotonic() of the latest start
        self.restarts = 0
        self.backoff = BACKOFF_S[0]
        self.due: float | None = None  # when a dead child is started again
        self.standby: Standby | None = None
        self.standby_due: float | None = None  # when a standby is started (None: this child has none)
        if standby:
            self.standby_due = 0.0

    def start(self) -> None:
        self.p = Proc(self.name, self.argv, die_with_parent=True)
        self.started, self.due = time.monotonic(), None
        if self.standby_due is not None:
            self.standby_due = max(self.standby_due, self.started + STANDBY_DELAY_S)

    def exited(self) -> int | None:
        return None if self.p is None else self.p.poll()


def stop_all(children: list[Child]) -> None:
    """The standbys first (their pipes closed: they leave), then each child (latest started first): SIGINT,
    SIGTERM after GRACE_S, SIGKILL after launch.TERM_GRACE_S more (launch.Proc.stop)."""
    for c in children:
        if c.standby is not None:
            c.standby.close()
    for c in children:
        if c.standby is not None:
            c.standby.p.stop(GRACE_S, log=log)
            c.standby = None
    for c in reversed(children):
        if c.p is not None:
            c.p.stop(GRACE_S, log=log)
            log.info("%s stopped (exit %s)", c.name, c.p.returncode)


def restarts_line(children: list[Child]) -> str:
    """"restarts: reducer 1, router 2" (or "no restarts")."""
    done = [f"{c.name} {c.restarts}" for c in children if c.restarts]
    return "restarts: " + ", ".join(done) if done else "no restarts"


def _tend_standby(c: Child, now: float) -> None:
    """Start c's standby when due, note when it is ready, replace it if it died."""
    sb = c.standby
    if sb is not None:
        if sb.poll_ready():
            log.info("standby of %s (pid %d) ready", c.name, sb.p.pid)
        elif sb.p.poll() is not None:
            log.warning("standby of %s (pid %d) exited with %s: another in %.0f s", c.name, sb.p.pid,
                        sb.p.returncode, BACKOFF_S[1])
            sb.close()
            c.standby, c.standby_due = None, now + BACKOFF_S[1]
    elif c.standby_due is not None and now >= c.standby_due and c.exited() is None:
        c.standby = Standby(c.name, c.argv)
        log.info("started a standby of %s (pid %d)", c.name, c.standby.p.pid)


def supervise(children: list[Child], stop: session.Stop, poll_s: float = POLL_S) -> int:
    """Restart every child that exits (in an instant with its standby if it has one ready or starting,
    else after its back-off), until stop is set; the exit code of `up` (2: a child refused its settings at
    its first start, which no restart can fix)."""
    last_status = time.monotonic()
    while not stop.wait(poll_s):
        now = time.monotonic()
        for c in children:
            code = c.exited()
            if code is not None and c.due is None:
                ran = now - c.started
                if code == 2 and c.restarts == 0 and ran < STABLE_S:
                    log.error("%s (pid %d) refused its options or settings (exit 2): stopping", c.name, c.p.pid)
                    return 2
                if ran >= STABLE_S:
                    c.backoff = BACKOFF_S[0]
                wait, c.backoff = c.backoff, min(c.backoff * 2, BACKOFF_S[1])
                if c.standby is not None and c.standby.p.poll() is None:
                    ready = "ready" if c.standby.ready else "still starting"
                    dead = c.p.pid
                    c.p, c.started, c.standby = c.standby.go(), now, None
                    c.standby_due = now + max(wait, STANDBY_DELAY_S)
                    c.restarts += 1
                    log.warning("%s (pid %d) exited with %s after %.1f s: its standby (pid %d, %s) takes over, "
                                "restart %d; %s", c.name, dead, code, ran, c.p.pid, ready, c.restarts,
                                restarts_line(children))
                    continue
                c.due = now + wait
                log.warning("%s (pid %d) exited with %s after %.1f s: restarting in %.1f s", c.name, c.p.pid, code,
                            ran, wait)
            if c.due is not None and now >= c.due and not stop.is_set():
                c.start()
                c.restarts += 1
                log.info("restarted %s (pid %d), restart %d; %s", c.name, c.p.pid, c.restarts,
                         restarts_line(children))
            if not stop.is_set():
                _tend_standby(c, now)
        if now - last_status >= STATUS_S:
            last_status = now
            log.info("%d children running; %s", sum(c.exited() is None for c in children), restarts_line(children))
    return 0


def run(args: argparse.Namespace) -> int:
    if args.workers < 1:
        print("vergence up: --workers must be at least 1", file=sys.stderr)
        return 2
    settings = load(args.config)
    rig = args.rig or settings.rig
    if accepts(args.listen):
        print(f"vergence up: {args.listen} is already in use (another `vergence up` or router?): stop it, or "
              "give this one another port with --listen", file=sys.stderr)
        return 2
    stop = session.Stop()
    children: list[Child] = []
    code = 0
    try:
        source = args.source or settings.capture.source
        # (no capture standby with cameras, which one process holds, nor with ROS 2 topics, which it would decode)
        held = source.startswith(("camera", "ros2"))
        standby = set() if args.no_standby else {"reducer"} | (set() if held else {"capture"})
        for name, argv in commands(args, rig):
            if stop.is_set():
                break
            children.append(Child(name, argv, standby=name in standby))
            children[-1].start()
            log.info("started %s (pid %d): %s", name, children[-1].p.pid, " ".join(argv[3:]))
            if name == "router":
                try:
                    wait_listening(args.listen, ROUTER_START_S, children[-1].p)
                except RuntimeError:
                    log.error("the router did not start (exit %s): nothing else started", children[-1].p.poll())
                    return 1
                except TimeoutError:  # a slow machine: the others keep trying to connect until it listens
                    log.warning("the router does not listen on %s after %.0f s yet", args.listen, ROUTER_START_S)
        code = supervise(children, stop)
    finally:
        stop_all(children)
        if children:
            log.info("stopped; %s", restarts_line(children))
    return code
