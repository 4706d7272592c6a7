"""Whether the slave's background moves with the motor (issue #35): the fovea's image motion mixes the camera's turn
with the target's own motion (pursuit and a slipping camera that chases a moving target look alike there), but a turn
of the camera turns every point of its image by that angle, whatever its depth (a column u px off the principal point
shifts by f tan(atan(u/f) + turn) - u: 1 + (u/f)^2 times the axis's f tan(turn)), where a target moves only its own
pixels. So between two frames whose pans differ by MIN_MOVE_DEG or more (at most MAX_DT_S apart), the slave band's
TILE px tiles off the fovea's and its neighbours' must turn by the motor's turn. Each tile's shift is read on the
bands' column profiles (the mean of each column), searched over +-(the motor's shift + SLACK_PX), and taken as the
turn it shows at its column; the largest group of tiles that turned alike (MIN_TILES or more, within AGREE_PX on the
axis: the background turns as one, a target's zoom spreads its tiles) gives r = its median turn / the motor's: 1 for
a camera that follows, 0 for one that does not (frozen, a slipping coupling), -1 for one that turns against the
encoder; no target rate in it. MAX_DT_S is 0.6 s: a slip that the target's learnt rate drives on at 1-2 deg/s turns
the motor MIN_MOVE_DEG within it (at 0.3 s it was never read, docs/FAULTS.md). A live band is read against live ones
only: a frozen camera's repeats (the band before, byte for byte) show the pan at which it froze, not their own; a
repeat against any band (it did not move).

Only r under STILL_MAX says the image did not follow (a target that fills the band read 0.27-0.48 on clean runs,
docs/FAULTS.md); where the motor's turn between the instants up to LATE_S before the two frames explains the shift
seen, it is a late Verdict: a camera whose images are that much later than its frames say shows that (a turn that
just began, none yet; told by vergence.head.lag), and so does a slipping camera's chase in its first LATE_S.
vergence.head.doubt takes a verdict as a pair that did not follow, a late one as a doubt (it holds the turn, names
nothing). A smaller min_move_deg reads a fault's probes (PROBE_DEG). The pans must be ones the motor reported (or
interpolated between two reports): one told past its newest report, extrapolated at its last rate, misses a turn
since, by degrees where a loop swings on such a late camera, and is not brought (the Frame's pan_guessed; the sim
loop likewise). The library only: the Controller runs it for the reducer (each Frame's slave band, as it arrives)
and for `vergence sim` (its own)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .follows import FOLLOWS_MAX, FOLLOWS_MIN

__all__ = ["Background", "Verdict", "central", "profile", "tile_shifts", "turn"]

MIN_MOVE_DEG = 0.6  # the pans of a verdict's two frames at least this far apart (as the doubt's decisive pairs)
MAX_DT_S = 0.6  # ... and at most this far apart in time
TILE, SLACK_PX = 32, 8  # a tile's width; the search beyond the motor's shift
ROWS = 29  # a band's central rows read (the base window's band): a band's height follows the fovea's window, which can
# grow and shrink frame to frame, and each new height started the bands anew (Tsukuba, seed 7404: no verdict in 2 s)
MATCHED = 0.9  # a tile's best normalised correlation at least this (a match without doubt) ...
TEXTURE = 1.0  # ... and its column profile's standard deviation at least this (grey levels)
MIN_TILES = 6  # background tiles that moved alike, for a verdict ...
AGREE_PX = 1.0  # ... within this of each other
STILL_MAX = 0.25  # r below this: the background did not move with the motor
LATE_S = 0.1  # a still background that the motor's turn up to this earlier explains is no verdict (a late image)
GAP_S = 0.015  # at most one verdict this often (at 250 Hz one frame in four pays the 0.1-0.2 ms of a verdict)


def turn(before: np.ndarray, after: np.ndarray, motor: float, focal_px: float, fovea_col: float,
         centre_col: float, about: bool = False) -> float | None:
    """How far the background turned (rad) from the column profile `before` to `after`, the motor having turned
    `motor` (rad) between them: the median turn of the largest group of tiles off the fovea that turned alike (None:
    fewer than MIN_TILES). Searched over +-(the motor's shift + SLACK_PX), or with `about` over SLACK_PX about the
    motor's shift (a turn of many pixels, known to a few: a texture's repeats are then no match)."""
    shift = focal_px * math.tan(motor)
    shifts = (tile_shifts(before, after, SLACK_PX, int(round(shift))) if about else
              tile_shifts(before, after, int(abs(shift)) + SLACK_PX))
    if not shifts:
        return None
    # the tiles off the fovea's and its neighbours' (the target there moves as it moves, not as the camera turns),
    # each as the turn it shows: a column u px off the axis moves f (tan(atan(u/f) + turn) - u/f), 1 + (u/f)^2
    # times the axis's (a 2.9 deg turn 35 deg off the scene's middle spread the tiles' shifts over 3.6 px)
    mid, s = np.array(shifts).T
    mid = mid + TILE / 2  # (each tile's middle column)
    keep = np.abs(mid - fovea_col) > 1.5 * TILE
    u, s = mid[keep] - centre_col, s[keep]
    scenery = np.sort(np.arctan((u + s) / focal_px) - np.arctan(u / focal_px))
    # the most of them that turned alike (within AGREE_PX on the axis): the background turns as one, a target's
    # zoom spreads
    ends = np.searchsorted(scenery, scenery + AGREE_PX / focal_px, side="right")
    i = int(np.argmax(ends - np.arange(scenery.size))) if scenery.size else 0
    if scenery.size == 0 or ends[i] - i < MIN_TILES:
        return None
    return float(np.median(scenery[i:ends[i]]))


def central(band: np.ndarray) -> np.ndarray:
    """A band's central ROWS rows (all where it has fewer)."""
    k = (band.shape[0] - ROWS) // 2
    return band[k:k + ROWS] if band.shape[0] > ROWS else band


