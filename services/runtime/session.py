"""The one Zenoh session builder and the shared options of every process.

Every process takes the options of zenoh-python's examples (--mode, --connect, --listen, --zenoh-config),
plus --rig (the key prefix) and --config (our TOML settings). Clients connect to the router at
tcp/127.0.0.1:7447 unless told otherwise; multicast scouting is off (explicit endpoints only), the lease
is short (1 s) so that a frozen process is noticed, and shared memory is off (it grew every subscriber's
memory by each publisher's pool: see zenoh_config).
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import os
import signal
import threading
import time

import zenoh

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
LEASE_MS = 1000
STANDBY_ENV = "VERGENCE_STANDBY"  # see open_session and services/ops/up.py
SAY_WAITING_S = 1.0  # open_session says why nothing happens after this long without a router ...
SAY_QUIET_S = 10.0  # ... unless it gives up within this long: a short wait ends with its one line (NoRouter)
CLIENT_WAIT_S = 5.0  # a client's default wait for a router (record, replay, monitor, view: --wait)
# zenoh's own threads (its ZENOH_RUNTIME variable, read when the first session opens): one thread reads the links
# and runs their tasks, and the links' set-up runs on it too, where zenoh's default has two readers behind a separate
# I/O thread: a message then reaches a subscriber without a hand-over between zenoh's threads. A put to a Python
# thread of another process and back: 330 -> 228 us (p50, 300 B, 4 ms apart); `vergence bench pipeline` 250 Hz p50
# 2.08-2.27 -> 1.88-1.95 ms (docs/PERFORMANCE.md). Sending keeps its own thread (tx), so a Python callback waiting for
# the interpreter never holds up a put. A ZENOH_RUNTIME of the user's own is left as it is; children inherit it.
ZENOH_RUNTIME = "(rx: (worker_threads: 1), net: (handover: rx), acc: (handover: rx))"
os.environ.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)

log = logging.getLogger("vergence.session")
_stops: list[threading.Event] = []  # every Stop's event: open_session gives up when one is set


def add_options(p: argparse.ArgumentParser, mode: str = "client") -> None:
    g = p.add_argument_group("zenoh")
    g.add_argument("--mode", "-m", choices=["peer", "client", "router"], default=mode,
                   help=f"zenoh session mode (default {mode})")
    g.add_argument("--connect", "-e", action="append", default=None, metavar="ENDPOINT",
                   help=f"endpoint to connect to, repeatable (default {DEFAULT_ROUTER} for clients)")
    g.add_argument("--listen", "-l", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint to listen on, repeatable")
    g.add_argument("--zenoh-config", metavar="FILE", help="a zenoh JSON5 config file, applied first")
    p.add_argument("--rig", default=None, help="rig name, the key prefix vergence/<rig>/ (default: head)")
    p.add_argument("--config", metavar="FILE", help="vergence settings (TOML)")


def add_wait(p: argparse.ArgumentParser, default: float = CLIENT_WAIT_S) -> None:
    """--wait S: how long a client waits for a router before it gives up (NoRouter: one line, exit 1)."""
    from services.runtime.args import number  # here: the router, which has no --wait, never imports vergence

    p.add_argument("--wait", type=number(0, 3600, lo_open=True), default=default, metavar="S",
                   help=f"give up (exit 1) when no Zenoh router answers within S seconds (default {default:g})")


class NoRouter(ConnectionError):
    """No Zenoh router (or peer) answered within a client's wait; `vergence` prints it as one line, exit 1."""


def zenoh_config(mode: str = "client", connect: list[str] | None = None, listen: list[str] | None = None,
                 config_file: str | None = None) -> zenoh.Config:
    conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    if connect is None and mode == "client" and not config_file:
        connect = [DEFAULT_ROUTER]
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if os.environ.get("VERGENCE_ZENOH_SHM") != "1" and not (config_file and _sets_shared_memory(config_file)):
        # no shared memory: with it (zenoh's default since 1.x), every subscriber kept the 16 MB pool of each
        # publisher it ever heard from mapped, so the workers and the reducer grew ~19 MB per capture restart
        # (tests/scenarios/test_supervise.py); frames are small enough that tcp on 127.0.0.1 costs little (README).
        # VERGENCE_ZENOH_SHM=1 leaves zenoh's default (to measure it), as does a config file that sets it.
        conf.insert_json5("transport/shared_memory/enabled", "false")
    if not config_file:
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("transport/link/tx/lease", str(LEASE_MS))
        conf.insert_json5("transport/link/tx/keep_alive", "4")
        if mode in ("client", "peer"):
            # keep trying to reach the router: at start and after it restarts (the peers of `vergence up` too)
            conf.insert_json5("connect/timeout_ms", "-1")
            # retry every 0.1-0.5 s (zenoh's default backs off to seconds): back within 0.5 s of a router
            # restart however long it was down (tests/deploy/test_restart.py, tests/scenarios/test_supervise.py)
            conf.insert_json5("connect/retry",
                              '{"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2}')
    return conf


def _sets_shared_memory(config_file: str) -> bool:
    """Whether a zenoh config file says anything about shared memory (then it decides)."""
    try:
        with open(config_file, encoding="utf-8") as fh:
            return "shared_memory" in fh.read()
    except OSError:
        return False


def config_from_args(args: argparse.Namespace) -> zenoh.Config:
    return zenoh_config(args.mode, args.connect, args.listen, args.zenoh_config)


