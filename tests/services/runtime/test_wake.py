"""The loop's processes hold a PM QoS request for short CPU wake-ups while they run (services/runtime/wake.py): the
value VERGENCE_CPU_WAKE_US asks for, the bytes written, a device that cannot be opened, and a real worker that holds
/dev/cpu_dma_latency at 0 while it runs, or nothing with `off`."""

from __future__ import annotations

import ctypes
import logging
import os
import struct
import sys
import threading
from pathlib import Path

import pytest

from procs import VERGENCE, Procs, free_port, wait_for
from services.runtime import wake
from vergence.config import ConfigError


@pytest.mark.parametrize("value,us", [(None, 0), ("", 0), ("off", None), ("OFF", None), ("0", 0), ("25", 25)])
def test_the_request_the_variable_asks_for(value, us):
    assert wake.request_us(value) == us


@pytest.mark.parametrize("value", ["fast", "-1", "2.5"])
def test_a_bad_value_names_the_variable(value):
    with pytest.raises(ConfigError, match=r"VERGENCE_CPU_WAKE_US=.*whole number of microseconds .* or 'off'"):
        wake.request_us(value)


@pytest.mark.parametrize("value,written", [(None, struct.pack("=i", 0)), ("30", struct.pack("=i", 30)), ("off", b"")])
def test_the_request_is_the_kernel_s_32_bit_integer_held_until_closed(tmp_path, monkeypatch, value, written):
    dev = tmp_path / "dev"
    dev.write_bytes(b"")
    if value is None:
        monkeypatch.delenv(wake.ENV, raising=False)
    else:
        monkeypatch.setenv(wake.ENV, value)
    h = wake.Hold.open(str(dev))
    assert dev.read_bytes() == written
    assert (h.fd is not None) == (value != "off")
    fd = h.fd
    h.close()
    assert h.fd is None
    if fd is not None:
        with pytest.raises(OSError):
            os.fstat(fd)
    h.close()  # twice: nothing


def test_a_device_that_cannot_be_opened_holds_nothing_and_says_which(tmp_path, monkeypatch, caplog):
    monkeypatch.delenv(wake.ENV, raising=False)
    monkeypatch.delenv(wake.SAID_ENV, raising=False)
    with caplog.at_level(logging.INFO, logger="vergence.wake"):
        h = wake.Hold.open(str(tmp_path / "none"))
    assert h.fd is None
    assert f"not held ({tmp_path / 'none'}: No such file or directory)" in caplog.text
    assert "VERGENCE_CPU_WAKE_US=off stops asking" in caplog.text


def test_up_s_check_refuses_a_bad_value_and_says_an_unwritable_device_once_for_all_its_children(tmp_path, monkeypatch,
                                                                                                   caplog):
    monkeypatch.setenv(wake.ENV, "soon")
    with pytest.raises(ConfigError, match="VERGENCE_CPU_WAKE_US='soon'"):
        wake.check()
    monkeypatch.delenv(wake.ENV)
    monkeypatch.delenv(wake.SAID_ENV, raising=False)
    monkeypatch.setattr(wake, "DEVICE", str(tmp_path / "none"))
    with caplog.at_level(logging.INFO, logger="vergence.wake"):
        wake.check()
        assert os.environ[wake.SAID_ENV] == "1"
        wake.Hold.open(str(tmp_path / "none"))  # a child: it inherits SAID_ENV, and says nothing at INFO
    assert [r.levelno for r in caplog.records] == [logging.INFO]
    assert f"not held ({tmp_path / 'none'} is not writable here)" in caplog.text


def _slack_after(fn) -> int:
    """The timer slack (ns, prctl PR_GET_TIMERSLACK) of a thread of its own after fn() ran on it from 50 us."""
    libc = ctypes.CDLL(None, use_errno=True)
    out = []

    def run():
        libc.prctl(wake.PR_SET_TIMERSLACK, 50_000, 0, 0, 0)
        fn()
        out.append(libc.prctl(30, 0, 0, 0, 0))  # PR_GET_TIMERSLACK

    th = threading.Thread(target=run)
    th.start()
    th.join(10)
    return out[0]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl is Linux's")
@pytest.mark.parametrize("value,slack", [(None, wake.SLACK_NS), ("20", wake.SLACK_NS), ("off", 50_000)])
def test_holding_sets_the_thread_s_timer_slack_to_1_us(tmp_path, monkeypatch, value, slack):
    if value is None:
        monkeypatch.delenv(wake.ENV, raising=False)
    else:
        monkeypatch.setenv(wake.ENV, value)
    holds = []
    assert _slack_after(lambda: holds.append(wake.Hold.open(str(tmp_path / "none")))) == slack
    holds[0].close()


def _holds(pid: int) -> bool:
    return any(os.readlink(f) == wake.DEVICE for f in Path(f"/proc/{pid}/fd").iterdir() if f.is_symlink())


def _request() -> int:
    with open(wake.DEVICE, "rb") as f:
        return struct.unpack("=i", f.read(4))[0]


@pytest.mark.slow
@pytest.mark.skipif(not os.access(wake.DEVICE, os.W_OK), reason=f"{wake.DEVICE} is not writable here (root only)")
@pytest.mark.parametrize("value", [None, "off"], ids=["default", "off"])
def test_a_worker_holds_the_cpus_wake_up_latency_at_0_while_it_runs(tmp_path, value):
    env = {k: v for k, v in os.environ.items() if k != wake.ENV}
    if value is not None:
        env[wake.ENV] = value
    with Procs(tmp_path) as P:
        # no router: the request is held from before the session opens (a worker waiting for its router holds it)
        p = P.spawn("worker", [VERGENCE, "worker", "--connect", f"tcp/127.0.0.1:{free_port()}"], env=env)
        wait_for(lambda: "still trying (Ctrl-C stops)" in p.text(), 60, "the waiting line", logs=p.tail)
        pid = p.p.pid
        assert _holds(pid) == (value is None)
        if value is None:
            assert _request() == 0
        p.signal(2)
        assert p.wait(10) == 0
