"""services.runtime.health: a process's counters and the bad-message policy (counted, logged once)."""

from __future__ import annotations

import logging

from services.runtime.health import Health


def test_health_counts_and_logs_once(caplog):
    h = Health("worker", "w-1", logging.getLogger("t"))
    with caplog.at_level(logging.WARNING):
        for _ in range(3):
            h.reject("frame", "garbage")
    h.count("correlations")
    st = h.status()
    assert st["bad"] == {"frame": 3} and st["counters"] == {"correlations": 1} and st["role"] == "worker"
    assert sum("bad frame" in r.message for r in caplog.records) == 1


def test_a_bad_message_puts_the_status_out_at_once_and_a_flood_at_most_every_prompt_s():
    """Node.tick: a status STATUS_S after the last one, or PROMPT_S after it once a bad message was counted; a flood
    of bad messages gives at most one status per PROMPT_S (times are tick's own argument: no clock, no session)."""
    from services.runtime import node as node_mod

    class Pub:
        def __init__(self):
            self.sent = []

        def put(self, payload):
            self.sent.append(payload)

    n = node_mod.Node.__new__(node_mod.Node)  # the status logic alone (no session)
    n.health, n.fields, n._status = Health("reducer", "r-1"), dict, Pub()
    n._last_status, n._next_status = 100.0, 100.0 + node_mod.STATUS_S
    n.tick(100.5)
    assert n._status.sent == []  # nothing new, not due
    n.health.reject("frame", "garbage")
    n.tick(100.05)
    assert n._status.sent == []  # within PROMPT_S of the last status
    n.tick(100.5)
    assert len(n._status.sent) == 1 and '"frame": 1' in n._status.sent[0]
    last = n._last_status
    assert last == 100.5
    for i in range(50):  # a flood, 50 bad messages in 50 ms: one status at most in it
        n.health.reject("frame", "garbage")
        n.tick(last + i * 0.001)
    assert len(n._status.sent) == 1
    n.tick(last + node_mod.PROMPT_S)
    assert len(n._status.sent) == 2 and '"frame": 51' in n._status.sent[1] and not n.health.news
    n.tick(n._last_status + node_mod.STATUS_S - 0.01)
    assert len(n._status.sent) == 2  # nothing new: the next at STATUS_S
    n.tick(n._last_status + node_mod.STATUS_S)
    assert len(n._status.sent) == 3
