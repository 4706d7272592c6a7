"""The terminal screen of `vergence monitor`, drawn from a monitor.Snapshot (a pure function of it: tested without
Zenoh, as the model is): the rates and latencies, the latest profile as bars with the winner and the
centre marked, the decision, the fixated point's depth, the motor's pans and faults, the pan history, the workers
and the processes' statuses; ANSI colours optional, every line fitted to the terminal's width."""

from __future__ import annotations

import math
import re
import time

import numpy as np

from ..wire import keys
from ..wire import messages as m
from .monitor import Snapshot
from ..network.retina import CLIP_WARN
from ..wire.status import Status

__all__ = ["render_text", "profile_bars", "sparkline", "timeline", "fixation_line"]


# ---- the terminal screen -------------------------------------------------------------------------------
_BLOCKS = " ▁▂▃▄▅▆▇█"
_SPARK = "▁▂▃▄▅▆▇█"
RED, CYAN, GREEN, YELLOW, DIM, BOLD, RESET = ("\x1b[31m", "\x1b[36m", "\x1b[32m", "\x1b[33m", "\x1b[2m",
                                              "\x1b[1m", "\x1b[0m")


def _winning_row(p: m.Profile) -> np.ndarray:
    """The layer-4 row of the winner: y(v*, k) for all k (the only row without vertical search)."""
    y = p.array()
    vi = p.v_shift + (p.rows - 1) // 2
    return y[min(max(vi, 0), p.rows - 1)]


def profile_bars(p: m.Profile, columns: int, rows: int = 10) -> tuple[list[str], int, int]:
    """The winner's layer-4 row as `rows` lines of `columns` block characters (column c holds the best
    y(k) of its k-range), scaled from the row's minimum (empty) to its maximum (full). Returns the lines
    (top first), the winner's column and the centre's column."""
    y = _winning_row(p)
    kk = len(y)
    columns = max(1, min(columns, kk))
    edges = np.linspace(0, kk, columns + 1).astype(int)
    vals = np.array([y[a:max(b, a + 1)].max() for a, b in zip(edges[:-1], edges[1:])])
    lo, hi = float(y.min()), float(y.max())
    frac = (vals - lo) / (hi - lo) if hi > lo else np.ones_like(vals)
    eighths = np.rint(frac * rows * 8).astype(int)
    lines = []
    for r in range(rows - 1, -1, -1):
        cells = np.clip(eighths - r * 8, 0, 8)
        lines.append("".join(_BLOCKS[c] for c in cells))

    def col(k: int) -> int:
        return int(min(columns - 1, max(0, np.searchsorted(edges, k, side="right") - 1)))

    return lines, col(p.k), col(p.k_centre)


def _deg(rad: float) -> str:
    return "   --   " if not math.isfinite(rad) else f"{math.degrees(rad):+7.3f}°"


def _ms(x: float) -> str:
    return "--" if not math.isfinite(x) else f"{x:.2f} ms"


def sparkline(values: list[float], columns: int, lo: float | None = None, hi: float | None = None) -> str:
    """values resampled onto `columns` cells of ▁..█ between lo and hi (default: their min and max)."""
    if not values or columns < 1:
        return ""
    v = np.asarray(values, dtype=np.float64)
    idx = np.linspace(0, len(v) - 1, min(columns, len(v))).round().astype(int)
    v = v[idx]
    lo = float(v.min()) if lo is None else lo
    hi = float(v.max()) if hi is None else hi
    f = (v - lo) / (hi - lo) if hi > lo else np.full_like(v, 0.5)
    return "".join(_SPARK[int(round(x * 7))] for x in np.clip(f, 0, 1))


def fixation_line(s: Snapshot, pm: str = "±") -> str:
    """Where the fovea is (the latest frame's, else the latest decision's) and the fixated point's depth."""
    p = s.profile
    at = s.fovea or ((p.x, p.y) if p is not None and p.x >= 0 else None)
    where = f"fovea ({at[0]}, {at[1]})" if at else "fovea ?"
    if p is not None and p.x >= 0 and at != (p.x, p.y):
        where += f" (the profile's: ({p.x}, {p.y}))"
    if p is None or not p.converged:
        return f"{where}   not converged, no depth"
    if not math.isfinite(p.depth_m):
        return f"{where}   converged, no depth"
    return f"{where}   converged, depth {p.depth_m:.3f} m {pm} {p.depth_sigma_m:.3f}"


