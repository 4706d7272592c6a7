"""Whether the slave's image follows the motor (issue #35): every decision is checked against the motor's own motion,
and a measurement that the motion cannot explain is a fault to name and hold on, never a target to chase.

The check. A confident decision at the slave's exposure t says the target's pan is z = pan + a (a: the angle of its
offset at the frame's focal length). Between a reference decision i and a newer one j the image moved by m = -(a_j -
a_i) while the motor moved p = pan_j - pan_i; if the image follows, m = p less the target's own motion, predicted from
the target's rate as learnt here (from consistent decisions while tracking or while the motor moved slowly: a
correction's image could teach the motor's own motion): r = (m + rate dt) / p is 1. Only where the motor moved faster
than any target (JUDGE_RATE_DEG_S beyond the learnt rate) and at least MIN_MOVE_DEG, with the pair's slack (the target's
acceleration, the offset's and the encoder's noise) small against it, must the image show most of that motion, whatever
the target did: such a pair is judged. r below FOLLOWS_MIN says the image did not follow (near 0: a frozen slave camera
or a slipping coupling; near -1: a camera turning the other way than the encoder says), r in FOLLOWS_MIN..FOLLOWS_MAX
that it did (r away from 1: the focal length is off by r); two that did not, in a row and agreeing, name the fault
("reversed" only where r is at most 2 x REVERSED_MAX and no lag explains it: Lag.unless_late). A pair short of the motor
at the learnt rate but not at the target's latest (the rate its last consistent pair showed: the learnt rate lags a
target that turns) is a doubt: it holds and probes as a fail does, and names nothing. Pursuit, slow moves and jumps of
the target are never judged. A byte-identical slave image after the motor moved IDENTICAL_MOVE_DEG is a frozen camera
outright; a background that did not move with it (vergence.head.scenery: r under STILL_MAX, no target rate in it) is a
pair that did not follow, in pursuit and at an undecided fovea too; one a late image would show too (Verdict.late) is a
doubt where the offset is under LEASH_DEG: it holds the chase a slipping camera starts (a correction's, not); and a
fovea's pair that did not follow, on a frame whose background turned with the motor, is a doubt (the fovea misread).

The leash. Until the image has been seen to follow (at the start, after a fault), no command goes further than
UNTRUSTED_DEG from the last pan where it followed (the anchor); a head held there probes back after BOUND_S, or as the
target turns back (its move), read less the target's motion as its offsets at rest show it (follows.Held). Once it has,
none goes further than LEASH_DEG past the pan the last consistent decision asked for (its z on at the learnt rate, a
cone past REF_MAX_S; wider by the target's motion since its newest image, SPEED_S); after a pair that did not follow,
none further from the anchor than the slave is, and after SUSPECT_S a probe toward the anchor confirms or clears it.

A fault: the slave goes back to the anchor (a search's candidate never seen to follow: where the search began) and
holds; the only moves are probes (PROBE_DEG from the anchor, one every PROBE_S, read less the target's own motion at the
anchor: follows.Held; none whose background did not move; at an undecided fovea, its background), and when the image
follows one again (a reversed camera's: one to either side in turn; a stalled motor: the encoder moves) the loop resumes
by itself. A frozen master camera (vergence.head.frozen) holds until it changes. A motor commanded STALL_ARM_DEG or more
away (past its dead band) that does not move for STALL_S is stalled, a search's commands too. A camera later than its
frames say is told by the moves of its faults and named (vergence.head.lag): naming it clears a frozen or reversed fault
(its image follows, later); from then on each frame goes through shift() first, and a pair's slack grows by the
uncertainty of the pans it reads. The library only: the reducer and `vergence sim` both run it (the Controller)."""

from __future__ import annotations

import logging
import math

from ..choices import Fault
from .focal import Focal
from .follows import ADVICE, FOLLOWS_MAX, FOLLOWS_MIN, SAME_PAN_DEG, Held, Seen, fail_kind, note, verdict
from .frozen import IDENTICAL_MOVE_DEG, Master, Slave
from .lag import LAG_AFTER_S, RETURN_FIT_S, Lag
from .scenery import STILL_MAX, Verdict
from .stall import Stall

