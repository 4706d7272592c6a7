"""Lost, and found again (issue #35, item 3): a slave whose band holds no confident match searches instead of waiting.

Lost. The fovea has texture (the frames are not black or flat: those hold, as before) but no decision has been
confident for LOST_S of exposures: the target is outside the band (further off than the slave image reaches, at a
limit after a fault, or started there), or the slave looks at something else. Where the slave is at the pan the last
confident decision put the target at (converged there, or moved there since), HELD_S: a fovea whose matches are sparse
(near the image's edge, on a flat patch) converges, then decides confidently only now and then, and a search would
take it away from where it is right (a fixate's weakly textured new point, its one confident decision followed: a sweep
found a look-alike 19 deg away and the slave stayed there, 30-195 px off the truth).

The search. First back to the last pan at which the loop was converged (where the target was last seen), then a
sweep about it, nearer stops first, alternating sides (without such a pan: about the present one, toward the middle
of the range first), in steps of STEP_OF_BAND of the angle half the band spans (at 640 px and f 500 px,
32 degrees: 19-degree steps), so that each stop's band overlaps the last one's; the last stop on each side is the
limit itself. Every stop is inside the motor's limits (and the Safety bounds each command
as it bounds every other). At each stop the motor is given ARRIVE_S to get there (within ARRIVED_DEG, by the pan at
the exposures), then DWELL_S of decisions there. A sweep that found nothing goes back to where it began (a fovea the
slave cannot see, occluded behind a nearer object, has nothing to find: no sweep for ever over the whole range) and
waits there REST_S, twice that after the next one, up to REST_MAX_S, then sweeps again. The status counts those
sweeps (`sweeps_empty`): `vergence monitor` asks whether the point is visible to the slave at all. First of all it
looks, within a leash (the Controller's: 1.5 deg from the pan, and within 2.9 deg of the anchor where the image was
never seen to follow): a camera reversed from the start, or one frozen or slipping since, is named over that move by
its background, not 19 degrees away after a sweep's first step; once the background turned with the motor (or after
DWELL_S there) it sweeps.

Found. The first confident decision ends the search: the loop takes over from that pan, not yet trusted
(vergence.head.doubt's leash: the image must follow a first move, which tells a true candidate, whose offset changes
by the move, from a false one). The library only: the Controller runs it, for the reducer and `vergence sim` alike."""

from __future__ import annotations

import logging
import math

__all__ = ["Search"]

log = logging.getLogger("vergence.search")

LOST_S = 0.4  # textured frames and no confident decision for this long: lost ...
HELD_S = 3.0  # ... or this long where the last confident one said converged, at the pan it holds (a fovea whose
# matches are sparse, near the image's edge say, converges and then decides confidently only now and then)
ARRIVE_S = 1.0  # the motor's time to reach a stop (then the next one regardless: a stall is the doubt's to name)
ARRIVED_DEG = 0.5  # at a stop: the pan at the exposure within this of it
DWELL_S = 0.2  # the decisions taken at a stop, after it arrived
STEP_OF_BAND = 0.6  # the sweep's step: this fraction of the angle the band reaches
MIN_STEP_DEG = 2.0  # a band narrower than this still steps this far
MARGIN_PX = 16  # the band's reach: half the image width less this (a window's half)
REST_S, REST_MAX_S = 2.0, 16.0  # after a sweep that found nothing, back where it began this long (doubling), then again
LOOK_MIN_DEG = 0.6  # a look shorter than this tells nothing (the background's verdicts want a turn this long)


