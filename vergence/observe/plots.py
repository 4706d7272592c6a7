"""Every PNG figure of the project, drawn with matplotlib on its Agg canvas (no display, no global backend).

- run_figure / plot_run: a closed loop on a still scene (`vergence sim --plot`): the slave's pan per frame
  with the converged pan and its +-1 px band, and the layer-4 profiles y(k) of the first and the last frame
  with their winners and the centre neuron k_c (the paper's figure 5);
- tracking_figure / plot_tracking: a target moving in depth (`vergence sim --motion ... --plot`): the
  converged pan (truth) and the slave's pan over time, and the error in pixels with the +-1 px band;
- monitor_figure / monitor_png: what `vergence monitor --png` writes: the latest profile y(k) with the
  winner and the centre marked, and the recent pan and commanded targets.

Each *_figure returns the matplotlib Figure, so a caller (a test) reads back what was plotted: every line
carries a gid ("pan", "truth", "band+", "profile_first", "winner", ...; see each function) and
Line2D.get_xdata()/get_ydata() give its values. matplotlib is imported inside the functions: importing
this module (or the services that may draw) costs nothing until a figure is drawn.
"""

from __future__ import annotations

import io
import warnings
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from .monitor import Snapshot
    from ..sim.loop import Step

__all__ = ["run_figure", "plot_run", "tracking_figure", "plot_tracking", "monitor_figure", "monitor_png",
           "save_png", "png_bytes", "lines"]

# the colours of the former drawings: pan blue, truth green, error/centre red, first profile orange
BLUE, GREEN, RED, ORANGE, GREY, BLACK = "#1f5fc8", "#289628", "#dc2828", "#ff8c00", "#8c8c8c", "#000000"


def _figure(width: int, height: int, dpi: float = 100.0) -> Figure:
    """An empty figure of exactly width x height pixels on an Agg canvas (layout by constrained_layout)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def png_bytes(fig: Figure) -> bytes:
    """The figure as PNG bytes, at its own size in pixels."""
    buf = io.BytesIO()
    with warnings.catch_warnings():  # a very small picture (160 x 120) is cramped, and still written
        warnings.filterwarnings("ignore", "constrained_layout not applied")
        fig.savefig(buf, format="png", dpi=fig.dpi)
    return buf.getvalue()


def save_png(fig: Figure, path: str) -> None:
    """Write the figure as a PNG file (OSError naming the path when it cannot be written)."""
    data = png_bytes(fig)
    try:
        with open(path, "wb") as f:
            f.write(data)
    except OSError as e:
        raise OSError(f"cannot write {path}: {e.strerror}") from e


def lines(ax: Axes) -> dict[str, object]:
    """The axes' lines by gid (what the figure shows, for a test or a caller)."""
    return {ln.get_gid(): ln for ln in ax.get_lines() if ln.get_gid()}


def _band(ax: Axes, centre: float, half: float, label: str) -> None:
    """Two thin grey dashed lines centre +- half (gids band+ / band-), one legend entry."""
    ax.axhline(centre + half, color=GREY, lw=1, ls="--", label=label, gid="band+")
    ax.axhline(centre - half, color=GREY, lw=1, ls="--", gid="band-")


def _style(ax: Axes, title: str, xlabel: str, ylabel: str, legend: bool = True) -> None:
    ax.set_title(title, loc="left", fontsize="medium")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, color="#e4e4e4", lw=0.6)
    ax.set_axisbelow(True)
    if legend:
        ax.legend(loc="best", fontsize="small", framealpha=0.85)


