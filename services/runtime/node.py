"""The life every process shares (the pipeline's, the observers', the clients', the bridge), so that each module
is mostly its job:

    with Node("worker", rig, conf, stop, name=name, log=log, fields=lambda: {"busy_s": busy()}) as node:
        sub = node.ring(keys.frame(rig), 1)     # a RingChannel subscriber, woken at exit
        pub = node.publisher(keys.correlation(rig, node.ident), express=True)
        node.thread(loop, name="worker-loop")   # the work, in a thread joined at exit
        node.ready()                            # the liveliness token: the others may count on us from now
        node.run_status()                       # a status every STATUS_S until stop (or the thread ends)

Entering opens the session (session.open_session: a SIGINT/SIGTERM before a router answers exits cleanly;
past `timeout` seconds without one, session.NoRouter, which `vergence` prints as one line, exit 1: every
client passes its wait) and declares the status publisher. The loop's roles (capture, worker, reducer, actuator) also
ask the kernel for short wake-ups while the block runs (services/runtime/wake.py: a PM QoS request). The id is
session.alive_key's (<name or host>-<pid>); the token is vergence/<rig>/alive/<role>/<id>; the status, JSON of
health.Health.status() plus fields(), goes out on vergence/<rig>/status/<role>/<id> every STATUS_S (run_status,
or tick() from the service's own loop), and PROMPT_S after a bad message was counted (Health.news): a forged or
broken message shows in the status at once, not up to a second later (at most 1/PROMPT_S statuses a second, whatever
arrives).

Leaving, however the block ends: the token goes first (nobody plans on us any more), then the stop is set
and each ring woken by a local empty sample, the threads are joined, the subscribers undeclared (no callback
runs while the session closes), the last status goes out with final_fields() (default: fields()) and
"exiting": true, one log line gives the counters (at debug level for a quiet node: a client), and the session
closes.
"""

from __future__ import annotations

import json
import logging
import threading
import time

import zenoh

from vergence.wire import keys

from services.runtime import heartbeat, session, wake
from services.runtime.health import Health

STATUS_S = 1.0
PROMPT_S = 0.1  # a status with a new bad count goes out this soon after the last one (not STATUS_S)
JOIN_S = 5.0  # the longest wait for each thread at exit


class Node:
    def __init__(self, role: str, rig: str, conf: zenoh.Config, stop: session.Stop, *, name: str | None = None,
                 log: logging.Logger | None = None, fields=None, final_fields=None, timeout: float | None = None,
                 quiet: bool = False):
        self.role, self.rig, self.conf, self.stop = role, rig, conf, stop
        self.timeout = timeout  # the longest wait for a router (None: as long as it takes; a client's --wait)
        self.quiet = quiet  # the exit's log line at debug level (a client's output is what it prints)
        self.alive = session.alive_key(rig, role, name)
        self.ident = keys.parse(self.alive).ident
        self.log = log or logging.getLogger(f"vergence.{role}")
        self.health = Health(role, self.ident, self.log)
        self.fields = fields or dict
        self.final_fields = final_fields or self.fields
        self.session: zenoh.Session | None = None
        self._subs: list = []
        self._wake: list[str] = []
        self._threads: list[threading.Thread] = []
        self._token = None
        self._cpu = wake.Hold()  # the loop's roles: short wake-ups asked of the kernel while the block runs
        self._next_status = self._last_status = 0.0

    # -- the block --------------------------------------------------------------------------------------------

    def __enter__(self) -> Node:
        if self.role in wake.ROLES:
            self._cpu = wake.Hold.open()
        try:
            self.session = session.open_session(self.conf, timeout=self.timeout)
        except BaseException:
            self._cpu.close()
            raise
        try:
            self._status = self.session.declare_publisher(keys.status(self.rig, self.role, self.ident))
        except BaseException:
            self.session.close()
            self._cpu.close()
            raise
        self._last_status = time.monotonic()
        self._next_status = self._last_status + STATUS_S
        return self

    def __exit__(self, *exc) -> None:
        s = self.session
        try:
            if self._token is not None:
                self._token.undeclare()
                self._token = None
            self.stop.set()
            for key in self._wake:  # a local, empty sample on each ring's own subscription
                s.put(key, b"", allowed_destination=zenoh.Locality.SESSION_LOCAL)
            for th in self._threads:
                th.join(JOIN_S)
            for sub in self._subs:
                sub.undeclare()
            final = self.final_fields()
            self._status.put(json.dumps(self.health.status(**final, exiting=True)))
            self.log.log(logging.DEBUG if self.quiet else logging.INFO, "%s %s exits: %s bad %s %s", self.role,
                         self.ident, self.health.counters, self.health.bad, final)
        finally:
            s.close()
            self._cpu.close()

    # -- declarations -----------------------------------------------------------------------------------------

    def publisher(self, key: str, **kw) -> zenoh.Publisher:
        return self.session.declare_publisher(key, **kw)

    def subscriber(self, key: str, handler, **kw) -> zenoh.Subscriber:
        """A subscriber, undeclared at exit (before the session closes: no callback runs while it does)."""
        sub = self.session.declare_subscriber(key, handler, **kw)
        self._subs.append(sub)
        return sub

    def liveliness_subscriber(self, key: str, handler, history: bool = False) -> zenoh.Subscriber:
        sub = self.session.liveliness().declare_subscriber(key, handler, history=history)
        self._subs.append(sub)
        return sub

    def ring(self, key: str, size: int, wake: str | None = None) -> zenoh.Subscriber:
        """A subscriber keeping the newest `size` samples (zenoh.handlers.RingChannel), for samples(); at
        exit a local empty sample on `wake` (default: key; a key the subscription matches) ends samples()."""
        sub = self.subscriber(key, zenoh.handlers.RingChannel(size))
        self._wake.append(wake or key)
        return sub

    def samples(self, sub: zenoh.Subscriber):
        """The samples of a ring, as they come, until the stop is set."""
        while True:
            sample = sub.recv()
            if self.stop.is_set():
                return
            yield sample

    def thread(self, target, *args, name: str) -> threading.Thread:
        """Run target(*args) in a (daemon) thread now; joined at exit, after the stop and the rings' wake."""
        th = threading.Thread(target=target, args=args, name=name, daemon=True)
        self._threads.append(th)
        th.start()
        return th

    def ready(self) -> None:
        """Declare the liveliness token vergence/<rig>/alive/<role>/<id>: call it once the subscriptions are
        up and the work can start (the capture plans shards from the workers' tokens)."""
        self._token = self.session.liveliness().declare_token(self.alive)

    # -- status -----------------------------------------------------------------------------------------------

    def status(self, now: float | None = None) -> None:
        """Publish the status now: health.status() with fields(); the loop that calls it turned (heartbeat)."""
        heartbeat.progress()
        self._last_status = time.monotonic() if now is None else now
        self._next_status = self._last_status + STATUS_S
        self._status.put(json.dumps(self.health.status(**self.fields())))

    def tick(self, now: float | None = None) -> None:
        """Publish the status if one is due: STATUS_S after the last, or PROMPT_S after it with a bad message counted
        since (for a service that runs its own loop)."""
        now = time.monotonic() if now is None else now
        if now >= self._next_status or (self.health.news and now >= self._last_status + PROMPT_S):
            self.status(now)

    def run_status(self) -> None:
        """Publish the status as tick() says until the stop is set or a thread of node.thread() ends."""
        while not self.stop.wait(PROMPT_S) and all(th.is_alive() for th in self._threads):
            self.tick()
