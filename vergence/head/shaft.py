"""The slave's pan in motion from the goals sent and the encoder's readings, not one reading (a noisy encoder).

A frame's pan at exposure is one encoder reading (or the line between two). While the motor rests,
vergence.head.rest takes the mean of its readings; in motion each frame's pan kept the reading's noise (0.05 deg is
0.44 px at f 500): pursuit at 30 Hz paid x1.5-2 of the clean run's RMS for it. But a motor in motion heads for the
goal it was sent, after its latency, as a servo does (to first order, with a time constant), and a goal has no noise.
So the shaft is modelled from the goals sent (on the motor's whole ticks where it takes them), the model's latency and
time constant fitted (LATENCIES x TAUS, least squares) to the readings of the last FIT_S at each refit, each pair's
residual variance summed over the refits with a HALF_LIFE_S memory where the best pair's is within SERVO_SD of the
noise (a servo does not change from one second to the next: a second alone often chose a pair 3-5 ms off, its frames
0.2 px off the shaft in a fast pursuit), and a frame's pan is the model's there plus the readings' mean residual over
that refit (a motor's steady lag). Used only for a noisy encoder: its noise read off each reading against the line
between its neighbours (no model in it: a stalled shaft's readings are on that line), less a tick's rounding, above
NOISY_DEG (a clean encoder's frames keep their reading, to the digit); and only where the frame's reading is within
SIGMAS of that noise of the model's pan and the residuals within BIAS_S of the frame average within SIGMAS standard
errors and half a tick (a shaft stalled, blocked or pushed is where its readings say). Measured: docs/FAULTS.md, "The
encoder's noise in motion" and "The servo's fit remembered where it fits"."""

from __future__ import annotations

import bisect
import itertools
import math
from collections import deque

from ..motors.base import MotorSettings
from .rest import KEEP_S, Rest

__all__ = ["Shaft", "NOISY_DEG"]

FIT_S = 1.0  # the readings the model is fitted to
REFIT_S = 0.25  # ... refitted this often
SETTLE_S = 0.1  # the model starts on the first reading this long before the first one it is judged by
BIAS_S = 0.2  # the residuals within this of a frame must average near 0 (else the shaft is not the model's)
LATENCIES = (0.0, 0.002, 0.005, 0.01, 0.02, 0.04)  # s: the motor's latency, fitted
TAUS = (0.005, 0.01, 0.02, 0.04, 0.08)  # s: its time constant, fitted (none of 0: a servo at its goal at once, which a
# second of noisy readings at 60 Hz chose now and then among near-equal pairs, its frames up to 0.056 deg off in a move)
NOISY_DEG = 0.03  # the encoder's noise (less the ticks' rounding) above this: a noisy one (clean: 0-0.024)
SIGMAS = 4.0  # a frame's reading further than this many of the noise from the model's pan: left as read
MIN_READINGS = 20  # readings in FIT_S before the model is fitted
HALF_LIFE_S = 3.0  # a pair's residuals of a refit weigh half as much this much later (docs/FAULTS.md, "The servo's
# fit remembered where it fits": one second of readings alone chose the true pair in 10-50 % of the refits)
SERVO_SD = 1.5  # ... remembered only where the best pair's residuals are within this many of the noise (a loop's
# first large moves, where the servo's acceleration limit shows, chose a pair 5 ms late that the memory then held)


