"""The play between the slave's motor and its camera (backlash), measured where the motor turns back, and taken out.

With play p, a camera driven through it stays put while the motor turns back across the gap: in steady motion it is
p / 2 behind the shaft, on the side the motor comes from. So each turn of the motor moves the target's pan as the
loop reads it (the shaft's pan plus the offset's angle) by p, a step the predictors chase for a period, and the
camera lags by the time the motor takes to cross the gap. The target's own turns look the same to the fovea (a fit
on the offsets in pursuit named play on clean sines: docs/FAULTS.md, "The play taken out, a third try"); the
background does not: it stands still, so its shift between two slave bands is the camera's own turn
(vergence.head.scenery.turn). So at each turn of the motor (its way in 3 x TRAVEL_DEG or more), read once the motor
is 2 x TRAVEL_DEG out of it or turns again (a loop 100 ms late hunts about the target's turns, its ways out 0.2-0.5
deg), each band on the way in TRAVEL_DEG or more from the turn before, and on the way out OUT_MIN_DEG to 2 x TRAVEL_DEG
from the turn, is read against the turn's band: on the way in the camera turned as the motor did, on the way out the
motor's turn less p (engaged on the other side). p = s (a way out's band's camera-less-motor turn - the way in's at
the same distance from the turn, on a robust line through the way in's: a focal length told wrong scales both alike),
s the motor's way into the turn, the median of the way out's; a band nearer the turn than p + MARGIN_DEG is left out
(the camera still in the gap: it reads its own way out). The turn's own band's error is in both, and so is a frame's
image a few ms off its pan (the motor's rate alike on either side). A noisy encoder's pans are its readings until the
shaft's model is fitted (vergence.head.shaft): read off them a turn read 0.24-0.3 deg of a play of 0.2, and named one
of 0.13-0.22 where there was none, so the turns wait for the model (`ready`) and are read at its pans (`repan`). Each
turn is a measurement; the median of the last KEEP (from the first turn read on: a target going to and fro in depth has
background at its far turns only, one turn in two, and waiting for three left the play in for 5-9 s) names the play
where it is NAME_DEG or more.

Taken out (`half` not 0): a frame's pan is the camera's, the shaft's through the play (the play operator: the camera
moves only where the shaft pushes it, half the play either side), and each goal for the camera is sent to the motor
half the play past it on the side the camera moves to (the operator's inverse). The Controller does both
(vergence.head.control)."""

from __future__ import annotations

import itertools
import logging
import math

import numpy as np

from .scenery import turn

__all__ = ["Play"]

log = logging.getLogger("vergence.play")

TRAVEL_DEG = 0.3  # the way in's bands are read this far or more from the turn before, to twice this from the turn (the
# largest play measured)
BACK_DEG = 0.25  # the motor's pans this far back from their furthest one way: a turn (less: its dither; whole-pixel
# decisions dither 0.1-0.2 deg about a target's turn)
REPLAY_S = 3.5  # the frames' pans kept to replay through a new play (the periodic predictor's span, and more)
KEEP_S = 2.0  # the bands kept (the way into a turn of a target going to and fro at 0.25 Hz is in the last 0.6 s)
NAME_DEG = 0.12  # the play named at this or more: under it, not told from an encoder's ticks (a Dynamixel's 0.088
# deg) read ahead of the shaft in motion (a clean sim read 0.01-0.06 deg, 0.09 with one band each side)
AGAIN_DEG = 0.03  # a named play changes where the median moves this much
SIDE = 1  # bands read on each side of a turn, at least (2 until session 54: a loop 100 ms late, before the play is
# taken out, leaves a turn's way out in one band, 0.25 to 0.6 deg in two frames, and read the play two turns later;
# one band's error, up to 0.09 deg on a clean sim, is the median's of KEEP to take out: 72 clean runs named none)
OUT_MIN_DEG = 0.15  # a turn's ways in and out are read from this far from it (a hunt's way out is often short)
MARGIN_DEG = 0.05  # ... the way out's by the bands where the play read is this much or more under their way out (nearer
# the turn than the play, the camera is still in the gap: such a band reads its own way out, not the play)
PAIR_DEG = 0.05  # the way in's line: the slopes of pairs of its bands this far apart or more
KEEP = 7  # the play named: the median of the last this many measurements
BACK_GOAL_DEG = 0.015  # a goal this far back from the furthest one sent, or less, keeps the side: a noisy encoder's
# set-points step back 0.006 deg in pursuit, and each side taken anew costs the motor the play's crossing twice
WITHDRAW_S = 1.0  # a fault named: the measurements this long before it are withdrawn (a stall's is named within 1 s)


