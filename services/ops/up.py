"""`vergence up [--workers N] [--source SPEC] [--driver sim] [--listen ENDPOINT] [--ros2]`: the whole pipeline here.

Starts, as child processes: a Zenoh router listening on ENDPOINT (default tcp/127.0.0.1:7447), the actuator,
N workers, the reducer and the capture. These are Zenoh peers: each connects to the router, learns the others
from it and links to them directly on 127.0.0.1, so a frame crosses one link per stage and the router carries
no data between them (it serves the clients: `vergence monitor`, workers on other nodes). With no arguments it
runs the simulated rig.

Each child and standby is forked from up, which has loaded once what they load at their start (numpy, numba and the
kernels, OpenCV, zenoh): services/ops/launch.py, Proc(fork=True); services/runtime/warm.py, preload.

Supervised: a child that exits (the router too) is started again after a back-off ([supervise] restart_s, 0.2 s,
doubled at each quick death up to restart_max_s, 5 s; back to restart_s once it has run 10 s), with one log line
per restart and the counts; the reducer and the capture, slow to start, each have a standby (a second process that
has imported and warmed up and waits in session.open_session) that takes over the moment its child dies. A child
that exits with 2 at its first start (bad options or settings) stops everything instead.

Liveness by heartbeat, not by exit (issue #29): each child and standby beats on a pipe of its own from a
thread that its work cannot starve (services/runtime/heartbeat.py). One silent for longer than [supervise]
heartbeat_s (1.5 s; start_grace_s, 30 s, for its first beat) is stopped or hung: up SIGKILLs its process
group and handles it as an exit (its standby takes over, or it restarts), the log line saying why. A busy
child keeps beating (the thread runs through a compile or a heavy frame); a SIGSTOPped, frozen or deadlocked
one does not (a loop that has not turned for stall_s, 10 s, stops the beats).

SIGINT (Ctrl-C) or SIGTERM ends the supervision and stops the standbys, then the children in order (capture
first, router last), each with SIGINT, then SIGTERM and SIGKILL after grace times (services/ops/launch.py);
children also get SIGTERM if `up` itself dies (Linux parent-death signal), so nothing is left behind.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import signal
import sys
import time

from vergence.wire import keys
from vergence.config import Settings, SuperviseSettings, load
from vergence.motors import DRIVERS, check_driver
from vergence.io.sources import SourceError, check_source, motor_faults

from services.runtime import heartbeat, session, wake, warm
from services.runtime.args import number, whole
from services.ops.launch import GRACE_S, Proc, accepts, vergence, wait_listening

log = logging.getLogger("vergence.up")
POLL_S = 0.05  # how often dead children are looked for
STABLE_S = 10.0  # a child that ran this long gets the first back-off again ([supervise] restart_s)
STATUS_S = 60.0  # a line with the restart counts this often
ROUTER_START_S = 10.0  # the router has this long to listen before anything else starts
STANDBY_DELAY_S = 1.0  # a standby is started this long after its child (not to slow the child's own start)
MAX_WORKERS = 64  # --workers: more than this many on one machine is a typing error


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workers", "-n", type=whole(1, MAX_WORKERS), default=2,
                   help=f"number of worker processes, 1 to {MAX_WORKERS} (default 2)")
    p.add_argument("--source", default=None, metavar="SPEC", help="capture source (default: settings, sim)")
    p.add_argument("--driver", choices=DRIVERS, default=None,
                   help=f"actuator driver: {', '.join(DRIVERS)} (default: settings, sim)")
    p.add_argument("--port", default=None, metavar="URL",
                   help="actuator serial port (the real drivers: dynamixel, line; ros2: its controller)")
    p.add_argument("--rate", type=number(0, 1000, note="0: as fast as possible"), default=None, metavar="HZ",
                   help="capture rate, 0 to 1000, 0: as fast as the source (default: settings, 30)")
    p.add_argument("--listen", "-l", default=session.DEFAULT_ROUTER, metavar="ENDPOINT",
                   help=f"the embedded router's endpoint, the one every child connects to (default "
                        f"{session.DEFAULT_ROUTER})")
    p.add_argument("--no-actuator", action="store_true", help="do not start the actuator (a real one runs elsewhere)")
    p.add_argument("--rig", default=None, help="rig name, the key prefix vergence/<rig>/ (default: head)")
    p.add_argument("--config", metavar="FILE", help="vergence settings (TOML), passed to every child")
    p.add_argument("--ros2", action="store_true", help="start `vergence ros2` too: the rig's topics as a ROS 2 node "
                                                        "(the [ros2] extra; docs/ROS2.md)")
    p.add_argument("--no-standby", action="store_true",
                   help="no standby reducer and capture (each a second process, ready to take over at once if "
                        "the first dies; the capture has none with cameras, which one process holds)")


def commands(args: argparse.Namespace, rig: str, lies: str = "") -> list[tuple[str, list[str]]]:
    """(name, argv) of every child, in start order: router, actuator, workers, reducer, capture; lies: the sim
    source's motor-side ones (vergence.io.sources.motor_faults), the sim actuator's --faults."""
    base = vergence()
    common = ["--mode", "peer", "--connect", args.listen, "--listen", "tcp/127.0.0.1:0", "--rig", rig]
    common += ["--config", args.config] if args.config else []
    out = [("router", base + ["router", "--listen", args.listen])]
    if not args.no_actuator:
        act = base + ["actuator"] + common
        if args.driver:
            act += ["--driver", args.driver]
        act += ["--port", args.port] if args.port else []
        out.append(("actuator", act + (["--faults", lies] if lies else [])))
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


class Heartbeat:
    """up's end of a child's heartbeat pipe (services/runtime/heartbeat.py): env, fds for its start, its last beat."""

    def __init__(self, sup: SuperviseSettings):
        self.sup = sup
        self.r, self._w = os.pipe()
        os.set_blocking(self.r, False)
        self.env = {heartbeat.ENV: f"{self._w},{sup.stall_s:g}"}
        self.fds = (self._w,)
        self.started = time.monotonic()
        self.last: float | None = None  # time.monotonic() of the latest beat read

    def spawned(self) -> None:
        """The child has its copy of the write end: close up's (its EOF: the child's exit); its start grace begins."""
        os.close(self._w)
        self._w = -1
        self.started = time.monotonic()

    def poll(self, now: float) -> None:
        """Read the beats that came (every byte there: one read can be short)."""
        while self.r >= 0:
            try:
                got = os.read(self.r, 4096)
            except BlockingIOError:
                return
            if not got:  # end of file: the child exited (up sees it by its exit)
                return
            self.last = now

    def silent(self, now: float) -> float | None:
        """How long it has not beaten, when longer than it may (heartbeat_s; before its first beat,
        start_grace_s); None while it beats."""
        sup = self.sup
        since, limit = (self.started, sup.start_grace_s) if self.last is None else (self.last, sup.heartbeat_s)
        return now - since if now - since > limit else None

    def close(self) -> None:
        for fd in (self.r, self._w):
            if fd >= 0:
                os.close(fd)
        self.r = self._w = -1


def spawn(name: str, argv: list[str], sup: SuperviseSettings, env: dict | None = None,
          pass_fds: tuple[int, ...] = ()) -> tuple[Proc, Heartbeat]:
    """A child (or standby) of up, dying with it, with a heartbeat pipe."""
    hb = Heartbeat(sup)
    try:
        p = Proc(name, argv, env=dict(os.environ if env is None else env, **hb.env), die_with_parent=True,
                 pass_fds=pass_fds + hb.fds, fork=argv[:3] == vergence())  # (tests give other commands)
    except BaseException:
        hb.close()
        raise
    hb.spawned()
    return p, hb


def kill_hung(p: Proc, hb: Heartbeat, now: float, what: str) -> str | None:
    """SIGKILL p's process group (nothing it started outlives it) if its heartbeat stopped; reaped. Why, or None
    while it beats."""
    hb.poll(now)
    silent = hb.silent(now)
    if silent is None or p.poll() is not None:
        return None
    why = (f"no heartbeat for {silent:.1f} s (stopped or hung)" if hb.last is not None else
           f"no first heartbeat within {silent:.1f} s of its start")
    log.warning("%s (pid %d): %s: SIGKILL", what, p.pid, why)
    p.signal_group(signal.SIGKILL)
    with contextlib.suppress(TimeoutError):
        p.wait(2.0)
    return why


class Standby:
    """A second copy of a child, started ahead: it has imported and warmed up, and waits in
    session.open_session for a byte on its pipe (then it is the child) or its end (then it leaves)."""

    def __init__(self, name: str, argv: list[str], sup: SuperviseSettings):
        self.name = name  # the child's
        ready_r, ready_w = os.pipe()
        go_r, go_w = os.pipe()
        env = dict(os.environ, **{session.STANDBY_ENV: f"{ready_w},{go_r}"})
        self.p, self.hb = spawn(f"the standby of {name}", argv, sup, env=env, pass_fds=(ready_w, go_r))
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
        """Let it open its session: from now on it is the child (its heartbeat, self.hb, the child's)."""
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

    def __init__(self, name: str, argv: list[str], standby: bool = False, sup: SuperviseSettings | None = None):
        self.name, self.argv = name, argv
        self.sup = sup or SuperviseSettings()
        self.p: Proc | None = None
        self.hb: Heartbeat | None = None
        self.why = ""  # why up killed the running process (its heartbeat stopped), for the exit's log line
        self.started = 0.0  # time.monotonic() of the latest start
        self.restarts = 0
        self.backoff = self.sup.restart_s
        self.due: float | None = None  # when a dead child is started again
        self.standby: Standby | None = None
        self.standby_due: float | None = 0.0 if standby else None  # when a standby is started (None: it has none)

    def start(self) -> None:
        if self.hb is not None:
            self.hb.close()
        self.p, self.hb = spawn(self.name, self.argv, self.sup)
        self.started, self.due, self.why = self.hb.started, None, ""  # (the clock its start grace counts on)
        if self.standby_due is not None:
            self.standby_due = max(self.standby_due, self.started + STANDBY_DELAY_S)

    def exited(self) -> int | None:
        return None if self.p is None else self.p.poll()

    def take_over(self, now: float) -> int:
        """Its standby becomes the child (with its heartbeat); the pid of the dead one."""
        dead = self.p.pid
        if self.hb is not None:
            self.hb.close()
        self.hb = self.standby.hb
        self.p, self.started, self.standby, self.why = self.standby.go(), now, None, ""
        return dead


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
        if c.hb is not None:
            c.hb.close()


def restarts_line(children: list[Child]) -> str:
    """"restarts: reducer 1, router 2" (or "no restarts")."""
    done = [f"{c.name} {c.restarts}" for c in children if c.restarts]
    return "restarts: " + ", ".join(done) if done else "no restarts"


def _tend_standby(c: Child, now: float) -> None:
    """Start c's standby when due, note when it is ready, replace it if it died."""
    sb = c.standby
    if sb is not None:
        kill_hung(sb.p, sb.hb, now, f"standby of {c.name}")
        if sb.poll_ready():
            log.info("standby of %s (pid %d) ready", c.name, sb.p.pid)
        elif sb.p.poll() is not None:
            log.warning("standby of %s (pid %d) exited with %s: another in %.0f s", c.name, sb.p.pid,
                        sb.p.returncode, c.sup.restart_max_s)
            sb.close()
            sb.hb.close()
            c.standby, c.standby_due = None, now + c.sup.restart_max_s
    elif c.standby_due is not None and now >= c.standby_due and c.exited() is None:
        c.standby = Standby(c.name, c.argv, c.sup)
        log.info("started a standby of %s (pid %d)", c.name, c.standby.p.pid)


def _exited(c: Child, code: int, now: float, children: list[Child]) -> bool:
    """Handle the exit of c (code): its standby takes over, or a restart is due after its back-off. False: it
    refused its settings at its first start (exit 2), which no restart fixes."""
    ran = now - c.started
    if code == 2 and c.restarts == 0 and ran < STABLE_S:
        log.error("%s (pid %d) refused its options or settings (exit 2): stopping", c.name, c.p.pid)
        return False
    if ran >= STABLE_S:
        c.backoff = c.sup.restart_s
    wait, c.backoff = c.backoff, min(c.backoff * 2, c.sup.restart_max_s)
    how = f"was killed by up ({c.why})" if c.why else f"exited with {code}"
    if c.standby is not None and c.standby.p.poll() is None:
        ready = "ready" if c.standby.ready else "still starting"
        dead = c.take_over(now)
        c.standby_due = now + max(wait, STANDBY_DELAY_S)
        c.restarts += 1
        log.warning("%s (pid %d) %s after %.1f s: its standby (pid %d, %s) takes over, restart %d; %s", c.name,
                    dead, how, ran, c.p.pid, ready, c.restarts, restarts_line(children))
        return True
    c.due = now + wait
    log.warning("%s (pid %d) %s after %.1f s: restarting in %.1f s", c.name, c.p.pid, how, ran, wait)
    return True


def supervise(children: list[Child], stop: session.Stop, poll_s: float = POLL_S) -> int:
    """Restart every child that exits (in an instant with its standby if it has one ready or starting,
    else after its back-off), or whose heartbeat stopped (SIGKILLed first), until stop is set; the exit
    code of `up` (2: a child refused its settings at its first start, which no restart can fix)."""
    last_status = time.monotonic()
    while not stop.wait(poll_s):
        now = time.monotonic()
        for c in children:
            if c.p is not None and c.due is None and c.hb is not None and not c.why:  # once: dying can take time
                c.why = kill_hung(c.p, c.hb, now, c.name) or ""
            code = c.exited()
            if code is not None and c.due is None and not _exited(c, code, now, children):
                return 2
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


def check(args: argparse.Namespace, settings: Settings) -> str | None:
    """What the children would refuse, found before one starts (a refusal then stops everything anyway, after
    every child started): the settings with the options over them, the rig's name, the source, the driver and
    its port, and an option that does not apply. The reason, or None."""
    if args.no_actuator and (args.driver or args.port):
        return f"--{'driver' if args.driver else 'port'} applies to the actuator, which --no-actuator does not start"
    try:
        keys.prefix(args.rig or settings.rig)
    except ValueError as e:
        return f"--rig: {e}"
    if not args.no_actuator:
        a = settings.actuator
        try:
            check_driver(args.driver or a.driver, args.port or a.port, args.port)
        except ValueError as e:
            return str(e)
    try:
        check_source(args.source or settings.capture.source)
        lies = motor_faults(args.source or settings.capture.source)
    except SourceError as e:
        return f"--source: {e}" if args.source else f"[capture] source: {e}"
    if lies and (args.no_actuator or (args.driver or settings.actuator.driver) != "sim"):
        return f"the source's {lies} makes the sim actuator lie: run it (--driver sim, no --no-actuator)"
    return None


def compile_first(stop: session.Stop) -> bool:
    """On a first start (numba's cache has no kernels: a fresh install, or after an upgrade), say so and compile
    them once, in one process (`python -m services.runtime.warm`), before any child starts: the children then
    load them in a fraction of a second instead of all compiling the same functions at once on the same cores.
    False when the compile failed or a SIGINT/SIGTERM came first."""
    if warm.compiled():
        return True
    log.info("first start on this machine: compiling the kernels once (numba, about 10-20 s; cached, so later "
             "starts take a few seconds) ...")
    t0 = time.monotonic()
    # a child of up as the others are (its own process group, gone with up; its errors on up's stderr)
    p = Proc("compile", [sys.executable, "-m", "services.runtime.warm"], die_with_parent=True)
    while p.alive() and not stop.is_set():
        stop.wait(0.1)
    if p.alive():
        p.stop(log=log)
        return False
    if p.returncode != 0:
        log.error("compiling the kernels failed (exit %d, its error above)", p.returncode)
        return False
    log.info("compiled in %.1f s; starting the pipeline", time.monotonic() - t0)
    return True


def run(args: argparse.Namespace) -> int:
    settings = load(args.config)
    wake.check()  # a bad VERGENCE_CPU_WAKE_US stops here, as a bad setting (exit 2); a device not writable: said once
    rig = args.rig or settings.rig
    why = check(args, settings)
    if why is not None:
        print(f"vergence up: {why}", file=sys.stderr)
        return 2
    if accepts(args.listen):
        print(f"vergence up: {args.listen} is already in use (another `vergence up` or router?): stop it, or "
              "give this one another port with --listen", file=sys.stderr)
        return 2
    stop = session.Stop()
    if not compile_first(stop):
        return 130 if stop.is_set() else 1
    warm.preload(settings)  # what every child loads, once: they are forked from up with it
    children: list[Child] = []
    code = 0
    try:
        source = args.source or settings.capture.source
        # (no capture standby with cameras, which one process holds, nor with ROS 2 topics, which it would decode)
        held = source.startswith(("camera", "ros2"))
        standby = set() if args.no_standby else {"reducer"} | (set() if held else {"capture"})
        for name, argv in commands(args, rig, motor_faults(source)):
            if stop.is_set():
                break
            children.append(Child(name, argv, standby=name in standby, sup=settings.supervise))
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
