"""The loop's processes ask the kernel for short wake-ups while they run (issue #33): a PM QoS request on
/dev/cpu_dma_latency, the one real-time tools (cyclictest, tuned's latency profiles) hold, which keeps every CPU out
of the idle states slower to leave than the request while the file is open.

Why: every stage of the loop runs after an idle wait (a frame every 4 ms at 250 Hz), and on this project's 2-vCPU
virtual machine a CPU woken from its halt runs the first work cold: a Zenoh put took 21 us after a 4 ms sleep
against 2.7 us with the request held, `vergence.match` 0.75 ms against 0.42 in a loop; `vergence bench pipeline`
at 250 Hz 0.2-0.3 ms less at the p50 with it (docs/PERFORMANCE.md). The cost: an idle CPU polls instead of
sleeping (more power; on a virtual machine the host sees the vCPUs busy). The kernel drops the request when the
process exits, however it exits. The process's timer slack goes to 1 us as well (timer_slack): its sleeps end when
they should.

VERGENCE_CPU_WAKE_US (children inherit it): unset, the request is 0 us (no idle state but polling); a number N,
N us (e.g. 10 on a laptop keeps the shallow states); `off`, nothing is asked. Opening the device needs root or a
udev rule granting it; where it cannot be opened, one log line says so and the process runs as it would without."""

from __future__ import annotations

import ctypes
import logging
import os
import struct
import sys

DEVICE = "/dev/cpu_dma_latency"
PR_SET_TIMERSLACK = 29  # prctl(2): the calling thread's timer slack, ns; threads it starts inherit it
SLACK_NS = 1000
ENV = "VERGENCE_CPU_WAKE_US"
ROLES = ("capture", "worker", "reducer", "actuator")  # the processes on the loop's path
SAID_ENV = "VERGENCE_CPU_WAKE_SAID"  # set by check(): the children of `vergence up` need not say it again

log = logging.getLogger("vergence.wake")


def request_us(value: str | None) -> int | None:
    """The request VERGENCE_CPU_WAKE_US asks for: None (unset) -> 0, "off" -> None (nothing), a whole number of
    microseconds >= 0 -> it; anything else a ConfigError naming the variable (`vergence` prints it, exit 2)."""
    if value is None or value.strip() == "":
        return 0
    if value.strip().lower() == "off":
        return None
    try:
        us = int(value)
    except ValueError:
        us = -1
    if us < 0:
        from vergence.config import ConfigError

        raise ConfigError(f"{ENV}={value!r}: a whole number of microseconds (0: the shortest wake-ups) or 'off'")
    return us


def check() -> None:
    """`vergence up`'s, before its children start: a bad VERGENCE_CPU_WAKE_US stops it (ConfigError, exit 2), and a
    device it cannot open is said once, here, not by each child (they inherit SAID_ENV)."""
    us = request_us(os.environ.get(ENV))
    if us is not None and not os.access(DEVICE, os.W_OK):
        log.info("the CPUs' wake-up latency is not held (%s is not writable here): run as root or let this user "
                 "write it (a udev rule) for faster wake-ups; %s=off stops asking", DEVICE, ENV)
    os.environ[SAID_ENV] = "1"


class Hold:
    """The request, held from open() to close() (or the process's exit). fd: None when nothing is held."""

    def __init__(self, fd: int | None = None):
        self.fd = fd

    @classmethod
    def open(cls, device: str = DEVICE) -> Hold:
        us = request_us(os.environ.get(ENV))
        if us is None:
            return cls()
        timer_slack(SLACK_NS)
        try:
            fd = os.open(device, os.O_WRONLY | os.O_CLOEXEC)
        except OSError as e:
            level = logging.DEBUG if os.environ.get(SAID_ENV) else logging.INFO
            log.log(level, "the CPUs' wake-up latency is not held (%s: %s): run as root or let this user write it "
                    "(a udev rule) for faster wake-ups; %s=off stops asking", device, e.strerror, ENV)
            return cls()
        try:
            os.write(fd, struct.pack("=i", us))
        except OSError as e:
            os.close(fd)
            log.info("the CPUs' wake-up latency is not held (%s refused %d us: %s)", device, us, e.strerror)
            return cls()
        log.debug("holding %s at %d us", device, us)
        return cls(fd)

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def timer_slack(ns: int) -> bool:
    """The calling thread's timer slack (and the threads it starts from now on): how late the kernel may end a
    sleep to batch wake-ups, 50 us by default. A sleep of 100 us overslept 85 us here (p50), 37 with 1 us of
    slack, 20 with the request held too; the simulated camera sleeps until its exposure before its read-out.
    False where it cannot be set (not Linux)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        return ctypes.CDLL(None, use_errno=True).prctl(PR_SET_TIMERSLACK, ns, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False
