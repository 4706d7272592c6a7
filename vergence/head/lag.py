"""A camera later than its frames say (issue #35): the lag between the motor's motion, as the frames' pans tell it,
and the slave's image of it, fitted where the loop's check (vergence.head.doubt) has a controlled move to watch.

An image older than its frame says (a camera latency that [camera] latency_s does not tell, an image not stamped at
its exposure) shows the motor's motion late: over a fast move it has not moved yet, which the check takes for a
frozen (or reversed) camera, and names. The moves of a fault tell: the move back to the anchor and each probe, a
late image follows them after its lag, a frozen, slipping or reversed one never does. RETURN_FIT_S after a fault is
named, and LAG_AFTER_S after a probe clears one, the lag L (0..MAX_LAG_S) that best explains the offsets of the
decisions since the move's reference by the motor's motion L earlier (a_k - a_ref = -(pan(t_k - L) - pan(t_ref -
L)), the target's own motion fitted as a rate and an acceleration; the pans read between the motor's own reports
(motor(): the reducer's motor states, the sim loop's encoder; the frames' pans where the caller has none, one a
frame, which a fast move between two frames is not a line through) is fitted. A lag counts only where the motor
moved PROBE_MIN_DEG under it and is at rest again by the window's end, and where it leaves at most LATE_FIT of no
lag's residual, and little. Where LATE_PAIRS such fits
agree the camera is named late: a log line, `late_ms` in the status, and from then on each frame is taken at its
exposure less the lag, with the pan then (shift(): the check and the controller both), so that the head runs
without more faults. A fault's probe whose image has not followed PROBE_FIT_S after it is judged by probe(): its
step fitted with a lag and the target's own motion (a late image's probe, whose frames' level the target's motion
hides). Measured: docs/FAULTS.md, "A camera later than its frames say"."""

from __future__ import annotations

import bisect
import logging
import math
from collections import deque

import numpy as np

from .follows import FOLLOWS_MAX, FOLLOWS_MIN

__all__ = ["Lag"]

log = logging.getLogger("vergence.doubt")

MAX_LAG_S, LAG_STEP_S = 0.25, 0.0025  # the lags a move's decisions are fitted with
LATE_FIT = 0.25  # a lag is fitted where it leaves at most this share of no lag's squared residual ...
LATE_RMS_DEG = 0.1  # ... and at most this residual (the offset's and the encoder's noise; a target moving meanwhile),
LATE_SHARE = 0.1  # or this share of the motion it explains (a frame's timing over a fast move)
LATE_AGREE_S = 0.02  # LATE_PAIRS fits, of the last LATE_PAIRS + 1, that agree within this name the camera late
LATE_PAIRS = 2
RETURN_FIT_S = 0.4  # a fault's lag (the move that raised it, the move back) is fitted this long after it
LAG_AFTER_S = 0.1  # a probe's lag is fitted this long after it cleared the fault (the image's whole step then seen)
LATE_NOISE_DEG = 0.02  # lags whose residual is within this (rms) of the best are alike: their middle is the lag
MOVED_DEG = 0.3  # a lag counts where the motor moved at least this much under it (a probe's smallest that counts)
PROBE_REST = 3  # a probe's lag counts where the motor is at rest over this many decisions at either end of its fit