def profile(band: np.ndarray) -> np.ndarray:
    """A band's column profile: the mean of each column (a horizontal shift moves it as it moves the rows)."""
    return band.mean(axis=0, dtype=np.float32)


def tile_shifts(b: np.ndarray, a: np.ndarray, reach: int, centre: int = 0) -> list[tuple[int, float]]:
    """Per TILE px tile of the profile `a` (the tiles from column reach - centre on, reach + centre short of its end),
    the shift s (px, sub-pixel) with a[c:c+T] ~ b[c+s:c+s+T] for |s - centre| < reach, b the profile of a band before:
    [(the tile's first column, s), ...] for the tiles with texture matched without doubt; every tile and shift in one
    normalised product."""
    starts = np.arange(max(0, reach - centre), min(a.size, b.size - centre) - TILE - reach + 1, TILE)
    if starts.size == 0:
        return []
    tiles = np.lib.stride_tricks.sliding_window_view(a, TILE)[starts]  # (tiles, T)
    tiles = tiles - tiles.mean(axis=1, keepdims=True)
    norm = np.linalg.norm(tiles, axis=1)
    wins = np.lib.stride_tricks.sliding_window_view(b, TILE)[starts[:, None] + centre + np.arange(-reach, reach + 1)]
    wins = wins - wins.mean(axis=2, keepdims=True)  # (tiles, shifts, T)
    r = np.einsum("it,ist->is", tiles, wins) / (norm[:, None] * np.linalg.norm(wins, axis=2) + 1e-9)
    n, m = r.shape
    k = r.argmax(axis=1)
    kk = np.clip(k, 1, m - 2)
    best, lo, hi = (r[np.arange(n), j] for j in (k, kk - 1, kk + 1))
    d = 2 * best - lo - hi
    shift = k - reach + centre + np.where(d > 0, 0.5 * (hi - lo) / np.where(d > 0, d, 1.0), 0.0)
    # flat, no match, or at the search's edge: none
    ok = (norm >= TEXTURE * math.sqrt(TILE)) & (best >= MATCHED) & (k > 0) & (k < m - 1)
    return list(zip(starts[ok].tolist(), shift[ok].tolist()))