def _paint(color: bool):
    """c(code, text): the text in an ANSI colour when color, else as it is."""
    def c(code: str, text: str) -> str:
        return f"{code}{text}{RESET}" if color else text

    return c


def render_text(s: Snapshot, width: int = 100, bar_rows: int = 10, color: bool = True) -> str:
    """The monitor's screen as text lines (ANSI colours when color). The profile bars mark the winner
    (red, ▲) and the centre neuron (cyan, ┴); everything else is a labelled figure."""
    width = max(40, width)
    out = _head_lines(s, color)
    out.append("")
    out += _profile_lines(s, width, bar_rows, color)
    out.append("")
    out += _motor_lines(s, width, color)
    out.append("")
    out += _process_lines(s, width, color)
    return "\n".join(part for line in out for part in _fit(line, width))


def _head_lines(s: Snapshot, color: bool) -> list[str]:
    """The title, the rates, the counts with the drops and the latencies."""
    c = _paint(color)
    out = []
    when = time.strftime("%H:%M:%S", time.localtime(s.now_ns / 1e9))
    bad = sum(s.malformed.values())
    title = f"vergence monitor · rig {s.rig or '*'} · {when}"
    out.append(c(BOLD, title) + (c(RED, f"   malformed {bad}") if bad else "   malformed 0"))
    out.append(f"rate   frames {s.frames_per_s:7.1f}/s   profiles {s.profiles_per_s:7.1f}/s   "
               f"commands {s.commands_per_s:7.1f}/s")
    pct = 100.0 * s.dropped / s.dropped_of if s.dropped_of else 0.0
    how = {"reducer": f" of {s.dropped_of}, reducer counters", "gaps": ", id gaps"}.get(s.dropped_from, "")
    drop = f"dropped {s.dropped} ({pct:.2f} %{how})"
    out.append(f"seen   frames {s.frames}   profiles {s.profiles}   commands {s.commands}   "
               + (c(YELLOW, drop) if s.dropped else drop))
    out.append(f"latency capture→command p50 {_ms(s.latency_p50_ms)}  p99 {_ms(s.latency_p99_ms)}  "
               f"(n {s.latency_n}, last {s.window_s:g} s)   capture→profile p50 {_ms(s.reduce_p50_ms)}  "
               f"p99 {_ms(s.reduce_p99_ms)}")
    return out


def _profile_lines(s: Snapshot, width: int, bar_rows: int, color: bool) -> list[str]:
    """The latest profile: its decision, the fixation and the winner's row as bars."""
    c = _paint(color)
    p = s.profile
    if p is None:
        return [c(DIM, "no profile yet (waiting on %s)" % keys.profile(s.rig or "*"))]
    side = {-1: "◀ left", 0: "● centre", 1: "right ▶"}.get(p.direction, "?")
    conf = c(GREEN, "moves") if p.confident else c(YELLOW, "abstains")
    age = (s.now_ns - p.t_capture_ns) / 1e9 if p.t_capture_ns else math.nan
    out = [f"profile frame {p.frame}  (age {age:.1f} s, w {p.window}, K {p.width - p.window + 1}, "
           f"rows {p.rows}, v {p.v_shift:+d}, workers {len(p.workers)})",
           f"decision k*={p.k} (sub-px {p.k_sub:.2f})  k_c={p.k_centre}  offset {p.offset_px:+.2f} px  "
           f"{side} {p.magnitude} px   confidence {p.confidence:.3f} {conf}   texture {p.texture:.1f}",
           fixation_line(s)]
    try:
        y = _winning_row(p)
        lines, wc, cc = profile_bars(p, width - 8, bar_rows)
    except (m.MessageError, ValueError) as e:
        out.append(c(RED, f"profile not drawable: {e}"))
        return out
    return out + _bar_lines(p, y, lines, wc, cc, color)


