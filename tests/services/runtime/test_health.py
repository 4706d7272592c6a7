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