# ---- vergence sim --plot: a still scene ------------------------------------------------------------------
def run_figure(steps: list[Step], one_px_deg: float, width: int = 900, height: int = 760) -> Figure:
    """The pan trajectory on top (gids: pan; truth, band+, band- when the converged pan is known), the
    layer-4 profiles of the first and the last frame below (profile_first, profile_last, winner_first,
    winner_last, centre)."""
    from matplotlib.ticker import MaxNLocator

    from ..network.decide import centre_offset

    fig = _figure(width, height)
    top, bot = fig.subplots(2, 1)
    frames = np.array([s.frame for s in steps], float)
    pans = np.array([s.pan_deg for s in steps], float)
    dots = dict(marker="o", ms=4) if len(steps) < 60 else {}
    top.plot(frames, pans, color=BLUE, lw=1.5, label="slave pan", gid="pan", **dots)
    truth = np.array([s.truth_pan_deg for s in steps], float)  # changes where --fixate-at moves the fovea
    known = bool(np.isfinite(truth).any())
    if known:
        many = np.unique(truth[np.isfinite(truth)]).size > 1
        steps_style = dict(drawstyle="steps-post") if many else {}
        top.plot(frames, truth, color=GREEN, lw=1.2, gid="truth", **steps_style,
                 label="converged pan" if many else f"converged pan {truth[0]:+.3f}°")
        top.plot(frames, truth + one_px_deg, color=GREY, lw=1, ls="--", gid="band+", **steps_style,
                 label=f"±1 px (±{one_px_deg:.3f}°)")
        top.plot(frames, truth - one_px_deg, color=GREY, lw=1, ls="--", gid="band-", **steps_style)
    top.xaxis.set_major_locator(MaxNLocator(integer=True))
    _style(top, "Slave pan per frame" + ("" if known else " (converged pan unknown)"),
           "frame", "pan (deg)")

    first, last = steps[0], steps[-1]
    kc = centre_offset(first.scores.size + first.window - 1, first.window)
    bot.plot(np.arange(first.scores.size), first.scores, color=ORANGE, lw=1.2,
             label=f"frame {first.frame}: y(k)", gid="profile_first")
    bot.plot(np.arange(last.scores.size), last.scores, color=BLUE, lw=1.2,
             label=f"frame {last.frame}: y(k)", gid="profile_last")
    bot.axvline(first.k, color=ORANGE, lw=1.5, ls=":", zorder=3, label=f"k* frame {first.frame} = {first.k}",
                gid="winner_first")
    bot.axvline(last.k, color=BLUE, lw=1.5, ls=":", zorder=3, label=f"k* frame {last.frame} = {last.k}",
                gid="winner_last")
    bot.axvline(kc, color=RED, lw=1, ls="--", zorder=3, label=f"k_c = {kc}", gid="centre")
    bot.set_xlim(0, max(1, first.scores.size - 1, last.scores.size - 1))
    _style(bot, "Layer 4: y(k), first and last frame (the paper's figure 5)", "k (offset of the slave window)",
           "y(k)")
    return fig


def plot_run(steps: list[Step], path: str, one_px_deg: float, width: int = 900, height: int = 760) -> Figure:
    """run_figure written to path as a PNG; returns the figure."""
    fig = run_figure(steps, one_px_deg, width, height)
    save_png(fig, path)
    return fig


# ---- vergence sim --motion ... --plot: a target moving in depth --------------------------------------------
def tracking_figure(steps: list[Step], title: str = "", first: int = 0, width: int = 900,
                    height: int = 700) -> Figure:
    """Truth and pan over time on top (gids truth, pan), the error f tan(pan - truth) in pixels below from
    frame `first` on (error, zero, band+, band-), its RMS and maximum in the title."""
    from ..sim.loop import tracking_error

    fig = _figure(width, height)
    top, bot = fig.subplots(2, 1, sharex=True)
    t = np.array([s.t_s for s in steps], float)
    pans = np.array([s.pan_deg for s in steps], float)
    truth = np.array([s.truth_pan_deg for s in steps], float)
    err = np.array([s.error_px for s in steps], float)
    # the truth wide and light under the pan: where they agree, the blue line runs inside the green one
    top.plot(t, truth, color=GREEN, lw=4, alpha=0.45, solid_capstyle="butt", label="truth (converged pan)",
             gid="truth")
    top.plot(t, pans, color=BLUE, lw=1.2, label="slave pan", gid="pan")
    _style(top, f"Slave pan and truth: {title}" if title else "Slave pan and truth", "time (s)", "pan (deg)")
    top.xaxis.set_tick_params(labelbottom=True)

    e = tracking_error(steps, first)
    t0 = steps[first].t_s if first < len(steps) else 0.0
    bot.axhline(0.0, color=BLACK, lw=0.8, gid="zero")
    _band(bot, 0.0, 1.0, "±1 px")
    bot.plot(t[first:], err[first:], color=RED, lw=1.2, label="error (px)", gid="error")
    _style(bot, f"Error f tan(pan - truth) from {t0:g} s: RMS {e['rms_px']:.2f} px, max {e['max_px']:.2f} px",
           "time (s)", "error (px)")
    return fig