def _bar_lines(p: m.Profile, y: np.ndarray, lines: list[str], wc: int, cc: int, color: bool) -> list[str]:
    """The bars labelled with the row's maximum and minimum, the winner's and the centre's marks, the k axis."""
    out = []
    ytop, ybot = f"{y.max():.0f}", f"{y.min():.0f}"
    for i, line in enumerate(lines):
        if line[cc] == " ":  # the centre column stays visible where its bar is low
            line = line[:cc] + "┊" + line[cc + 1:]
        label = ytop if i == 0 else ybot if i == len(lines) - 1 else ""
        if color:
            line = "".join(
                (RED + ch + RESET) if j == wc else (CYAN + ch + RESET) if j == cc else ch
                for j, ch in enumerate(line))
        out.append(f"{label:>7} {line}")
    marks = [" "] * len(lines[0])
    marks[cc] = "┴"
    marks[wc] = "▲"
    mark = "".join(marks)
    if color:
        mark = mark.replace("▲", RED + "▲" + RESET).replace("┴", CYAN + "┴" + RESET)
    out.append(" " * 8 + mark)
    kk = len(y)
    axis = f"k=0{' ' * max(1, len(lines[0]) - len(str(kk - 1)) - 5)}k={kk - 1}"
    out.append(" " * 8 + axis)
    out.append(" " * 8 + f"▲ winner k*={p.k}   ┴ centre k_c={p.k_centre}")
    return out


def _motor_lines(s: Snapshot, width: int, color: bool) -> list[str]:
    """The pans (measured, goal, target, limits), the motor's status and faults, the truth, the pan history."""
    c = _paint(color)
    out = []
    lim = ""
    if math.isfinite(s.min_rad) and math.isfinite(s.max_rad):
        lim = f"   limits {math.degrees(s.min_rad):+.1f}°..{math.degrees(s.max_rad):+.1f}°"
    status = s.motor_status or "no motor state"
    if s.at_limit:
        status += " AT LIMIT"
    out.append(f"pan {_deg(s.pan_rad)}   goal {_deg(s.goal_rad)}   target {_deg(s.target_rad)}{lim}   "
               f"status {status}")
    if s.motor_status in ("disconnected", "absent"):  # a fault, not a state: say it in red, with why
        out.append(c(RED, f"MOTOR {s.motor_status.upper()}: commands are not executed; {s.motor_note[:width]}"))
    if math.isfinite(s.truth_rad):
        out.append(f"truth {_deg(s.truth_rad)} (the simulator's converged pan at the last capture; that frame's "
                   f"pan is {s.truth_error_px:+.2f} px off it)")
    if s.tracking_n:
        out.append(f"tracking over the last {s.window_s:g} s: the frames' pans are {s.tracking_rms_px:.2f} px RMS "
                   f"off the truth (max {s.tracking_max_px:.2f} px, {s.tracking_n} frames)")
    pans, truths = [v for _, v in s.pan_history], [v for _, v in s.truth_history]
    if pans:  # the truth's history on the same scales, under the pans': the slave following the target
        lo, hi = min(pans + truths), max(pans + truths)
        span = max(a for a, _ in s.pan_history + s.truth_history)
        scale = f"{math.degrees(lo):+.2f}°..{math.degrees(hi):+.2f}°, {span:.0f} s"
        out.append(f"pan history   ({scale}) " + timeline(s.pan_history, width - 45, span, lo, hi))
        if truths:
            out.append(f"truth history ({scale}) " + timeline(s.truth_history, width - 45, span, lo, hi))
    return out


