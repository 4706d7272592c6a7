"""The predictive controller's predictors (split from control.py, issue #35): a constant-velocity Kalman filter of
the target's pan and rate (Predictor), a periodic fit that predicts a target moving to and fro (Periodic), and the
Referee that weighs them by how well each has predicted. vergence.head.control.Controller runs them."""

from __future__ import annotations

import math
from collections import deque

import numpy as np

__all__ = ["Predictor", "Periodic", "Referee"]


class Predictor:
    """A constant-velocity Kalman filter of the target's pan (radians) over exposure times (seconds).

    update(t, z) takes a measurement z of the target's pan exposed at t; at(t) is the estimate there.
    q: the variance of the target's acceleration (rad^2/s^4, piecewise constant between measurements),
    r: the measurement variance (rad^2), gate: the largest innovation (rad) taken as motion (larger:
    restart at z), vmax: the bound of the estimated rate (rad/s)."""

    def __init__(self, q: float, r: float, gate: float, vmax: float):
        self.q, self.r, self.gate, self.vmax = q, r, gate, vmax
        self.t: float | None = None
        self.x = self.v = 0.0
        self.p = [[0.0, 0.0], [0.0, 0.0]]
        self.restarts = 0

    def reset(self) -> None:
        self.t = None

    def jump(self, t: float, z: float) -> None:
        """The target is now at z (another one): there at rest, the filter's confidence kept (a restart's wide rate
        would take the next decisions' noise for motion)."""
        self.t, self.x, self.v = t, z, 0.0

    def _start(self, t: float, z: float) -> None:
        self.t, self.x, self.v = t, z, 0.0
        self.p = [[self.r, 0.0], [0.0, (self.vmax / 2) ** 2]]

    def update(self, t: float, z: float) -> None:
        if self.t is None or t < self.t - 1.0:  # none yet, or time went back (a new capture): start over
            self._start(t, z)
            return
        dt = max(0.0, t - self.t)
        (p00, p01), (_, p11) = self.p
        x = self.x + self.v * dt
        q = self.q  # piecewise-constant white acceleration of variance q
        p00 = p00 + dt * (2 * p01 + dt * p11) + q * dt ** 4 / 4
        p01 = p01 + dt * p11 + q * dt ** 3 / 2
        p11 = p11 + q * dt ** 2
        y = z - x
        if abs(y) > self.gate:
            self.restarts += 1
            self._start(t, z)
            return
        s = p00 + self.r
        k0, k1 = p00 / s, p01 / s
        self.x = x + k0 * y
        self.v = max(-self.vmax, min(self.vmax, self.v + k1 * y))
        self.p = [[(1 - k0) * p00, (1 - k0) * p01], [(1 - k0) * p01, p11 - k1 * p01]]
        self.t = t

    def at(self, t: float) -> float:
        """The estimated pan at time t (the last estimate carried at the estimated rate)."""
        return self.x + self.v * (t - self.t)


