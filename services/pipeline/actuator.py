"""`vergence actuator --driver sim|dynamixel|line|ros2 [--port URL] [--id 1] [--baud 57600] [--faults SPEC]`: drive
the slave pan. --faults stall=T0-T1:encoder_noise=DEG makes the sim motor lie (vergence/motors/simulated.py; `vergence
up` passes a sim source's two keys on).

Subscribes to vergence/<rig>/command (messages.Command: pan_rad is the absolute target pan of the slave) and
publishes messages.MotorState on vergence/<rig>/motor_state at [actuator] state_hz and after each command.
The Zenoh callback only keeps the newest command (a flood is coalesced, never queued); one thread runs
vergence.motors.runner.MotorLoop, which owns every decision (safety, watchdog, reconnection). Counters go out as
JSON on vergence/<rig>/status/actuator/<id> every second and at exit: commands (received, a flood's superseded
ones included), applied, refused, clamped, superseded, motor_states (published); a malformed command under
bad.command.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import threading
import time

from vergence.wire import keys
from vergence.config import ConfigError, load
from vergence.motors import DRIVERS, PortError, check_driver, make_driver
from vergence.motors.runner import MotorLoop
from vergence.sim.faults import motor_lies

from services.runtime import heartbeat, session
from services.runtime.args import number, whole
from services.runtime.node import Node

log = logging.getLogger("vergence.actuator")


def configure(p: argparse.ArgumentParser) -> None:
    session.add_options(p)
    p.add_argument("--driver", choices=DRIVERS, default=None,
                   help="motor driver (default: from the settings, else sim)")
    p.add_argument("--port", default=None, metavar="URL",
                   help="serial port or pyserial URL: /dev/ttyUSB0, socket://host:port, loop:// "
                        "(list ports: python -m serial.tools.list_ports -v); ros2: CONTROLLER[:joint=NAME]"
                        "[:mode=forward|trajectory][:joints=A,B][:states=TOPIC] (vergence/motors/ros2.py)")
    p.add_argument("--id", type=whole(0, 252), default=None, help="motor id on the bus (Dynamixel; default 1)")
    p.add_argument("--baud", type=whole(1200, 10_000_000), default=None, help="serial speed (default 57600)")
    p.add_argument("--state-hz", type=number(0, 1000, lo_open=True), default=None, help="motor_state rate (default 50)")
    p.add_argument("--faults", metavar="SPEC", default="",
                   help="the sim motor's lies: stall=T0-T1 (s from the first commanded frame's exposure), "
                        "encoder_noise=DEG (vergence/sim/faults.py)")


class Latest:
    """A one-slot mailbox: the Zenoh callback puts, the motor thread takes; a newer message replaces an
    older one that was not taken yet (counted in `superseded`)."""

    def __init__(self):
        self.cond = threading.Condition()
        self.item = None
        self.superseded = 0

    def put(self, item) -> None:
        with self.cond:
            if self.item is not None:
                self.superseded += 1
            self.item = item
            self.cond.notify()

    def take(self, timeout: float):
        with self.cond:
            if self.item is None:
                self.cond.wait(timeout)
            item, self.item = self.item, None
            return item


class Actuator:
    """The motor loop's side of the process: each command or superseded flood counted in the Node's health
    (commands, applied, refused, clamped; a malformed one under bad.command), each state published and
    counted (motor_states), the status from the motor thread's own loop (serve)."""

    def __init__(self, loop: MotorLoop, node: Node, publisher):
        self.loop, self.node, self.health, self.pub = loop, node, node.health, publisher

    def publish(self, state) -> None:
        self.pub.put(state.to_bytes())
        self.health.count("motor_states")

    def superseded(self, n: int) -> None:
        self.loop.superseded(n)
        self.health.count("commands", n)
        self.health.count("superseded", n)

    def command(self, data: bytes) -> None:
        loop, health = self.loop, self.health
        before = (loop.malformed, loop.safety.ignored, loop.safety.clamped)
        state = loop.command(data)
        health.count("commands")
        if loop.malformed > before[0]:
            health.reject("command", loop.note)
        elif loop.safety.ignored > before[1]:
            health.count("refused")
        else:
            health.count("applied")
            if loop.safety.clamped > before[2]:
                health.count("clamped")
        self.publish(state)

    def fields(self) -> dict:
        return {"motor": self.loop.status, "driver": self.loop.driver.name}


def serve(act: Actuator, inbox: Latest, stop: session.Stop, state_hz: float) -> None:
    """Run the motor loop until stop: commands as they come, a state every 1/state_hz, the status when due."""
    period = 1.0 / state_hz if state_hz > 0 else 0.02
    next_tick = time.monotonic()
    seen = 0
    while not stop.is_set():
        data = inbox.take(max(0.0, min(0.1, next_tick - time.monotonic())))
        if inbox.superseded != seen:
            n, seen = inbox.superseded - seen, inbox.superseded
            act.superseded(n)
        if data is not None:
            act.command(data)
        now = time.monotonic()
        if now >= next_tick:
            heartbeat.progress()  # the motor loop turns (services/runtime/heartbeat.py)
            act.publish(act.loop.tick())
            next_tick = max(next_tick + period, now - period)
        act.node.tick(now)


def main(settings, conf, stop: session.Stop, lies: dict | None = None) -> int:
    a = settings.actuator
    rig = settings.rig
    try:
        driver = make_driver(a.driver, a.motor, a.port, lies)
    except (PortError, ValueError) as e:
        print(f"vergence actuator: {e}", file=sys.stderr)
        return 2
    loop = MotorLoop(driver, a.motor, rig)
    try:
        first = loop.start()
    except PortError as e:
        print(f"vergence actuator: {e}", file=sys.stderr)
        return 2
    acts: list[Actuator] = []
    with Node("actuator", rig, conf, stop, log=log, fields=lambda: acts[0].fields() if acts else {}) as node:
        act = Actuator(loop, node, node.publisher(keys.motor_state(rig)))
        acts.append(act)
        inbox = Latest()
        node.subscriber(keys.command(rig), lambda sample: inbox.put(sample.payload.to_bytes()))
        node.ready()
        log.info("actuator %s on %s: %s", driver.describe(), keys.command(rig), first.status)
        act.publish(first)
        try:
            serve(act, inbox, stop, a.state_hz)
        finally:
            act.publish(loop.stop())
    return 0


def settings_from_args(args: argparse.Namespace):
    st = load(args.config)
    a, m = st.actuator, st.actuator.motor
    m = dataclasses.replace(m, **{k: v for k, v in (("id", args.id), ("baud", args.baud)) if v is not None})
    a = dataclasses.replace(a, motor=m, **{k: v for k, v in (("driver", args.driver), ("port", args.port),
                                                               ("state_hz", args.state_hz)) if v is not None})
    return dataclasses.replace(st, actuator=a, **({"rig": args.rig} if args.rig else {}))


def run(args: argparse.Namespace) -> int:
    try:
        settings = settings_from_args(args)
        check_driver(settings.actuator.driver, settings.actuator.port, args.port)  # --port with sim: refused
        lies = motor_lies(args.faults) if args.faults else None  # (refused for a real driver by make_driver)
    except (ConfigError, ValueError) as e:
        print(f"vergence actuator: {e}", file=sys.stderr)
        return 2
    stop = session.Stop()
    return main(settings, session.config_from_args(args), stop, lies)
