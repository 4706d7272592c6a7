"""services/runtime/heartbeat.py and up's end of it (issue #29), in this process: when a child beats, how long up
lets it be silent, and the thread that beats. The real processes: tests/services/ops/test_up.py (small children
killed or kept) and tests/scenarios/test_supervise.py (SIGSTOP under `vergence up`, a fresh compile)."""

from __future__ import annotations

import os
import select
import threading

import pytest

from procs import wait_for
from vergence.config import SuperviseSettings
from services.runtime import heartbeat
from services.ops import up


def test_it_beats_until_its_loop_stalls(monkeypatch):
    monkeypatch.setattr(heartbeat, "_last", [0.0])
    assert heartbeat.beating(10.0, 1e6)  # no progress yet: start-up, always
    heartbeat._last[0] = 100.0
    assert heartbeat.beating(10.0, 109.9) and not heartbeat.beating(10.0, 110.0)
    assert heartbeat.beating(0.0, 1e6)  # stall_s 0: not checked


def test_up_takes_a_child_for_hung_after_heartbeat_s_and_a_fresh_one_after_start_grace_s():
    hb = up.Heartbeat(SuperviseSettings(heartbeat_s=1.5, start_grace_s=30.0, stall_s=10.0))
    try:
        assert hb.env == {heartbeat.ENV: f"{hb.fds[0]},10"}
        t0 = hb.started
        assert hb.silent(t0 + 29.9) is None and hb.silent(t0 + 30.5) == pytest.approx(30.5)
        os.write(hb.fds[0], b"hhh")  # what a child's thread writes
        hb.poll(t0 + 40.0)
        assert hb.last == t0 + 40.0
        assert hb.silent(t0 + 41.4) is None and hb.silent(t0 + 41.6) == pytest.approx(1.6)
        hb.poll(t0 + 42.0)  # nothing more came
        assert hb.last == t0 + 40.0
    finally:
        hb.close()


@pytest.mark.realtime  # times a thread or a wake-up: kept in the main process of a split run
def test_the_thread_beats_and_leaves_when_up_is_gone(monkeypatch):
    r, w = os.pipe()
    monkeypatch.setenv(heartbeat.ENV, f"{w},0")
    monkeypatch.setattr(heartbeat, "_last", [0.0])
    assert heartbeat.start()
    assert heartbeat.ENV not in os.environ  # what this process starts is not up's child
    beats = 0
    while beats < 3:
        assert select.select([r], [], [], 2.0)[0], "no beat within 2 s"
        beats += len(os.read(r, 64))
    os.close(r)  # up is gone: the next write fails, the thread ends (and closes its end)
    wait_for(lambda: not any(t.name == "heartbeat" for t in threading.enumerate()), 5, "the thread's end")
    assert not heartbeat.start()  # no ENV: not under up, nothing started