class Periodic:
    """A target that moves back and forth: its pan over the last window_s as a constant plus `harmonics`
    harmonics of one frequency (least squares), the frequency the one whose fit leaves the least residual
    (searched every `every` samples kept over a log grid from the lowest of which `cycles` periods fit in the
    history, to max_hz, then refined over a fine grid between the neighbours of each of its REFINED deepest local
    minima); predict(at) extrapolates the fit. None while the history is shorter than min_s.

    Where a target repeats its motion (a hand moving an object to and fro, a pendulum, the simulator's
    sines), this predicts far past where any polynomial holds, as primate smooth pursuit does for periodic
    targets to overcome its own latency of about 100 ms; where it does not, its predictions are poor, and the
    Referee leaves them out.

    Its cost does not grow with the frame rate: the history keeps samples at least MIN_DT_S apart (a newer
    one closer than that replaces the newest; at 60 Hz every sample is kept), the fit is made again only when
    a sample is kept, and every grid is fitted at once (the normal equations of all its frequencies in one
    batch, the harmonics by the angle-addition recurrence; its figures: docs/PERFORMANCE.md)."""

    MIN_DT_S = 1 / 64  # the history's spacing: 3 harmonics of max_hz need 24 Hz; 64 Hz keeps a 60 Hz camera's
    GRID, FINE = 40, 33  # the search's log grid, and its fine grid between a minimum's neighbours
    REFINED = 2  # the grid's local minima refined (the deepest first)
    SUBHARMONIC = 1.5  # a refined minimum at half another's frequency wins only where its residual is under 1 / this

    def __init__(self, harmonics: int = 3, window_s: float = 3.0, min_s: float = 0.4, max_hz: float = 4.0,
                 cycles: float = 0.6, every: int = 10):
        self.k, self.window_s, self.min_s, self.max_hz, self.every = harmonics, window_s, min_s, max_hz, every
        self.cycles = cycles
        self.t: deque[float] = deque()
        self.z: deque[float] = deque()
        self.hz: float | None = None
        self.kept = 0  # samples appended since the last search (a replaced newest one not counted)
        self.appended = 0  # samples appended, ever
        self._fit: tuple | None = None  # (appended, hz, the newest time, coefficients) of the latest fit

    def reset(self) -> None:
        self.t.clear()
        self.z.clear()
        self.hz = None
        self._fit = None

    def move(self, ts: list[float], ds: list[float]) -> None:
        """Each sample moved by ds interpolated at its time (ts ascending): the pans they were read at were off."""
        for k, t in enumerate(self.t):
            self.z[k] += float(np.interp(t, ts, ds))
        self._fit = None

    def refocus(self, ts: list[float], pans: list[float], ratio: float) -> None:
        """The samples' angles were read at a focal length off by `ratio` (the image's motion over the one told):
        each sample (a frame's pan, interpolated in ts and pans, plus its offset's angle) gets the angle at the
        measured one."""
        if not (math.isfinite(ratio) and ratio > 0) or not ts:
            return
        at = list(self.t)
        self.move(at, [math.atan(math.tan(z - p) / ratio) - (z - p) for z, p in zip(self.z, np.interp(at, ts, pans))])

    def add(self, t: float, z: float) -> None:
        if self.t and t <= self.t[-1]:
            return
        if len(self.t) >= 2 and self.t[-1] - self.t[-2] < self.MIN_DT_S:
            # the newest is closer than MIN_DT_S to the one before it: this one takes its place (the newest is
            # always the latest measurement; the ones before it are MIN_DT_S apart at least)
            self.t[-1], self.z[-1] = t, z
        else:
            self.t.append(t)
            self.z.append(z)
            self.kept += 1
            self.appended += 1
        while self.t[-1] - self.t[0] > self.window_s:
            self.t.popleft()
            self.z.popleft()

    def _design(self, tt: np.ndarray, hz: np.ndarray) -> np.ndarray:
        """(len(hz), 2 harmonics + 1, len(tt)): the constant, then cos, sin of each harmonic at each time."""
        w = 2 * math.pi * np.asarray(hz, float)[:, None] * np.asarray(tt, float)[None, :]
        x = np.empty((len(w), 2 * self.k + 1, w.shape[1]))
        x[:, 0] = 1.0
        c1, s1 = np.cos(w, out=x[:, 1]), np.sin(w, out=x[:, 2])
        for j in range(1, self.k):
            c, sn = x[:, 2 * j - 1], x[:, 2 * j]
            np.subtract(c * c1, sn * s1, out=x[:, 2 * j + 1])
            np.add(sn * c1, c * s1, out=x[:, 2 * j + 2])
        return x

    def _fits(self, tt: np.ndarray, zs: np.ndarray, hz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The residual sum of squares and the coefficients of the fit at each frequency of hz (batched normal
        equations; the mean taken out of zs first, which the constant takes back, for their conditioning)."""
        x = self._design(tt, hz)
        mean = float(np.mean(zs))
        zc = zs - mean
        rhs = x @ zc
        try:
            coef = np.linalg.solve(x @ x.transpose(0, 2, 1), rhs[..., None])[..., 0]
        except np.linalg.LinAlgError:  # a degenerate history (repeated times): least squares one by one
            coef = np.stack([np.linalg.lstsq(xi.T, zc, rcond=None)[0] for xi in x])
        res = float(zc @ zc) - np.sum(coef * rhs, axis=1)
        coef[:, 0] += mean
        return res, coef

    def _search(self, tt: np.ndarray, zs: np.ndarray, span: float) -> float:
        grid = np.geomspace(self.cycles / span, self.max_hz, self.GRID)
        res = self._fits(tt, zs, grid)[0]
        # the REFINED deepest local minima, not only the deepest point: with harmonics over a window of a period or
        # two the true frequency's well is narrower than the grid's steps, and a point on its wall can leave more than
        # a spurious minimum's bottom (about 0.6 x the frequency, whose harmonics bracket it over so short a window)
        low = np.flatnonzero((res <= np.r_[np.inf, res[:-1]]) & (res <= np.r_[res[1:], np.inf]))
        picks = []
        for i in low[np.argsort(res[low])][:self.REFINED] if len(low) else [int(np.argmin(res))]:
            fine = np.linspace(grid[max(0, i - 1)], grid[min(len(grid) - 1, i + 1)], self.FINE)
            r = self._fits(tt, zs, fine)[0]
            picks.append((float(r.min()), float(fine[int(np.argmin(r))])))
        (r0, f0), *others = sorted(picks)
        # a subharmonic's three harmonics hold the frequency itself: where it fits little better it fits the noise
        # (an encoder's), and its prediction goes astray; the frequency unless its half is clearly the better fit
        return next((f for r, f in others if 1.8 <= f / f0 <= 2.2 and r <= self.SUBHARMONIC * r0), f0)

    def predict(self, at: float) -> float | None:
        if len(self.t) < 4 * self.k + 4 or self.t[-1] - self.t[0] < self.min_s:
            return None
        span = self.t[-1] - self.t[0]
        if self.hz is None or self.kept >= self.every or self.hz < self.cycles / span:
            ts, zs = np.fromiter(self.t, float), np.fromiter(self.z, float)
            self.hz = self._search(ts - ts[-1], zs, span)
            self.kept = 0
        if self._fit is None or self._fit[:2] != (self.appended, self.hz):  # refit on a new sample kept
            ts, zs = np.fromiter(self.t, float), np.fromiter(self.z, float)
            self._fit = (self.appended, self.hz, ts[-1], self._fits(ts - ts[-1], zs, np.array([self.hz]))[1][0])
        _, hz, t_ref, coef = self._fit
        # the fit at one instant: _design's recurrence in plain floats (a dozen numpy calls cost 30x more)
        w = 2 * math.pi * hz * (at - t_ref)
        c1, s1 = math.cos(w), math.sin(w)
        c, sn = c1, s1
        z = float(coef[0]) + float(coef[1]) * c + float(coef[2]) * sn
        for j in range(1, self.k):
            c, sn = c * c1 - sn * s1, sn * c1 + c * s1
            z += float(coef[2 * j + 1]) * c + float(coef[2 * j + 2]) * sn
        return z


class Referee:
    """Which predictions to trust, by how well each predicted: every prediction made for an instant is scored
    once the measurements around that instant are in (the measurement interpolated there), its squared error
    averaged (exponentially, over about `memory` scores). blend(preds) weighs the predictions (None: that
    predictor has none now) by the inverse square of their mean squared errors, so the one that predicts
    best all but decides; the first is the fallback, alone until another has `warm` scores."""

    PENDING = 64  # predictions kept awaiting their measurement (a second at 64 Hz; older ones are dropped)

    def __init__(self, n: int, memory: int = 30, warm: int = 8, power: float = 2.0):
        self.alpha, self.warm, self.power = 1.0 / memory, warm, power
        self.pending: deque[tuple[float, list]] = deque()
        self.mse: list[float | None] = [None] * n
        self.scored = [0] * n
        self.last: tuple[float, float] | None = None

    def reset(self) -> None:
        """After a jump: the scores start again (a fit of the motion before says nothing of the one after)."""
        self.pending.clear()
        self.last = None
        self.mse = [None] * len(self.mse)
        self.scored = [0] * len(self.scored)

    def predicted(self, at: float, preds: list) -> None:
        self.pending.append((at, preds))
        while len(self.pending) > self.PENDING:
            self.pending.popleft()

    def measured(self, t: float, z: float) -> None:
        last, self.last = self.last, (t, z)
        while self.pending and self.pending[0][0] <= t:
            at, preds = self.pending.popleft()
            if last is None or at < last[0]:
                continue
            truth = last[1] + (z - last[1]) * (at - last[0]) / (t - last[0]) if t > last[0] else z
            for k, p in enumerate(preds):
                if p is not None:
                    e = (p - truth) ** 2
                    self.mse[k] = e if self.mse[k] is None else self.mse[k] + self.alpha * (e - self.mse[k])
                    self.scored[k] += 1

    def blend(self, preds: list) -> float:
        use = [(p, self.mse[k]) for k, p in enumerate(preds)
               if p is not None and self.mse[k] is not None and (k == 0 or self.scored[k] >= self.warm)]
        if len(use) < 2:
            return preds[0]
        w = [1.0 / max(m, 1e-18) ** self.power for _, m in use]
        return sum(wi * p for wi, (p, _) in zip(w, use)) / sum(w)