__all__ = ["ADVICE", "Doubt", "Fault"]

log = logging.getLogger("vergence.doubt")

MIN_MOVE_DEG = 0.6  # a pair is decisive only where the motor moved at least this much
SLACK_DEG = 0.15  # the encoder's ticks and noise, and the offset's, in a pair
TARGET_ACCEL_DEG_S2 = 50.0  # what the target's predicted motion may be off by: accel x dt^2 / 2
DECISIVE = 0.35  # a pair is decisive where its slack is at most this fraction of the motor's motion
JUDGE_RATE_DEG_S = 36.0  # a pair is judged where the motor moved faster than this beyond the target's learnt rate
TRACKING_DEG = 0.3  # an offset below this: tracking, not correcting (the target's rate is learnt) ...
LEARN_RATE_DEG_S = 12.0  # ... as it is where the motor moved slower than this
FAILS = 2  # decisive pairs that did not follow, in a row, to name a fault
TARGET_RATE_DEG_S = 45.0  # a target's rate: what seems faster is a jump (a sine of 1.07 Hz, 0.3-1.0 m: 35 deg/s)
LONG_S = 0.07  # ... unless the rate over the consistent decisions of this long is not (one pair's noise)
LEAD_S = 0.1  # the leash widens by the target's motion over this (a set-point aims ahead of the last measurement)
SPEED_S, AGE_S = 1.0, 0.2  # ... and by its motion since the newest image (AGE_S of it at most), at the fastest rate
# learnt over SPEED_S (a 2 Hz sine seen 100 ms late turns within that: docs/FAULTS.md)
REF_MAX_S = 0.3  # a reference older than this is replaced by the newest decision (the leash's centre stays)
UNTRUSTED_DEG = 2.9  # the leash about the anchor until the image has been seen to follow
LEASH_DEG = 1.5  # the leash past the pan the last consistent measurement asked for
PROBE_DEG, PROBE_S = 0.5, 1.0  # during a fault: a probing move this far from the anchor, at most one a period
RETURN_S = 0.25  # a fault's move back to the anchor is sent again this long after it where the pan never got there
PROBE_MIN_DEG = 0.3  # a probe's pair counts when the motor moved at least this much
PROBE_FIT_S = 0.35  # a fault's probe whose image has not followed by this long after it is fitted (Lag.probe)
SUSPECT_S = 0.1  # a pair that did not follow holds the motor this long, then probes
BOUND_S = 0.2  # an untrusted head held at its leash's end this long probes (a slipping camera's runaway ends there)
BG_FOLLOWS = 2  # a fault's background verdicts in a row that moved with the motor clear it where the fovea is undecided
PRECISE = 0.2  # a decisive pair with at most this slack per motion counts for the focal length (docs/FAULTS.md)