def plot_tracking(steps: list[Step], path: str, title: str = "", first: int = 0, width: int = 900,
                  height: int = 700) -> Figure:
    """tracking_figure written to path as a PNG; returns the figure."""
    fig = tracking_figure(steps, title, first, width, height)
    save_png(fig, path)
    return fig


# ---- vergence monitor --png: the live profile and the pan history --------------------------------------------
def monitor_figure(s: Snapshot, width: int = 960, height: int = 720) -> Figure:
    """The latest profile y(k) against k (gid profile) with the winner (winner, a red line, and winner_dot on
    the curve) and the centre neuron (centre, blue dashed) on top, over 3/5 of the height; below it the
    slave pan (pan) and the commanded targets (target, orange dots) against the seconds before now.
    The layout and fonts scale with the size (designed at 960 x 720)."""
    from .screen import _winning_row, fixation_line

    # fonts shrink with the picture down to 60 % (below 576 x 432 the text takes more of it)
    fig = _figure(width, height, dpi=100.0 * max(0.6, min(width / 960, height / 720)))
    legend = width >= 480 and height >= 360  # below, a legend would hide the curves: the titles say it all
    top, bot = fig.subplots(2, 1, height_ratios=[3, 2])
    p = s.profile
    if p is None:
        top.text(0.5, 0.5, "no profile", color=RED, fontsize="x-large", ha="center", va="center",
                 transform=top.transAxes)
        top.set_xticks([])
        top.set_yticks([])
        top.set_title(fixation_line(s, "±"), loc="left", fontsize="medium")
    else:
        y = _winning_row(p)
        k = np.arange(len(y))
        top.plot(k, y, color=BLACK, lw=1, label="y(k), the winner's row", gid="profile")
        top.axvline(p.k, color=RED, lw=1, label=f"winner k*={p.k} ({p.k_sub:.2f})", gid="winner")
        top.plot([p.k], [float(y[p.k])], "o", mfc="none", mec=RED, mew=2, ms=8, gid="winner_dot")
        top.axvline(p.k_centre, color=BLUE, lw=1, ls="--", label=f"centre k_c={p.k_centre}", gid="centre")
        top.set_xlim(0, max(1, len(y) - 1))
        side = {-1: "left", 0: "centre", 1: "right"}.get(p.direction, "?")
        _style(top, f"layer 4, frame {p.frame}: winner k*={p.k} ({p.k_sub:.2f}), centre k_c={p.k_centre}, "
               f"{side} {p.magnitude} px, confidence {p.confidence:.3f}{'' if p.confident else ' (abstains)'}\n"
               f"{fixation_line(s, '±')}", "k (offset in the slave band)", "y(k)", legend)

    span = max([a for a, _ in s.pan_history + s.target_history] + [1.0])
    if s.pan_history or s.target_history:
        if s.pan_history:
            a, v = np.array(s.pan_history, float).T
            bot.plot(-a, np.degrees(v), color=BLUE, lw=2, marker="o" if len(a) == 1 else None, label="slave pan",
                     gid="pan")
        if s.target_history:
            a, v = np.array(s.target_history, float).T
            bot.plot(-a, np.degrees(v), "o", color=ORANGE, ms=3, label="commanded target", gid="target")
        lo, hi = bot.get_ylim()
        if hi - lo < 0.1:  # a still slave: show 0.1 degrees, not the float noise
            mid = (lo + hi) / 2
            bot.set_ylim(mid - 0.05, mid + 0.05)
        bot.ticklabel_format(axis="y", useOffset=False)
        none = "" if s.target_history else " (no command in it)"
        _style(bot, f"slave pan (blue) and commanded target (orange), last {span:.1f} s{none}",
               "seconds before now", "pan (deg)", legend)
    else:
        bot.text(0.5, 0.5, "no pan history", color=GREY, ha="center", va="center", transform=bot.transAxes)
        bot.set_title(f"slave pan (blue) and commanded target (orange), last {span:.1f} s", loc="left",
                      fontsize="medium")
        bot.set_xlabel("seconds before now")
        bot.set_ylabel("pan (deg)")
        bot.set_yticks([])
    bot.set_xlim(-span, 0)
    return fig


def monitor_png(s: Snapshot, width: int = 960, height: int = 720) -> bytes:
    """monitor_figure as PNG bytes of exactly width x height pixels."""
    return png_bytes(monitor_figure(s, width, height))