class Shaft:
    """The encoder's readings are the Rest's (vergence.head.rest: its motor() keeps them, times on the frames' clock,
    pans in radians); commanded() each goal sent, at() a frame's pan; then() and past() a past frame's as the model now
    has it, raw() whether the frames' pans may still be a noisy encoder's readings (the play's turns wait for it).
    `fit`: the servo's (latency, time constant) fitted (None: not fitted, or a clean encoder); `sd`: the encoder's noise
    (rad; None: not read yet); `offset`: the readings' mean residual about the model."""

    def __init__(self, readings: Rest, motor: MotorSettings | None = None):
        self.motor = motor or MotorSettings(quantise=False)  # (its whole ticks: where it stops, what it reads)
        self.tick = self.motor.tick_rad  # (0: none), whose rounding is no noise
        self.t, self.r = readings.t, readings.pan  # (the Rest's own, in time order, the last KEEP_S of them)
        self.ct: deque[float] = deque()
        self.cg: deque[float] = deque()
        self.fit: tuple[float, float] | None = None  # (latency, tau)
        self.sd: float | None = None
        self.t_fit = -math.inf
        self.offset = 0.0
        self.scores: dict[tuple[float, float], float] = {}  # each pair's residual variance, summed over the refits
        self.t_scored: float | None = None  # ... as of this refit

    def commanded(self, t: float, goal: float) -> None:
        if not (math.isfinite(t) and math.isfinite(goal)):
            return
        if self.ct and t < self.ct[-1]:
            self.ct.clear()
            self.cg.clear()
        self.ct.append(t)
        self.cg.append(self.motor.from_motor(self.motor.whole_ticks(self.motor.to_motor(goal))))  # as it takes it
        while self.ct[-1] - self.ct[0] > KEEP_S:
            self.ct.popleft()
            self.cg.popleft()

    def _model(self, lat: float, tau: float, t0: float, times: list[float]) -> list[float] | None:
        """The model's pans at `times` (ascending, from t0 on), started on the reading at or before t0."""
        i = bisect.bisect_right(self.t, t0) - 1
        if i < 0 or not self.ct:
            return None
        x, tx = self.r[i], self.t[i]
        k = bisect.bisect_right(self.ct, tx - lat) - 1
        g = self.cg[k] if k >= 0 else x
        k += 1
        out = []
        for t in times:
            while k < len(self.ct) and self.ct[k] + lat <= t:
                tc = self.ct[k] + lat
                x = g + (x - g) * math.exp(-(tc - tx) / tau) if tau > 0 else g
                tx, g = tc, self.cg[k]
                k += 1
            x = g + (x - g) * math.exp(-(t - tx) / tau) if tau > 0 else g
            tx = t
            out.append(x)
        return out

    def _refit(self, now: float) -> None:
        self.t_fit = now
        a = bisect.bisect_left(self.t, now - FIT_S)
        ts = list(self.t)[a:]
        t0 = ts[0] - SETTLE_S if ts else now
        judged = [j for j, t in enumerate(ts) if t >= ts[0] + SETTLE_S] if ts else []
        if len(judged) < MIN_READINGS or not self.ct or self.ct[-1] < now - FIT_S:
            self.fit = self.sd = None
            return
        rs = list(self.r)[a:]
        self.sd, self.fit = _noise(ts, rs, self.tick), None
        if self.sd < math.radians(NOISY_DEG):
            return  # a clean encoder: its frames keep their reading, no model is fitted
        if self.t_scored is not None and now < self.t_scored:
            self.scores, self.t_scored = {}, None  # (a clock gone back: what was summed says nothing of the new one)
        keep = 0.0 if self.t_scored is None else 0.5 ** ((now - self.t_scored) / HALF_LIFE_S)
        means, var = {}, {}
        for lat in LATENCIES:
            for tau in TAUS:
                m = self._model(lat, tau, t0, ts)
                if m is None:
                    continue
                res = [rs[j] - m[j] for j in judged]
                means[(lat, tau)] = mean = sum(res) / len(res)
                var[(lat, tau)] = sum((e - mean) ** 2 for e in res) / len(res)
        if not var:
            return
        if min(var.values()) <= (SERVO_SD * self.sd) ** 2:  # (else no pair is this servo here: not remembered)
            self.t_scored = now
            for pair, v in var.items():
                self.scores[pair] = keep * self.scores.get(pair, 0.0) + v
        best = min(var, key=lambda pair: (self.scores.get(pair, math.inf), var[pair]))
        self.fit, self.offset = best, means[best]

    def at(self, t: float, pan: float) -> float:
        """The slave's pan at t: the model's there plus the readings' mean residual, or `pan` (the frame's)."""
        if not (math.isfinite(t) and math.isfinite(pan)) or not self.t:
            return pan
        if t - self.t_fit >= REFIT_S or t < self.t_fit - KEEP_S:
            self._refit(t)
        return self.then(t, pan)

    def then(self, t: float, pan: float) -> float:
        """at() without a refit: a past frame's pan as the model now has it (`pan` where none is fitted)."""
        est = self.past(t, pan)
        return pan if est is None else est

    def past(self, t: float, pan: float) -> float | None:
        """then(), but None where a fitted model has no reading before the frame to start from (a noisy encoder's first
        frames: their pans are its readings)."""
        if not (math.isfinite(t) and math.isfinite(pan)) or self.fit is None or not self.t:
            return pan
        lat, tau = self.fit
        a, b = bisect.bisect_left(self.t, t - BIAS_S), bisect.bisect_right(self.t, t + BIAS_S)
        ts = list(itertools.islice(self.t, a, b))  # (not the whole deque copied, a frame at a time)
        if not ts:
            return pan
        ins = bisect.bisect_left(ts, t)
        m = self._model(lat, tau, min(ts[0], t) - SETTLE_S, ts[:ins] + [t] + ts[ins:])
        if m is None:
            return None
        here = m.pop(ins)
        bias = sum(self.r[a + j] - m[j] for j in range(len(ts))) / len(ts)
        if abs(bias - self.offset) > SIGMAS * self.sd / math.sqrt(len(ts)) + self.tick / 2:
            return pan  # the shaft does not go where the model says (stalled, blocked, pushed): as read
        est = here + self.offset
        return est if abs(est - pan) <= SIGMAS * self.sd else pan

    def raw(self, t: float) -> bool:
        """The frames' pans at t may be raw readings of a noisy encoder: within FIT_S + SETTLE_S of the first reading
        kept (the noise not read yet), or its noise read over NOISY_DEG and no model fitted."""
        if not self.t:
            return False
        if self.sd is None:
            return t - self.t[0] < FIT_S + SETTLE_S
        return self.sd >= math.radians(NOISY_DEG) and self.fit is None

    def status(self) -> dict:
        """For the reducer's status: the encoder's noise as read (deg; None: not yet a second of readings)."""
        return {"encoder_noise_deg": None if self.sd is None else round(math.degrees(self.sd), 3)}


def _noise(ts: list[float], rs: list[float], tick: float) -> float:
    """The encoder's noise (rad), from the readings alone: each reading against the line between its neighbours
    (a shaft at rest, stalled or moving smoothly is on it; their noise is not), the RMS of all but the tenth furthest
    (a command's start is no noise) over a Gaussian's RMS within its 90 % (0.789), less the ticks' rounding."""
    e2 = []
    for j in range(1, len(ts) - 1):
        w = (ts[j] - ts[j - 1]) / (ts[j + 1] - ts[j - 1])
        e = rs[j] - ((1 - w) * rs[j - 1] + w * rs[j + 1])
        e2.append(e * e / (1 + (1 - w) ** 2 + w * w))
    if not e2:
        return 0.0
    near = sorted(e2)[:max(1, int(0.9 * len(e2)))]
    var = sum(near) / len(near) / 0.789 ** 2
    return math.sqrt(max(0.0, var - tick ** 2 / 12))