class Lag:
    """The frames' pans and the decisions' offsets of the last second, the fits of the lag between them, and the
    lag named (late_s, None until LATE_PAIRS fits agree). Times are the frames' own (their exposure as stamped)."""

    def __init__(self):
        self.pans: deque[tuple[float, float]] = deque()  # (t, pan) of every frame, 2 MAX_LAG_S back
        self.seen: deque[tuple[float, float]] = deque()  # (t, a) of the confident decisions
        self.lags: list[float | None] = []  # the latest fits (None: none fitted)
        self.late_s: float | None = None
        self.pending: tuple[float, float, float] | None = None  # (t_ref, a_ref, due) of the next fit
        self.reported = False  # the motor's own reports are kept (not the frames' pans)

    def shift(self, t: float, pan: float) -> tuple[float, float, float]:
        """A frame as its stamp says it (t its slave's exposure, pan the slave's pan then) into (t, pan) as its
        image shows it, and how far off that pan may be: the same and 0, or for a camera named late, late_s earlier,
        the pan then, and half of what the motor moved between the two frames' pans it was read between."""
        if not (math.isfinite(t) and math.isfinite(pan)):
            return t, pan, 0.0
        if not self.reported:
            self.motor(t, pan, report=False)
        if self.late_s is None:
            return t, pan, 0.0
        ts = t - self.late_s
        i = bisect.bisect_left(self.pans, (ts, -math.inf))
        if not 0 < i < len(self.pans):  # before the first pan kept or after the last: that one (as np.interp)
            return ts, float(self.pans[min(i, len(self.pans) - 1)][1]), 0.0
        (t0, p0), (t1, p1) = self.pans[i - 1], self.pans[i]
        return ts, float(p0 + (p1 - p0) * (ts - t0) / (t1 - t0)), float(0.5 * abs(p1 - p0))

    def motor(self, t: float, pan: float, report: bool = True) -> None:
        """The motor's own report of its pan at t (the frames' clock), where the caller has them: denser than one a
        frame (a fast move between two frames is no line), and never a pan extrapolated to an exposure; from the
        first on, the frames' pans are not kept (report=False: shift()'s, each frame's at its exposure)."""
        if not (math.isfinite(t) and math.isfinite(pan)):
            return
        self.reported |= report
        i = bisect.bisect_left(self.pans, (t, -math.inf))
        if i < len(self.pans) and self.pans[i][0] == t:
            return
        self.pans.insert(i, (t, pan))
        while self.pans[-1][0] - self.pans[0][0] > 4 * MAX_LAG_S:  # (a probe's fit reads 2 MAX_LAG_S before its ref)
            self.pans.popleft()

    def _pan_at(self, t: np.ndarray) -> np.ndarray:
        ts = np.fromiter((q[0] for q in self.pans), float, len(self.pans))
        ps = np.fromiter((q[1] for q in self.pans), float, len(self.pans))
        return np.interp(t, ts, ps)

    def _lagged(self, tk: np.ndarray, t_ref: float, earliest: float, oldest: float):
        """The lags (0..MAX_LAG_S) that reach back from `earliest` no further than the pan kept at `oldest`, and at
        each (rows) the motor's motion since t_ref that much earlier, at the decisions' times tk; None: no lag."""
        lags = np.arange(0.0, MAX_LAG_S + 1e-9, LAG_STEP_S)
        lags = lags[earliest - lags >= oldest]
        if not lags.size:
            return None
        return lags, self._pan_at(tk[None, :] - lags[:, None]) - self._pan_at(t_ref - lags)[:, None]

    def unless_late(self, kind: str, t_i: float, t_j: float, moved: float) -> str:
        """A pair's fail kind: "frozen" for a "reversed" one where the motor's motion a lag (2 LAG_STEP_S..MAX_LAG_S)
        earlier explains the image's motion `moved` between t_i and t_j as following it (r in FOLLOWS_MIN..FOLLOWS_MAX,
        over MOVED_DEG or more): a late image of an earlier turn, not a camera turning the other way (whose advice,
        flip the direction, would break a good head). Before the first pan kept, the motor is taken at that pan."""
        if kind != "reversed" or len(self.pans) < 2:
            return kind
        lags = np.arange(2 * LAG_STEP_S, MAX_LAG_S + 1e-9, LAG_STEP_S)
        p = self._pan_at(t_j - lags) - self._pan_at(t_i - lags)
        big = np.abs(p) >= math.radians(MOVED_DEG)
        r = np.divide(moved, p, out=np.zeros_like(p), where=big)
        return "frozen" if bool((big & (r >= FOLLOWS_MIN) & (r <= FOLLOWS_MAX)).any()) else kind

    def saw(self, t: float, a: float) -> None:
        """A confident decision's offset (t as shift() returned it); a fit when due."""
        self.seen.append((t + (self.late_s or 0.0), a))
        while self.seen[-1][0] - self.seen[0][0] > 3 * MAX_LAG_S + LAG_AFTER_S:
            self.seen.popleft()
        if self.pending is not None and t + (self.late_s or 0.0) >= self.pending[2]:
            self.flush()

    def expect(self, t_ref: float, a_ref: float, due: float) -> None:
        """A controlled move is under way from the decision (t_ref, a_ref): fit its lag at `due` (times as shift()
        returned them); a fit still pending is made now."""
        self.flush()
        shift = self.late_s or 0.0
        self.pending = (t_ref + shift, a_ref, due + shift)

    def flush(self) -> None:
        """The pending fit, now."""
        if self.pending is None:
            return
        t_ref, a_ref, _ = self.pending
        self.pending = None
        lag = self.fit(t_ref, a_ref)
        if lag is not None:
            log.info("the slave's image followed the motor %.0f ms after the frames' pans say it moved", lag * 1e3)

    def fit(self, t_ref: float, a_ref: float) -> float | None:
        """The lag that best explains the decisions since (t_ref, a_ref) (see the module's text): it joins the
        latest fits, and where LATE_PAIRS of them agree the camera is named late. Returns the lag fitted (None:
        none, or under two steps)."""
        seen = [(tk, ak) for tk, ak in self.seen if tk > t_ref]
        if len(seen) < 4 or len(self.pans) < 2:
            return None
        tk = np.array([q[0] for q in seen])
        oldest = next(q[0] for q in self.pans if q[0] >= self.pans[-1][0] - 2 * MAX_LAG_S)
        if (lagged := self._lagged(tk, t_ref, t_ref, oldest)) is None:
            return None
        lags, moved = lagged
        da = np.array([q[1] for q in seen]) - a_ref
        res = da[None, :] + moved  # the target's own motion, at each lag: fitted as a rate and an acceleration
        span = np.ptp(moved, axis=1)
        # a lag counts where it shows the motor moving, and at rest again over the window's last decisions (a lag
        # that puts a move at the window's end leaves the target's fitted motion free to explain its part of it)
        counts = (span >= math.radians(MOVED_DEG)) & (
            np.abs(moved[:, -1] - moved[:, -3]) <= np.maximum(0.1 * span, math.radians(0.05)))
        if not counts.any():
            self.lags = (self.lags + [None])[-(LATE_PAIRS + 1):]
            return None
        tau = tk - t_ref
        x = np.stack([tau, tau * tau], 1)
        sse = ((res - res @ (x @ np.linalg.pinv(x)).T) ** 2).sum(axis=1)
        sse[~counts] = np.inf  # (a lag that moves every motion out of the window explains any image)
        k = int(np.argmin(sse))
        # the frames sample the motor's step and the image's: lags within a frame explain them alike; their middle
        near = np.flatnonzero(sse <= sse[k] + len(seen) * math.radians(LATE_NOISE_DEG) ** 2)
        near = near[(near >= near[near <= k].max() if (near <= k).any() else 0)]
        run = near[: int(np.argmax(np.diff(np.append(near, near[-1] + 2)) > 1)) + 1]
        best = float(lags[run].mean())
        fit = best >= 2 * LAG_STEP_S and (not math.isfinite(sse[0]) or sse[k] <= LATE_FIT * sse[0]) and \
            math.sqrt(sse[k] / len(seen)) <= max(math.radians(LATE_RMS_DEG), LATE_SHARE * float(np.ptp(moved[k])))
        return self.note(best if fit else None)

    def note(self, lag: float | None) -> float | None:
        """A lag fitted (None: none): it joins the latest fits, and where LATE_PAIRS of them agree the camera is named
        late. Returns it (None also under two steps: no lag)."""
        lag = lag if lag is not None and lag >= 2 * LAG_STEP_S else None
        self.lags = (self.lags + [lag])[-(LATE_PAIRS + 1):]
        if lag is None:
            return None
        agree = [x for x in self.lags if x is not None and abs(x - lag) <= LATE_AGREE_S]
        if len(agree) >= LATE_PAIRS:
            late = float(np.median(agree))
            if self.late_s is None or abs(late - self.late_s) > LATE_AGREE_S:
                log.warning("the slave's image follows the motor %.0f ms later than its frames say: taken as late "
                            "from now; set [camera] latency_s (`vergence latency` measures it) or stamp the images at "
                            "their exposure", late * 1e3)
            self.late_s = late
        return lag

    def probe(self, t_ref: float, a_ref: float) -> float | None:
        """A probe's r, the decision (t_ref, a_ref) the last before it, where the image may be late and the target
        moving: the decisions from MAX_LAG_S before it on are fitted as the motor's motion L earlier times -r (L in
        0..MAX_LAG_S, the one that fits best), plus the target's own motion as a constant, a rate and an acceleration
        over the rest before the probe and the probe. A probe's step is no smooth motion, so it tells r even where the
        target moved more than the probe meanwhile (the frames' level does not: a late camera's probes never cleared
        its fault while the target moved at 6 deg/s). A lag counts where the motor is at rest over the first and the
        last PROBE_REST decisions and moved MOVED_DEG between; None where none counts, or the fit leaves more than
        LATE_RMS_DEG (or LATE_SHARE of the motion), or where r says the image followed and a lag where it did not fits
        within LATE_NOISE_DEG as well (a reversed camera's probe, the target moving at 0.9 Hz, fitted r 0.67 at 150 ms
        and -0.52 at none: named late twice, which cleared its fault). Where r says the image followed, its lag is
        noted (note())."""
        seen = [(tk, ak) for tk, ak in self.seen if tk > t_ref - MAX_LAG_S]
        if len(seen) < 4 * PROBE_REST or len(self.pans) < 2:
            return None
        tk = np.array([q[0] for q in seen])
        if (lagged := self._lagged(tk, t_ref, tk[0], self.pans[0][0])) is None:
            return None
        lags, moved = lagged
        da = np.array([q[1] for q in seen]) - a_ref
        span = np.ptp(moved, axis=1)
        still = np.maximum(0.1 * span, math.radians(0.05))
        ends = (np.ptp(moved[:, :PROBE_REST], axis=1) <= still) & (np.ptp(moved[:, -PROBE_REST:], axis=1) <= still)
        tau = tk - t_ref
        fits = []
        for i in np.flatnonzero((span >= math.radians(MOVED_DEG)) & ends):
            x = np.stack([-moved[i], np.ones_like(tau), tau, tau * tau], 1)
            sol = np.linalg.lstsq(x, da, rcond=None)[0]
            fits.append((math.sqrt(float(((da - x @ sol) ** 2).sum()) / len(seen)), float(sol[0]), float(span[i]),
                         float(lags[i])))
        best = min(fits, default=None)
        if best is None or best[0] > max(math.radians(LATE_RMS_DEG), LATE_SHARE * best[2]):
            return None
        follows = FOLLOWS_MIN <= best[1] <= FOLLOWS_MAX
        if follows and any(not FOLLOWS_MIN <= f[1] <= FOLLOWS_MAX and f[0] - best[0] <= math.radians(LATE_NOISE_DEG)
                           for f in fits):
            return None  # a lag where the image did not follow fits as well (a moving target's): no verdict
        if follows:
            log.info("a probe's image followed the motor %.0f ms after the frames' pans say it moved", best[3] * 1e3)
            self.note(best[3])
        return best[1]