class Doubt:
    """The check and its leash for one slave camera (see the module's text). observe() every decision,
    gate() every command; `fault` is the present fault (None: the image follows), `note` what to check."""

    def __init__(self):
        self.fault: Fault | None = None
        self.anchor = None  # the last pan at which the image followed (the first pan seen)
        self.home: float | None = None  # the anchor before a search's candidate, until its image is seen to follow
        self.trusted = False  # the image has been seen to follow since the start or the last fault
        self.ref = self.centre = None  # the next pair's reference decision; the last consistent one (leash's centre)
        # the target's rate, rad/s: learnt, the last pair's; (t, z) of LONG_S; (t, |rate|) as learnt over SPEED_S
        self.rate, self.trend, self.zs, self.speeds = 0.0, 0.0, [], []
        self.fails, self.t_fail = [], 0.0  # the kinds of the pairs that did not follow, and when the last one was
        self.focal = Focal()  # the focal length's ratio, from precise pairs that followed and from pursuit
        self.t_probe, self.probe_sign, self.fit_ref = None, 1.0, None  # a fault's last probe, its side, its fit's ref
        self.sides = (0.0, -math.inf)  # a reversed fault's last probe that followed: its side, when
        self.t_still, self.turned_now = -math.inf, False  # the last still background (not late); this one turned
        self.returned, self.held, self.still = None, Held(), Held()  # the move back's time; the target's motion at rest
        # each camera's images, frame to frame; a motor that does not follow its commands (its dead band: the Safety's)
        self.master, self.slave, self.stall = Master(), Slave(), Stall()
        self.t_bound: float | None = None  # since when an untrusted head is held at its leash's end; a probe's start
        self.probe_ref, self.probe_goal, self.turn = None, 0.0, False  # a probe's decision before it (None: none), its
        # goal, and whether it is a turn's (the controller's own move back from the leash's end: _stuck)
        self.t_held = self.last_seen = None  # since when a pair that did not follow holds the motor; the last decision
        self.faults = self.resumed = self.bg_follows = 0  # faults named so far, and cleared; see _probe_result
        self.t_last, self.fovea = None, None  # the last decision's exposure and fovea
        self.lag, self.u = Lag(), 0.0  # a camera later than its frames say; the last shift()'s pan's uncertainty

    @property
    def note(self) -> str:  # what to check (vergence.head.follows.note)
        return note(self.fault, self.focal.ratio, self.lag.late_s)

    def shift(self, t: float, pan: float) -> tuple[float, float]:
        """A frame as its stamp says it (t its slave's exposure, pan the slave's pan then) into (t, pan) as its image
        shows it: the same, or for a camera named late, lag.late_s earlier and the pan then. Every frame goes through
        here before observe() (the Controller does it): the pans kept are what a lag is fitted on."""
        t, pan, self.u = self.lag.shift(t, pan)
        return t, pan

    # -- decisions ---------------------------------------------------------------------------------------------------
    def observe(self, t: float, pan: float, a: float | None, slave: int | None = None,
                master: int | None = None, fovea: tuple[int, int] | None = None,
                background: Verdict | None = None, off_axis: float = 0.0) -> Fault | None:
        """One decided frame: t the slave's exposure (s), pan the slave's pan then (rad), a the angle of a
        confident decision's offset (None: no confident decision), slave and master the images' digests (None:
        unknown), fovea the master point it was decided at (a new one is a new target), background the verdict on
        the slave's background (vergence.head.scenery.Verdict; None: none). Returns the present fault."""
        if not (math.isfinite(t) and math.isfinite(pan)) or (self.t_last is not None and t <= self.t_last):
            return self.fault  # out of order or not a time: nothing to learn
        self.t_last = t
        if fovea != self.fovea:
            self.fovea, self.ref, self.centre = fovea, None, None
            self.rate, self.trend, self.zs, self.speeds = 0.0, 0.0, [], []
            self.focal.clear()
            self.held, self.still = Held(), Held()  # (the old point's offsets and the new one's are no target's motion)
        self.anchor = pan if self.anchor is None else self.anchor
        seen = self.master.see(t, master, fovea)
        if seen == "changed" and self.fault is Fault.MASTER_FROZEN:
            self._clear(t, self.anchor, "the master's images change again")
        elif seen == "frozen" and self.fault is None:
            self._raise(t, Fault.MASTER_FROZEN, f"the same master image for {t - self.master.same_since:.2f} s")
        frozen = self.slave.frozen(t, pan, slave, seen == "changed")
        if self.fault is None and (still := self.stall.stalled(t, pan)) is not None:
            self.anchor = pan  # the encoder tells the truth: the motor is here
            self._raise(t, Fault.STALLED, f"no move in {still:.2f} s")
        if background is not None and not background.late and background.r < STILL_MAX:
            self.t_still = t  # the background did not move with the motor: no probe over it follows
        # this frame's background turned with the motor: a fovea's pair that did not is the fovea's misreading (a doubt)
        self.turned_now = background is not None and background.turned
        if self.fault is not None:
            late = self.lag.late_s
            if a is not None and math.isfinite(a):
                self.lag.saw(t, a)
            self._probe_result(t, pan, a, frozen, background)
            if self.lag.late_s != late and self.fault in (Fault.SLAVE_FROZEN, Fault.REVERSED):  # (the image follows)
                self._clear(t, pan, f"its image follows the motor {self.lag.late_s * 1e3:.0f} ms later than its frames "
                                    "say")
            return self.fault
        if frozen:
            return self._fail(t, "frozen", f"a byte-identical slave image (a {IDENTICAL_MOVE_DEG} deg move or noise)")
        still = background is not None and background.r < STILL_MAX  # the scene behind did not move with the motor
        why = f"the background moved {background.r:.2f} x the motor" if still else ""
        if a is None or not math.isfinite(a):  # (the fovea undecided: its background still says it)
            return self._fail(t, fail_kind(background.r), why) if still and not background.late else self.fault
        now, late = Seen(t, pan, a, self.u), self.lag.late_s
        self.last_seen = now
        self.lag.saw(t, a)
        if self.lag.late_s != late:  # named late: the next frames are taken at their images' instants, no pair across
            self.ref, self.centre, self.fails = None, None, []
            return self.fault
        self.focal.off_axis = off_axis  # (the fovea's column off the principal point over the focal length told)
        self.focal.add(t, pan, a)
        if still and not background.late:
            return self._fail(t, fail_kind(background.r), why)
        if still and abs(a) <= math.radians(LEASH_DEG):  # (a late image's: near the target, a chase, not a correction)
            self._fail(t, "doubt", "as a late image's might not")  # (held; the pair may say more)
        if self.probe_ref is None or abs(pan - self.probe_ref.pan) < math.radians(SAME_PAN_DEG):
            self.still.add(t, a, pan)  # (a probe's frames that moved are read against the run before it)
        if self.probe_ref is not None:
            self._probed(t, now)
            return self.fault
        if self.fails and t - self.t_fail > REF_MAX_S:
            self.fails.clear()  # a suspicion nothing confirmed (a probe under way returned above)
        if self.ref is None or t - self.ref.t > REF_MAX_S:
            self.ref = now  # (the leash's centre stays where the last consistent measurement put it)
            self.centre = now if self.centre is None else self.centre
        else:
            self._pair(self.ref, now)
        return self.fault

    def _pair(self, i: Seen, j: Seen) -> None:
        """What the pair (i, j) says. Where the motor moved faster than any target (JUDGE_RATE_DEG_S, beyond the
        target's learnt rate) and far enough, the image must show most of that motion, whatever the target did: the
        pair is judged, the image followed (j's pan is verified) or did not (a fail). Otherwise nothing is judged:
        a pair that agrees with the motor and the learnt rate, one where the target moved by itself (or jumped), or
        one where the motor was no faster than a target, is consistent (the next reference and the leash's centre);
        a fast move not yet far enough keeps i as the reference."""
        dt, p = j.t - i.t, j.pan - i.pan
        pred = self.rate * dt  # the target's predicted motion
        moved = -(j.a - i.a) + pred  # the image's motion, the target's predicted motion taken out
        e = moved - p  # what the motor's motion does not explain
        slack = math.radians(SLACK_DEG + 0.5 * TARGET_ACCEL_DEG_S2 * dt * dt) + i.u + j.u
        own = abs(p - pred)  # the motor's motion beyond the target's predicted one
        big = abs(p) >= math.radians(MIN_MOVE_DEG) and slack <= DECISIVE * abs(p)
        # (a pair that did not follow arms the judge: the next one that moved far enough is judged, fast or not)
        if big and own >= math.radians(MIN_MOVE_DEG) and (self.fails or own >= math.radians(JUDGE_RATE_DEG_S) * dt):
            r = moved / p
            # short of the motor's motion also where the target went on at the rate its last decisions showed (a
            # learnt rate lags a target that turns; that one is learnt only where the motor could not teach it)
            if verdict(r) is not None:
                vetoed = verdict((moved - pred + self.trend * dt) / p) is None
                kind = "doubt" if vetoed or self.turned_now else self.lag.unless_late(fail_kind(r), i.t, j.t, moved)
                self._fail(j.t, kind, f"r = {r:.2f} over {math.degrees(p):.2f} deg")
                return
            if r <= FOLLOWS_MAX:
                self._followed(j, r, slack <= PRECISE * abs(p))
            self._consistent(i, j, learn=False)  # the motor was fast: its motion says nothing of the target's
        elif abs(e) <= slack + 0.5 * abs(p):
            if big and FOLLOWS_MIN <= moved / p <= FOLLOWS_MAX:  # (within the slack is not yet followed)
                self._followed(j, moved / p, False)
            elif self.trusted and not self.fails and abs(p) < math.radians(SAME_PAN_DEG):
                self.anchor = j.pan  # at rest where the image agrees: the pan to go back to
            self._consistent(i, j)
        elif abs(p) < 0.5 * abs(e) or abs(p) < math.radians(JUDGE_RATE_DEG_S) * dt:
            self._consistent(i, j)  # the target moved by itself (or jumped), or the motor was no faster than it

    def _followed(self, j: Seen, r: float, precise: bool) -> None:
        """A decisive pair that followed: j's pan is verified (a precise one's r counts toward the focal ratio)."""
        self.fails.clear()
        if precise:
            self.focal.pair(r)
        self.trusted, self.anchor, self.home = True, j.pan, None

    def _consistent(self, i: Seen, j: Seen, learn: bool = True) -> None:
        """j agrees with i (or the target moved by itself between them): j is the next reference and the leash's
        centre, and, while tracking (i's offset small) or where the motor moved slowly, the target's rate is learnt
        (a correction's image could teach the motor's own motion: a slipping coupling's does). A pair faster than any
        target is a jump (rates 0) unless the rate since LONG_S ago is not and the pair's is within TARGET_RATE_DEG_S
        of the one up to i (one pair's noise on a fast target: docs/FAULTS.md, "A step of the target is no rate")."""
        dt, fast = j.t - i.t, math.radians(TARGET_RATE_DEG_S)
        slow = abs(j.pan - i.pan) < math.radians(LEARN_RATE_DEG_S) * dt
        self.zs = [(t, z) for t, z in self.zs if j.t - t <= LONG_S]
        if dt > 0:
            v = (j.z - i.z) / dt
            if abs(v) > fast and self.zs and j.t - self.zs[0][0] >= 2 * dt:
                t0, z0 = self.zs[0]
                v = (j.z - z0) / (j.t - t0) if i.t <= t0 or abs(v - (i.z - z0) / (i.t - t0)) <= fast else v
            jump = abs(v) > fast
            self.trend = 0.0 if jump else v
            if learn and (slow or abs(i.a) < math.radians(TRACKING_DEG)):
                self.rate = 0.0 if jump else 0.5 * self.rate + 0.5 * v
                self.speeds = [q for q in self.speeds if j.t - q[0] <= SPEED_S] + [(j.t, abs(self.rate))]
        self.ref = self.centre = j
        self.zs.append((j.t, j.z))

    def _fail(self, t: float, kind: str, why: str) -> Fault | None:
        """A pair (or a probe) that did not follow, of `kind` ("frozen", "reversed", or "doubt": short of the motor's
        motion at the learnt rate, not at the target's latest; it holds and probes, and names nothing)."""
        if kind == "doubt" and self.fails and self.fails[-1] != kind:
            return self.fault  # (a pair that did not follow is not undone by one that may have)
        if self.fails and self.fails[-1] != kind:
            self.fails.clear()  # a fault is named by pairs that agree on it
        self.fails += [kind] * (2 if why.startswith("a byte-identical") else 1)  # (the bytes say it outright)
        self.t_fail = t
        if len(self.fails) >= FAILS and kind != "doubt":
            fault = Fault.REVERSED if kind == "reversed" else Fault.SLAVE_FROZEN
            self._raise(t, fault, why)
        return self.fault

    def _raise(self, t: float, fault: Fault, why: str) -> None:
        if fault in (Fault.SLAVE_FROZEN, Fault.REVERSED) and self.last_seen is not None:
            late = self.lag.late_s  # the image of the move that raised it, and of the move back: a late one shows both
            self.lag.expect(self.last_seen.t, self.last_seen.a, t + RETURN_FIT_S)
            if self.lag.late_s != late:  # the fit that was due named the camera late: that is what the pairs saw
                self.lag.pending, self.ref, self.centre, self.fails = None, None, None, []
                return
        if fault in (Fault.SLAVE_FROZEN, Fault.REVERSED) and not self.trusted and self.home is not None:
            self.anchor = self.home  # a search's candidate never seen to follow: back to where the search began
        self.fault, self.t_probe, self.returned, self.bg_follows, self.home = fault, t, None, 0, None
        self.trusted, self.ref, self.t_held, self.sides, self.fails = False, None, None, (0.0, -math.inf), []
        self.focal.clear()
        self.faults, self.probe_ref, self.t_bound = self.faults + 1, None, None  # (a probe of the leash or a suspicion)
        log.error("fault %s (%s): holding at %.2f deg; %s", fault, why,
                  math.degrees(self.anchor if self.anchor is not None else math.nan), ADVICE[fault])

    def _clear(self, t: float, pan: float, how: str) -> None:
        log.warning("fault %s cleared (%s): resuming from %.2f deg", self.fault, how, math.degrees(pan))
        self.fault, self.resumed = None, self.resumed + 1
        self.relocate(pan, trusted=True)

    def relocate(self, pan: float, trusted: bool = False) -> None:
        """A search found a candidate at `pan` (vergence.head.search), or a fault cleared there (trusted): the loop
        goes on from there as at the start, untrusted its image not yet seen to follow (the leash until a move does)."""
        self.home = None if trusted else self.anchor if self.home is None else self.home
        self.anchor, self.trusted, self.ref, self.centre = pan, trusted, None, None
        self.stall.reset()
        self.rate, self.trend, self.zs, self.speeds, self.fails = 0.0, 0.0, [], [], []
        self.probe_ref = self.t_bound = None

    def _probe_result(self, t: float, pan: float, a: float | None, frozen: bool, background: Verdict | None) -> None:
        """A frame during a fault: whether a probe's image followed, at the fovea, or where it is undecided (on an
        edge, a flat patch) from BG_FOLLOWS background verdicts in a row that moved with the motor (a probe's move)."""
        if self.fault is Fault.MASTER_FROZEN or self.anchor is None:
            return
        away = pan - self.anchor
        if self.fault is Fault.STALLED:
            if self.t_probe is not None and abs(away) >= math.radians(PROBE_MIN_DEG):
                self._clear(t, pan, "the motor moved again")
            return
        if background is not None:
            follows = not frozen and background.turned
            self.bg_follows = self.bg_follows + 1 if follows else 0
        if a is None or not math.isfinite(a):
            if background is not None and self.bg_follows >= BG_FOLLOWS:
                self._clear(t, pan, f"a probe moved the background r = {background.r:.2f}, the fovea undecided")
            return
        if abs(away) < math.radians(SAME_PAN_DEG):
            self.ref = Seen(t, pan, a)  # a fresh reference at the anchor for the next probe
            self.held.add(t, a)
            return
        if self.ref is None or frozen or abs(pan - self.ref.pan) < math.radians(PROBE_MIN_DEG):
            return
        rs = self.held.ratios(self.ref.t, self.ref.pan, self.ref.a, t, pan, a)  # both must follow
        if self.fit_ref is self.ref:
            return  # fitted, and it did not follow: the level, which the target's motion moves too, says no more
        if not all(FOLLOWS_MIN <= r <= FOLLOWS_MAX for r in rs) and t - self.ref.t >= PROBE_FIT_S:
            self.fit_ref = self.ref  # once a probe: its step against a late image and the target's own motion
            rs = rs if (fitted := self.lag.probe(self.ref.t, self.ref.a)) is None else (fitted,)
        if all(FOLLOWS_MIN <= r <= FOLLOWS_MAX for r in rs) and self.t_still <= self.ref.t:
            side, self.sides = self.sides, (math.copysign(1.0, away), t)
            if self.fault is Fault.REVERSED and (side[0] == self.sides[0] or t - side[1] > 1.5 * PROBE_S):
                return  # a reversed camera's image follows probes to both sides, one after the other (a false match
                # can follow one: an ambiguous fovea's two matches, 15 px apart, taken in turn)
            if self.fit_ref is not self.ref:  # (a fitted probe has noted its lag)
                self.lag.expect(self.ref.t, self.ref.a, t + LAG_AFTER_S)  # (then the image's whole step is seen)
            how = f"a probe of {math.degrees(pan - self.ref.pan):+.2f} deg moved the image r = {min(rs):.2f}"
            self._clear(t, pan, how)

    # -- commands ----------------------------------------------------------------------------------------------------
    def gate(self, pan: float, goal: float | None, t_now: float) -> float | None:
        """The command the doubt lets out for the controller's `goal` (None: no move) at the present `pan`."""
        if self.fault is not None:
            return self._during_fault(pan, t_now)
        if goal is None or not math.isfinite(goal):
            return None
        if self.trusted and self.centre is not None:
            c, fast = self.centre, max((v for t, v in self.speeds if self.t_last - t <= SPEED_S), default=0.0)
            dt, seen = max(0.0, t_now - c.t), min(max(0.0, t_now - self.t_last), AGE_S)
            centre = c.z + self.rate * min(dt, REF_MAX_S)  # (past REF_MAX_S the target went on or turned: a cone)
            lim = math.radians(LEASH_DEG) + abs(self.rate) * (LEAD_S + max(0.0, dt - REF_MAX_S)) + fast * seen
        elif self.anchor is not None:
            centre, lim = self.anchor, math.radians(UNTRUSTED_DEG)
            if (probe := self._stuck(pan, goal, t_now, lim)) is not None:
                return probe
        else:
            return goal
        goal = min(max(goal, centre - lim), centre + lim)
        if self.fails and self.anchor is not None and abs(goal - self.anchor) > abs(pan - self.anchor):
            goal = self._suspect(pan, t_now)  # a pair did not follow: no further from the last pan that did
        else:
            self.t_held = None
        self.stall.commanded(pan, goal, t_now)
        return goal

    def _stuck(self, pan: float, goal: float, t_now: float, lim: float) -> float | None:
        """A head not yet trusted, held at its leash's end for BOUND_S: a probe back toward the anchor (or None). Held
        there, a goal back inside the leash (the target turned) goes out, its move read as the probe (a turn's)."""
        if self.probe_ref is not None:
            return self._probing(t_now)
        end = abs(abs(pan - self.anchor) - lim) <= math.radians(SAME_PAN_DEG)
        if end and self.t_bound is not None and abs(goal - self.anchor) <= lim and self.last_seen is not None \
                and self.still.fits(pan):  # (the target's motion there fits: read against it, the move is a probe)
            return self._probe(pan, pan - self.anchor, t_now, turn=True)
        if abs(goal - self.anchor) <= lim or not end:
            self.t_bound = None
        elif self.t_bound is None:
            self.t_bound = t_now
        elif t_now - self.t_bound >= BOUND_S and self.last_seen is not None:
            return self._probe(pan, goal - self.anchor, t_now)
        return None

    def _suspect(self, pan: float, t_now: float) -> float:
        """A pair did not follow: held (later frames may confirm it), after SUSPECT_S a probe toward the anchor."""
        if (probe := self._probing(t_now)) is not None:
            return probe
        if self.t_held is None:
            self.t_held = t_now
        elif (t_now - self.t_held >= SUSPECT_S and self.last_seen is not None
              and abs(pan - self.anchor) >= math.radians(PROBE_MIN_DEG)):
            self.t_held = None
            return self._probe(pan, pan - self.anchor, t_now)
        return pan

    def _probe(self, pan: float, away: float, t_now: float, turn: bool = False) -> float | None:
        """A probe PROBE_DEG from `pan` toward the anchor (against `away`), read in _probed. Its goal (a turn's: None,
        the controller's goal goes out, and its move is read within PROBE_FIT_S, or the probe ends unread)."""
        self.probe_ref, self.t_bound, self.turn = self.last_seen, t_now, turn
        self.probe_goal = pan - math.copysign(math.radians(PROBE_DEG), away)
        return None if turn else self.probe_goal

    def _probing(self, t_now: float) -> float | None:
        """The goal of the probe under way; None where there is none (or a turn's) or its time (2 PROBE_S) is over."""
        if self.probe_ref is not None and t_now - self.t_bound >= (PROBE_FIT_S if self.turn else 2 * PROBE_S):
            self.probe_ref = self.t_bound = None
        return None if self.probe_ref is None or self.turn else self.probe_goal

    def _probed(self, t: float, now: Seen) -> None:
        """The image of a probe (a head not yet trusted, or held by a pair that did not follow): it followed (the
        head is trusted) or not (a fail; a doubt where the target's latest rate, not the learnt one, explains it)."""
        ref, p = self.probe_ref, now.pan - self.probe_ref.pan
        if abs(p) < math.radians(PROBE_MIN_DEG) or p * (self.probe_goal - ref.pan) <= 0:
            return  # (not the probe's move yet: a frame's pan can still be on its way the other way)
        r, rt = ((-(now.a - ref.a) + v * (now.t - ref.t)) / p for v in (self.rate, self.trend))
        if (m := self.still.motion(ref.t, now.t, ref.pan)) is not None:
            r = -(now.a - ref.a - m) / p  # the target's motion as its offsets at rest before the probe fit it
        self.probe_ref = self.t_bound = None
        if verdict(r) is None and r <= FOLLOWS_MAX and self.t_still <= ref.t:
            self._followed(now, r, False)
            self.ref = self.centre = now
        else:
            doubt = (verdict(rt) is None and rt <= FOLLOWS_MAX) or self.turned_now
            kind = fail_kind(max(r, -(now.a - ref.a) / p))  # (reversed only where a still target's reading says so too)
            kind = self.lag.unless_late(kind, ref.t, now.t, -(now.a - ref.a))
            self._fail(t, "doubt" if doubt else kind, f"a probe moved the image r = {r:.2f}")

    def _during_fault(self, pan: float, t_now: float) -> float | None:
        if self.fault is Fault.MASTER_FROZEN or self.anchor is None:
            return None
        far = abs(pan - self.anchor) > math.radians(PROBE_DEG + SAME_PAN_DEG)
        if self.returned is None or (far and t_now - self.returned >= RETURN_S):
            # back to the last pan at which the image followed (again where the Safety's max_step_deg cut it short)
            self.returned = t_now
            return self.anchor
        if not far:
            self.returned = math.inf  # back (a probe's overshoot is no move back cut short)
        if self.t_probe is not None and t_now - self.t_probe >= PROBE_S:
            self.t_probe, self.probe_sign = t_now, -self.probe_sign
            return self.anchor + self.probe_sign * math.radians(PROBE_DEG)
        if t_now - self.t_probe >= PROBE_S / 2 and abs(pan - self.anchor) > math.radians(SAME_PAN_DEG):
            return self.anchor  # a probe's time is over: back to the anchor
        return None

    def status(self) -> dict:
        """For the reducer's status: the fault (or None), what to check, and the counts."""
        return {"fault": self.fault and str(self.fault), "fault_note": self.note, "faults": self.faults,
                "faults_cleared": self.resumed,
                "focal_ratio": None if self.focal.ratio is None else round(self.focal.ratio, 3),
                "late_ms": None if self.lag.late_s is None else round(self.lag.late_s * 1e3, 1)}