class Search:
    """observe() every decision of a slave whose image can follow the motor: the search's goal (radians) while it
    searches, else None. `searching` says whether it does; `searches` and `found` count them."""

    def __init__(self):
        self.t_lost: float | None = None  # the first textured, unconfident exposure since the last confident one
        self.blind = False  # the last frame's fovea had no texture (black or flat): it holds
        self.converged: float | None = None  # the last pan at which the loop was converged (within 1 px)
        self.seen: float | None = None  # the pan the last confident decision put the target at
        self.stops: list[float] = []
        self.goal: float | None = None
        self.t_goal = 0.0  # when the present stop was set
        self.t_arrived: float | None = None
        self.searching = False
        self.searches = 0
        self.found = 0
        self.empty = 0  # the present search's sweeps that found nothing (a point the slave cannot see: say so)
        self.step = math.radians(15.0)
        self._all: list[float] = []  # the whole sweep, to start over from
        self.centre, self.rest, self.t_rest = 0.0, REST_S, None  # where it began; the next rest; the present one's end
        self.look: float | None = None  # the first move of a head whose image has not yet been seen to follow

    def reset(self) -> None:
        """Forget being lost (a fault began: the doubt holds; or a new target)."""
        self.t_lost = None
        self.blind = False
        self._stop()

    def _stop(self) -> None:
        self.searching, self.stops, self.goal, self.t_arrived, self.empty, self.look = False, [], None, None, 0, None
        self.rest, self.t_rest = REST_S, None

    def observe(self, t: float, pan: float, confident: bool, textured: bool, offset_px: float, focal_px: float,
                width_px: int | None, lo: float, hi: float, leash: tuple[float, float] | None = None,
                at: float | None = None) -> float | None:
        """One decided frame (t: the slave's exposure, s; pan: its pan then, rad; lo, hi: the motor's soft limits,
        rad): the search's goal, or None (not lost, found, or held: black or flat frames). leash: the pans it may
        go to until its image has been seen to follow the motor (None: it has): a search then looks first, to the
        leash's end nearer the range's middle (or the other, LOOK_MIN_DEG away at least), and sweeps after DWELL_S
        there or as soon as the leash is None. at: the target's pan a confident decision says (pan plus its offset's
        angle; default pan + atan(offset_px / focal_px), the principal point's)."""
        if not (math.isfinite(t) and math.isfinite(pan)):
            return None
        self.blind = not confident and not textured  # (said in the status: the "abstain, and name it")
        if confident and math.isfinite(offset_px):
            ok = math.isfinite(focal_px) and focal_px > 0
            self.seen = at if at is not None else pan + math.atan(offset_px / focal_px) if ok else pan
            if abs(offset_px) <= 1.0:
                self.converged = pan
            if self.searching:
                self.found += 1
                log.warning("search: a candidate at %.2f deg (offset %+.1f px): the loop takes over", math.degrees(pan),
                            offset_px)
            self.t_lost = None
            self._stop()
            return None
        if not textured:
            self.t_lost = None  # black or flat frames: hold, as always
            self._stop()
            return None
        if self.t_lost is None:
            self.t_lost = t
        if not self.searching:
            held = self.seen is not None and abs(pan - self.seen) <= math.radians(ARRIVED_DEG)
            if t - self.t_lost < (HELD_S if held else LOST_S):
                return None
            self._start(t, pan, focal_px, width_px, lo, hi)
            ends = sorted((min(max(e, lo), hi) for e in leash or ()), key=lambda e: abs(e - (lo + hi) / 2))
            self.look = next((e for e in ends if abs(e - pan) >= math.radians(LOOK_MIN_DEG)), None)
        if leash is None and self.look is not None:
            self.look = self.goal = None  # the image followed: the sweep
        return self._next(t, pan)

    def _start(self, t: float, pan: float, focal_px: float, width_px: int | None, lo: float, hi: float) -> None:
        if width_px and math.isfinite(focal_px) and focal_px > 0:
            # half the band's span of offsets, wherever the fovea is (off centre, the band reaches further one way)
            reach = max(0.0, width_px / 2 - MARGIN_PX)
            self.step = max(math.radians(MIN_STEP_DEG), STEP_OF_BAND * math.atan(reach / focal_px))
        c = self.converged if self.converged is not None and lo <= self.converged <= hi else pan
        c = min(max(c, lo), hi)
        stops = [c] if abs(c - pan) > self.step / 2 else []
        up = [c + n * self.step for n in range(1, int((hi - c) / self.step) + 1)]
        down = [c - n * self.step for n in range(1, int((c - lo) / self.step) + 1)]
        if hi - (up[-1] if up else c) > self.step / 4:
            up.append(hi)
        if (down[-1] if down else c) - lo > self.step / 4:
            down.append(lo)
        # the side it is on first; from nowhere known, the side toward the middle of the range (where a head looks
        # parallel or converges: the pan zero of most heads)
        side = pan - c if c != pan else (lo + hi) / 2 - pan
        first, second = (up, down) if side >= 0 else (down, up)
        for n in range(max(len(up), len(down))):
            stops += [s[n] for s in (first, second) if n < len(s)]
        self.stops = [s for s in stops if abs(s - pan) > math.radians(ARRIVED_DEG)] or [c]
        self.searching, self.goal, self.t_arrived = True, None, None
        self.searches += 1
        log.warning("search: no confident match for %.1f s with a textured fovea: searching %d pans in steps of "
                    "%.1f deg from %.2f deg", t - self.t_lost, len(self.stops), math.degrees(self.step),
                    math.degrees(c))
        self._all, self.centre = list(self.stops), c

    def _next(self, t: float, pan: float) -> float:
        if self.look is not None and self.goal is None:
            self.goal, self.t_goal, self.t_arrived = self.look, t, None
        if self.goal is not None:
            if self.t_arrived is None and abs(pan - self.goal) <= math.radians(ARRIVED_DEG):
                self.t_arrived = t
            done = (self.t_arrived is not None and t - self.t_arrived >= DWELL_S) or \
                (self.t_arrived is None and t - self.t_goal >= ARRIVE_S)
            if not done:
                return self.goal
            self.look = None
        if not self.stops:  # the sweep is done: back where it began, a while, then again
            if self.t_rest is None:
                self.t_rest, self.rest = t + self.rest, min(2 * self.rest, REST_MAX_S)
                self.empty += 1
                log.warning("search: nothing found in a sweep of %d pans: back at %.2f deg, again in %.0f s",
                            len(self._all), math.degrees(self.centre), self.t_rest - t)
            if t < self.t_rest:
                self.goal = self.centre
                return self.goal
            self.stops, self.t_rest = list(self._all), None
        self.goal, self.t_goal, self.t_arrived = self.stops.pop(0), t, None  # (_start made every stop inside)
        return self.goal

    def status(self) -> dict:
        """The reducer's status fields: searching, searches (begun), found (ended by a confident decision),
        sweeps_empty (the present search's sweeps of the range that found nothing), and no_texture (the last frame's
        fovea had none: a black or flat image, which holds)."""
        return {"searching": self.searching, "searches": self.searches, "found": self.found,
                "sweeps_empty": self.empty, "no_texture": self.blind}