def open_session(conf: zenoh.Config, timeout: float | None = None) -> zenoh.Session:
    """zenoh.open, after moving everything allocated so far out of the garbage collector's reach.

    A service has imported numpy, numba, OpenCV and zenoh and warmed its kernels by now: hundreds of
    thousands of objects that live as long as the process. Left to the collector, its full passes over them
    took half the reducer's CPU at 250 frames/s and stalled a message for tens of ms at a time; frozen, a
    collection only walks what the message loop allocates.

    zenoh.open keeps trying while no router answers, and a main thread blocked in it never runs a signal
    handler: it runs in a thread, and a SIGINT/SIGTERM (a Stop) meanwhile ends the process cleanly
    (SystemExit 0, nothing opened); after SAY_WAITING_S it logs once which endpoints it waits for (unless
    `timeout` is at most SAY_QUIET_S: then the NoRouter is the one line); past `timeout` seconds it raises
    NoRouter (a ConnectionError). A peer's zenoh.open returns at once, router or not: with a timeout, a peer
    session must also see a router or a peer within it (else closed, NoRouter), as a client's does.

    A standby of `vergence up` (STANDBY_ENV set) waits here first, everything before its session done, until
    up starts it in place of a dead child (or leaves, if up closes the pipe)."""
    _standby()
    gc.collect()
    gc.freeze()
    box: list = []

    def opener():
        try:
            box.append(zenoh.open(conf))
        except Exception as e:  # a bad endpoint or config: raised in the caller's thread
            box.append(e)

    t = threading.Thread(target=opener, name="zenoh-open", daemon=True)
    t0 = time.monotonic()
    said = False
    t.start()
    while t.is_alive():
        t.join(0.05)
        if any(e.is_set() for e in _stops):
            raise SystemExit(0)  # stopped before a router answered: nothing to close
        waited = time.monotonic() - t0
        if t.is_alive() and not said and waited >= SAY_WAITING_S and (timeout is None or timeout > SAY_QUIET_S):
            said = True
            log.warning("no Zenoh router or peer answers at %s yet; still trying (Ctrl-C stops)", _endpoints(conf))
        if t.is_alive() and timeout is not None and waited >= timeout:
            raise _no_router(conf, timeout)
    if isinstance(box[0], Exception):
        raise box[0]
    s = box[0]
    if timeout is not None and _mode(conf) == "peer":
        while not (s.info.routers_zid() or s.info.peers_zid()):
            if any(e.is_set() for e in _stops):
                s.close()
                raise SystemExit(0)
            if time.monotonic() - t0 >= timeout:
                s.close()
                raise _no_router(conf, timeout)
            time.sleep(0.05)
    return s


def _no_router(conf: zenoh.Config, timeout: float) -> NoRouter:
    return NoRouter(f"no Zenoh router or peer answered at {_endpoints(conf)} within {timeout:g} s; start one with "
                    "`vergence up` (or `vergence router`), or pass --connect ENDPOINT")


def _mode(conf: zenoh.Config) -> str:
    try:
        return json.loads(conf.get_json("mode"))
    except Exception:  # an odd config file: zenoh's default
        return "peer"


def _endpoints(conf: zenoh.Config) -> str:
    try:
        return ", ".join(json.loads(conf.get_json("connect/endpoints"))) or "no endpoint"
    except Exception:  # an odd config file: say what we can
        return "the configured endpoints"


def _standby() -> None:
    """In a standby (STANDBY_ENV = "READY_FD,GO_FD", set by `vergence up`): write a byte to READY_FD (imports
    and warm-up done), then block until a byte arrives on GO_FD; end of file (up stopped or died): exit 0."""
    spec = os.environ.pop(STANDBY_ENV, None)
    if not spec:
        return
    ready, go = (int(fd) for fd in spec.split(","))
    try:
        os.write(ready, b"r")
        os.close(ready)
    except OSError:  # up is gone
        raise SystemExit(0) from None
    with os.fdopen(go, "rb", buffering=0) as fh:
        if not fh.read(1):
            raise SystemExit(0)


def alive_key(rig: str, role: str, name: str | None = None) -> str:
    """vergence/<rig>/alive/<role>/<id>; id defaults to <hostname>-<pid> and always ends in -<pid>."""
    if name is None:
        name = f"{os.uname().nodename}-{os.getpid()}"
    elif not name.endswith(f"-{os.getpid()}"):
        name = f"{name}-{os.getpid()}"
    from vergence.wire import keys  # here, not at the top: `vergence router` never pays for importing vergence

    return keys.alive(rig, role, name)


class Stop:
    """A threading.Event set by SIGINT/SIGTERM: loops poll it, so every process exits cleanly."""

    def __init__(self, install: bool = True):
        self.event = threading.Event()
        if install:  # the process's own: open_session gives up when it is set
            _stops.append(self.event)
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, self._handler)

    def _handler(self, signum, frame):
        # Not self.event.set() here: a handler runs between two bytecodes of the main thread, which may be holding the
        # event's lock (inside Event.wait, or a first handler's Event.set when a second signal comes: Ctrl-C twice, a
        # `timeout` forwarding its signal), and that Lock is not reentrant: the process hung for good. A thread sets
        # it, once the main thread lets go.
        try:
            threading.Thread(target=self.event.set, name="stop", daemon=True).start()
        except RuntimeError:  # no new thread at the interpreter's shutdown: nothing holds the lock any more
            self.event.set()

    def is_set(self) -> bool:
        return self.event.is_set()

    def set(self) -> None:
        self.event.set()

    def wait(self, timeout: float | None = None) -> bool:
        return self.event.wait(timeout)