def timeline(history: list[tuple[float, float]], columns: int, span: float, lo: float, hi: float) -> str:
    """(seconds before now, value) pairs as `columns` cells of ▁..█ between lo and hi, the oldest `span` seconds
    at the left and now at the right, each cell the latest value of its time (a cell with none the one before it;
    blank before the first): two histories of one span line up in time."""
    if not history or columns < 1:
        return ""
    cells: list[float | None] = [None] * columns
    for age, v in sorted(history, reverse=True):  # oldest first: a cell keeps its latest value
        i = min(columns - 1, max(0, int((1.0 - age / span) * columns))) if span > 0 else columns - 1
        cells[i] = v
    for i in range(1, columns):
        if cells[i] is None:
            cells[i] = cells[i - 1]
    return "".join(" " if v is None else sparkline([v], 1, lo, hi) for v in cells)


def _process_lines(s: Snapshot, width: int, color: bool) -> list[str]:
    """The workers and their shards, the other live processes, their statuses' figures, the malformed kinds."""
    c = _paint(color)
    out = []
    if s.workers:
        ws = "   ".join(f"{w} k {r[0]}..{r[1] - 1}" if r else f"{w} (no shard yet)"
                       for w, r in s.workers.items())
        out.append(f"workers {len(s.workers)}: {ws}")
    else:
        out.append(c(YELLOW, "workers 0: none alive"))
    others = [f"{role} {', '.join(ids)}" for role, ids in s.alive.items() if role != "worker"]
    out.append("alive  " + ("   ".join(others) if others else "(no other process seen)"))
    for name, d in s.status.items():
        out += _status_lines(name, d, c)
    for kind, n in sorted(s.malformed.items()):
        out.append(c(RED, f"malformed {kind}: {n} (last: {s.last_error.get(kind, '')[:width - 30]})"))
    return out


def _status_lines(name: str, d: Status, c) -> list[str]:
    """A process's status: a reducer's gatherer counters, a capture's clipped shares (warned when high)."""
    out = []
    g = d.gatherer() if name.startswith("reducer/") else {}
    if (fault := d.fault()) is not None:  # the loop holds: say it first, in red, with what to check
        out.append(c(RED, f"FAULT {fault[0]}: {fault[1]}"))
    elif (late := d.number("late_ms", 0.0, 1000.0)) is not None:  # a camera the loop named late (vergence.head.lag)
        out.append(c(YELLOW, f"camera late: the slave's image follows the motor {late:.0f} ms later than its frames "
                             "say; set [camera] latency_s (`vergence latency` measures it)"))
    if (note := d.search_note()) is not None:  # lost: the slave sweeps its range (vergence.head.search)
        out.append(c(YELLOW, note))
    if (note := d.texture_note()) is not None:  # black or flat frames: it holds
        out.append(c(YELLOW, note))
    if g:
        pending = d.number("pending", 0, 2 ** 53)
        out.append(f"{name}: " + "  ".join(f"{k} {g[k]}" for k in ("frames", "complete", "dropped",
                                                                   "superseded", "late", "unexpected")
                                           if k in g) + f"  pending {'?' if pending is None else int(pending)}")
    shares = d.clipped() if name.startswith("capture/") else {}
    if shares:
        line = f"{name}: clipped " + ", ".join(f"{cam} {100 * v:.0f} %" for cam, v in sorted(shares.items()))
        if any(v >= CLIP_WARN for v in shares.values()):
            out.append(c(YELLOW, line + " of the fovea's rows: set both cameras' exposure alike"))
        else:
            out.append(line)
    return out


_ANSI = re.compile(r"\x1b\[[0-9;]*m")
FIELD_SEP = "   "  # between the fields of a line: where a line too wide for the terminal is broken


def _fit(line: str, width: int) -> list[str]:
    """A screen line as lines of at most `width` visible characters (ANSI codes do not count), broken between
    its fields (FIELD_SEP), the continuation indented by 2; a single field wider than that stays whole."""
    def vis(t: str) -> int:
        return len(_ANSI.sub("", t))

    if vis(line) <= width:
        return [line]
    parts = line.split(FIELD_SEP)
    out, cur = [], parts[0]
    for part in parts[1:]:
        if vis(cur) + len(FIELD_SEP) + vis(part) <= width:
            cur += FIELD_SEP + part
        else:
            out.append(cur)
            cur = "  " + part.lstrip()
    out.append(cur)
    return out