class Verdict(NamedTuple):
    """r: the background's shift over the motor's (1: it follows, 0: it did not move, -1: against); late: it did not
    move, but the motor's turn up to LATE_S earlier explains that (a late image shows it so): hold, name nothing."""
    r: float
    late: bool = False

    @property
    def turned(self) -> bool:
        """The background turned with the motor (r in FOLLOWS_MIN..FOLLOWS_MAX, not a late image's)."""
        return not self.late and FOLLOWS_MIN <= self.r <= FOLLOWS_MAX


@dataclass
class _Band:
    t: float
    pan: float
    profile: np.ndarray
    repeat: bool = False  # the band before's, repeated (a frozen camera's): no image of its instant


class Background:
    """The slave bands of the last MAX_DT_S (their exposures and pans); see() one more, a verdict or None."""

    def __init__(self):
        self.bands: list[_Band] = []
        self.key = None  # (the band's shape, the fovea): a new one starts anew
        self.t_verdict = -math.inf  # the last verdict's exposure
        self.pans: list[tuple[float, float]] = []  # (t, pan) of every band of the last MAX_DT_S + LATE_S, any key

    def see(self, t: float, pan: float, band: np.ndarray, focal_px: float, fovea_col: float,
            key=None, min_move_deg: float = MIN_MOVE_DEG, centre_col: float | None = None,
            seen: np.ndarray | None = None) -> Verdict | None:
        """One frame's slave band (t its exposure, s; pan the slave's then, rad; fovea_col the fovea's column in
        it; centre_col the principal point's, default its middle; seen its central rows' profile where the caller
        has it): r of its background against the latest earlier band at least MIN_MOVE_DEG away in pan (None: no
        verdict)."""
        if not (math.isfinite(t) and math.isfinite(pan) and focal_px > 0) or band.ndim != 2:
            return None
        band = central(band)
        key = (band.shape, key)
        if self.pans and t <= self.pans[-1][0]:
            self.pans = []
        if key != self.key or not self.pans:
            self.bands, self.key, self.t_verdict = [], key, -math.inf
        self.bands = [b for b in self.bands if t - b.t <= MAX_DT_S + LATE_S]
        # the pans outlive a new key (a window grown and back, a new fovea): what the motor did is what it did
        self.pans = [p for p in self.pans if t - p[0] <= MAX_DT_S + LATE_S] + [(t, pan)]
        seen = profile(band) if seen is None else seen
        repeat = bool(self.bands) and np.array_equal(seen, self.bands[-1].profile)
        # a live band is read against live ones: a frozen camera's repeats are no image of their instants (a frozen
        # one against them all: it did not move)
        before = next((b for b in reversed(self.bands) if t - b.t <= MAX_DT_S and (repeat or not b.repeat)
                       and abs(pan - b.pan) >= math.radians(min_move_deg)), None)
        self.bands.append(_Band(t, pan, seen, repeat))
        if before is None or t - self.t_verdict < GAP_S:
            return None
        self.t_verdict = t
        moved = turn(before.profile, self.bands[-1].profile, pan - before.pan, focal_px, fovea_col,
                     (band.shape[1] - 1) / 2 if centre_col is None else centre_col)
        if moved is None:
            return None
        r = moved / (pan - before.pan)
        return Verdict(r, r < STILL_MAX and self._late(before, self.bands[-1], moved, focal_px))

    def _late(self, i: _Band, j: _Band, moved: float, focal_px: float) -> bool:
        """Whether the motor's turn between the instants up to LATE_S before i's and j's exposures explains the
        background's turn `moved` (rad; within AGREE_PX on the axis, or a quarter of the turn): a camera whose images
        are that much later than its frames say shows that (a turn that just began, none yet). Also where the pans
        are not known that far back."""
        ts, ps = [p[0] for p in self.pans], [p[1] for p in self.pans]
        if ts[0] > i.t - LATE_S:
            return True
        slack = max(AGREE_PX / focal_px, 0.25 * abs(j.pan - i.pan))
        return any(abs(float(np.interp(j.t - lag, ts, ps) - np.interp(i.t - lag, ts, ps)) - moved) <= slack
                   for lag in (LATE_S / 3, 2 * LATE_S / 3, LATE_S))

