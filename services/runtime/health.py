"""The counters of one process and the bad-message policy (count, log once per kind, skip): every service's
health, published as its status."""

from __future__ import annotations

import os
import threading
import time

__all__ = ["Health"]


class Health:
    """Counters of one process and the bad-message policy: count, log once per kind, skip.

    status() is what the services publish as JSON on vergence/<rig>/status/<role>/<id>."""

    def __init__(self, role: str, ident: str, log=None):
        self.role, self.ident, self.log = role, ident, log
        self.counters: dict[str, int] = {}
        self.bad: dict[str, int] = {}
        self._logged: set[str] = set()
        self.news = False  # a bad message counted since the last status() (services/runtime/node.py: sent sooner)
        self._lock = threading.Lock()  # zenoh callbacks of several threads count too

    def count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counters[name] = self.counters.get(name, 0) + n

    def reject(self, kind: str, err: Exception | str) -> None:
        """A message of `kind` that failed to decode or validate: counted, logged the first time."""
        with self._lock:
            self.bad[kind] = self.bad.get(kind, 0) + 1
            self.news = True
            first = kind not in self._logged
            self._logged.add(kind)
        if first and self.log is not None:
            self.log.warning("bad %s message skipped (further ones are only counted): %s", kind, err)

    def flag(self) -> None:
        """Something bad was counted elsewhere (a source's own counters): the status goes out as for reject()."""
        self.news = True

    def status(self, **extra) -> dict:
        with self._lock:
            d = {"role": self.role, "id": self.ident, "pid": os.getpid(), "t_ns": time.time_ns(),
                 "counters": dict(self.counters), "bad": dict(self.bad)}
            self.news = False
        d.update(extra)
        return d