class Play:
    """see() every slave band (its exposure, the shaft's pan then, its column profile, ...), pan() each frame's pan
    into the camera's, goal() each goal for the camera into the motor's; `half`: half the named play (rad, 0: none)."""

    def __init__(self):
        self.key = None  # the bands' (shape, fovea): a new one starts the turns anew
        self.way = 0.0  # the motor's way since the last turn (+1, -1; 0: not yet known)
        self.peak: tuple | None = None  # the furthest band that way since: (t, pan, profile)
        self.low: tuple | None = None  # (... and the least far, before a way is known)
        self.turns: list[tuple[float, float, np.ndarray]] = []  # the last two turns (t, pan, profile), oldest first
        self.bands: list[tuple[float, float, np.ndarray]] = []  # the bands of the last KEEP_S (t, pan, profile)
        self.pending: tuple | None = None  # (the last turn, the one before) until the motor is 2 x TRAVEL_DEG out
        self.due: list[tuple] = []  # (turn, the one before, its way out's end) to read once the pans are ready
        self.plays: list[float] = []  # the measurements (rad)
        self.when: list[float] = []  # ... and when each was read (s)
        self.half = 0.0
        self.cam: float | None = None  # the camera's pan as the frames' shaft pans push it
        self.sent: float | None = None  # the camera's pan the goals sent leave it at
        self.side = 0.0  # the side of the play the goals sent push the camera from (+1, -1; 0: none yet)
        self.far: float | None = None  # the goal sent furthest that side since the side was taken
        self.past: list[tuple[float, float, float]] = []  # (t, shaft, camera) of the frames of the last REPLAY_S

    def see(self, t: float, pan: float, profile: np.ndarray, key, focal_px: float, fovea_col: float,
            centre_col: float, repan=None, ready: bool = True) -> bool:
        """One slave band; True where the named play changed (what was learnt through the old one is off by the
        change). repan(t, pan): a band's pan as the shaft's model now has it (default: as seen); ready: False while
        the bands' pans may still be raw readings of a noisy encoder (the turns then wait, their bands kept)."""
        if not (math.isfinite(t) and math.isfinite(pan) and math.isfinite(focal_px) and focal_px > 0):
            return False
        band = (t, pan, profile)
        self.bands = [b for b in self.bands if t - KEEP_S <= b[0] < t] + [band]
        if key != self.key or (self.peak is not None and t <= self.peak[0]):
            self.key, self.way, self.peak, self.low, self.turns, self.pending = key, 0.0, band, band, [], None
            self.bands, self.due = [band], []
            return False
        back = math.radians(BACK_DEG)
        if self.way == 0.0:  # which way first: the first move of BACK_DEG from the furthest either way
            self.peak = band if pan > self.peak[1] else self.peak
            self.low = band if pan < self.low[1] else self.low
            if self.peak[1] - pan >= back:
                self.way, self.turns, self.peak = -1.0, [self.peak], band
            elif pan - self.low[1] >= back:
                self.way, self.turns, self.peak = 1.0, [self.low], band
            return False
        travel = math.radians(TRAVEL_DEG)
        if self.way * (pan - self.peak[1]) >= 0:  # (the last of a rest there)
            self.peak = band
        elif self.way * (self.peak[1] - pan) >= back:  # a turn: the motor came back BACK_DEG from its furthest that way
            self.turns, self.way, self.peak = (self.turns + [self.peak])[-2:], -self.way, band
            x = self.turns[-1]
            if self.pending is not None:  # (its way out ended here: a hunt about the target's turn)
                self.due, self.pending = self.due + [self.pending + (x[0],)], None
            # read once the motor is 2 x TRAVEL_DEG out of it or turns again, where the way into it was 3 x TRAVEL_DEG
            # or more
            if len(self.turns) == 2 and abs(x[1] - self.turns[0][1]) >= 3 * travel:
                self.pending = (x, self.turns[0])
        if self.pending is not None and _way(self.pending) * (self.pending[0][1] - pan) >= 2 * travel:
            self.due, self.pending = self.due + [self.pending + (t,)], None
        self.due = [d for d in self.due if t - d[1][0] <= KEEP_S]  # (its bands gone: unread)
        if not ready:
            return False
        changed = False
        for x, before, end in self.due:
            changed = self._read(x, before, end, t, repan, focal_px, fovea_col, centre_col) or changed
        self.due = []
        return changed

    def _read(self, x: tuple, before: tuple, end: float, t: float, repan, focal_px: float, fovea_col: float,
              centre_col: float) -> bool:
        """One turn x (the turn before it `before`, its way out seen up to `end`) read; True where the named play
        changed."""
        travel = math.radians(TRAVEL_DEG)
        into = _way((x, before))
        bands = [b for b in self.bands if before[0] < b[0] <= end]
        if repan is not None:  # (a band the model has no pan for is left out; the turn's own error is in all alike)
            bands = [(b[0], repan(b[0], b[1]), b[2]) for b in bands]
            bands, xp = [b for b in bands if b[1] is not None], repan(x[0], x[1])
            x = x if xp is None else (x[0], xp, x[2])
        inner, near = min(2 * travel, abs(x[1] - before[1]) - travel), math.radians(OUT_MIN_DEG)
        # each band OUT_MIN_DEG to 2 x TRAVEL_DEG from the turn (on the way in, TRAVEL_DEG or more from the turn before:
        # the camera half the play behind the shaft there, engaged: on the way in on one side, out on the other),
        # against the turn's band: the camera turned the motor's turn, then the motor's less the play. Each band of the
        # way out against the way in's line at its distance: the turn's own error (an encoder's whole ticks read its
        # furthest pan up to half a tick past the shaft's) is in both, and a focal length told wrong scales both alike
        # (only bands at the furthest the motor had come that way since the turn before: in a dither's dip the camera
        # may be anywhere in the play)
        sides: tuple[list[float], list[float]] = ([], [])
        way, furthest = into, -math.inf
        for b in bands:
            out = b[0] > x[0]
            if b[0] == x[0]:
                way, furthest = -way, -math.inf
            furthest = max(furthest, way * b[1])
            if way * b[1] >= furthest and b[0] != x[0] and near <= abs(b[1] - x[1]) <= (2 * travel if out else inner):
                moved = turn(x[2], b[2], b[1] - x[1], focal_px, fovea_col, centre_col, about=True)
                if moved is not None:
                    sides[out].append((moved - (b[1] - x[1]), abs(b[1] - x[1])))
        line, reads = _line(sides[0]), []
        if line is None:
            return False
        for m, d in sides[1]:
            q = into * (m - line(d))
            if q <= d - math.radians(MARGIN_DEG):
                reads.append(q)
        if len(reads) < SIDE:
            return False
        p = float(np.median(reads))
        log.debug("a turn at %.3f s: play %.3f deg", x[0], math.degrees(p))
        if not -travel <= p <= travel:
            return False
        self.plays, self.when = (self.plays + [p])[-KEEP:], (self.when + [t])[-KEEP:]
        return self._name()

    def _name(self) -> bool:
        """The play the measurements name (the median of them; none: 0); True where it changed."""
        med = float(np.median(self.plays)) if self.plays else 0.0
        half = med / 2 if med >= math.radians(NAME_DEG) else 0.0
        if abs(half - self.half) * 2 < math.radians(AGAIN_DEG) and (half == 0) == (self.half == 0):
            return False
        log.info("the play between the slave's motor and its camera: %.3f deg", math.degrees(2 * half))
        self.half = half
        return True

    def pan(self, t: float, shaft: float) -> float:
        """The camera's pan at t, the shaft at `shaft` (rad; every frame, in order): the play operator."""
        if not (math.isfinite(t) and math.isfinite(shaft)):
            return shaft
        c = self.cam = shaft if self.cam is None else _through(self.cam, shaft, self.half)
        self.past = [q for q in self.past if t - REPLAY_S <= q[0] < t] + [(t, shaft, c)]
        return c

    def peek(self, shaft: float) -> float:
        """The camera's pan the next frame's pan() gives for `shaft` (rad), nothing changed."""
        if self.cam is None or not math.isfinite(shaft):
            return shaft
        return _through(self.cam, shaft, self.half)

    def replay(self) -> list[tuple[float, float]]:
        """After the named play changed: the frames' shaft pans of the last REPLAY_S through it again, and by how much
        each one's camera pan moves [(t, change), ...] (rad): what was learnt from them moves with them."""
        c, moved = None, []
        for k, (t, shaft, was) in enumerate(self.past):
            c = shaft if c is None else _through(c, shaft, self.half)
            moved.append((t, c - was))
            self.past[k] = (t, shaft, c)
        if c is not None:
            self.cam = c
        return moved

    def goal(self, goal: float) -> float:
        """The motor's goal that leaves the camera at `goal` (rad): half the play past it on the way the camera goes
        from where the goals sent left it (the way turns where a goal is more than BACK_GOAL_DEG back from the
        furthest sent that way; a smaller step back leaves the camera at most that much past it)."""
        was = self.cam if self.sent is None else self.sent
        self.sent = goal
        if self.far is None:  # (no side yet)
            if was is not None and goal != was:  # (the same goal again: the same side)
                self.side, self.far = math.copysign(1.0, goal - was), goal
        elif self.side * (goal - self.far) >= 0:
            self.far = goal
        elif self.side * (self.far - goal) > math.radians(BACK_GOAL_DEG):
            self.side, self.far = -self.side, goal
        return goal + self.side * self.half

    def status(self) -> dict:
        """For the reducer's status: the play measured (deg; None before a turn was read; 0 where it is under
        NAME_DEG, and taken out from there on)."""
        return {"play_deg": None if not self.plays else round(math.degrees(2 * self.half), 3)}

    def lost(self, t: float | None = None) -> bool:
        """A fault or a search: the turns read so far say nothing of the next (a slipped camera is elsewhere). t: a
        fault's frame (s): the measurements of the WITHDRAW_S before it are withdrawn too (the lie may have been under
        way, not yet named, over them: a slip's first 0.2 s read as a play of 0.29 deg where there was none); True where
        the named play changed."""
        self.key, self.pending, self.due = object(), None, []
        if t is None or not self.when or self.when[-1] < t - WITHDRAW_S:
            return False
        keep = [k for k, w in enumerate(self.when) if w < t - WITHDRAW_S]
        log.info("a fault: the play's %d measurements of the last %.1f s withdrawn", len(self.when) - len(keep),
                 WITHDRAW_S)
        self.plays, self.when = [self.plays[k] for k in keep], [self.when[k] for k in keep]
        return self._name()


def _line(side: list[tuple[float, float]]):
    """The way in's measurements [(measurement, its distance from the turn), ...] as a function of the distance: a
    robust line (the median of the pairwise slopes, of pairs PAIR_DEG apart or more, and the median intercept; a
    focal length told wrong makes the measurement grow with the distance); None: no measurement."""
    if not side:
        return None
    apart = math.radians(PAIR_DEG)
    slopes = [(m2 - m1) / (d2 - d1) for (m1, d1), (m2, d2) in itertools.combinations(side, 2) if abs(d2 - d1) >= apart]
    k = float(np.median(slopes)) if slopes else 0.0
    c = float(np.median([m - k * d for m, d in side]))
    return lambda d: c + k * d


def _way(pending: tuple) -> float:
    """The way the motor came into a pending turn (x, the turn before it): +1, -1."""
    x, before = pending
    return math.copysign(1.0, x[1] - before[1])


def _through(camera: float, shaft: float, half: float) -> float:
    """The camera's pan once the shaft is at `shaft`, from `camera`, through a play of 2 x half: it moves only where
    the shaft pushes it."""
    return min(max(camera, shaft - half), shaft + half)
