"""The capture's fovea: where it is, and the fixate requests that move it (a zenoh callback thread writes, the
capture's loop reads). Split from services/pipeline/capture.py (issue #34); the rules: docs/SERVICE.md."""

from __future__ import annotations

import logging
import threading
import time

from vergence.network import retina
from vergence.wire.messages import Fixate, MessageError

from services.runtime.health import Health

log = logging.getLogger("vergence.capture")


class Fovea:
    """Where the fovea is, and the fixate requests that move it (zenoh callback thread -> capture loop)."""

    LOG_EVERY_S = 1.0

    def __init__(self, x: int, y: int, shape: tuple[int, int], params, health: Health):
        self.lock = threading.Lock()
        self.x, self.y = x, y
        self.shape, self.params, self.health = shape, params, health
        self._last_log = -1e9
        # the latest well-formed request that was refused, for the status (`vergence fixate` reads it to say why
        # at once): its t_ns, which the asker knows, and our reason
        self.rejection: dict | None = None

    def at(self) -> tuple[int, int]:
        with self.lock:
            return self.x, self.y

    def fields(self) -> dict:
        """For the status: the fovea's centre and the latest refused request, if any."""
        with self.lock:
            out = {"fovea": [self.x, self.y]}
            if self.rejection is not None:
                out["fixate_rejection"] = dict(self.rejection)
            return out

    def _reject(self, why: str) -> None:
        self.health.reject("fixate", why)
        self.health.count("fixate_rejected")
        now = time.monotonic()
        if now - self._last_log >= self.LOG_EVERY_S:  # every reason, at most once a second
            self._last_log = now
            log.warning("fixate request rejected, the fovea stays at (%d, %d): %s", self.x, self.y, why)

    def on_fixate(self, payload: bytes) -> tuple[int, int] | None:
        """A fixate request's bytes -> the new fovea centre, or None (rejected, counted, logged)."""
        try:
            req = Fixate.from_bytes(payload)
        except MessageError as e:
            self._reject(str(e))
            return None
        x, y = int(round(req.x)), int(round(req.y))
        try:
            retina.check_point(self.shape, x, y, self.params.window, self.params.vsearch)
        except retina.BorderError as e:
            why = f"({req.x:g}, {req.y:g}): {e}"
            self._reject(why)
            with self.lock:
                self.rejection = {"t_ns": req.t_ns, "why": why}
            return None
        with self.lock:
            self.x, self.y = x, y
        self.health.count("fixations")
        log.info("fixate: fovea to (%d, %d)%s", x, y, f" for {req.source}" if req.source else "")
        return x, y
