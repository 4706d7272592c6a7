"""Rerun set-up for the cockpit and every process of the project that logs to Rerun: the optional extra's import
with analytics off (import_rerun), the application id and the cockpit's layout (blueprint)."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

log = logging.getLogger("vergence.view")
APP_ID = "vergence"
INSTALL_HINT = "pip install 'vergence[view]' (in a checkout: pip install -e '.[view]')"


class MissingExtra(RuntimeError):
    """rerun-sdk is not installed."""


def analytics_off() -> None:
    """Make sure Rerun's anonymous usage analytics are off before any rerun code runs in this process.

    Rerun reads one switch, `analytics_enabled` in its per-user config (<XDG_CONFIG_HOME or ~/.config>/rerun/
    analytics.json), written by `rerun analytics disable`. When the config does not say disabled, this runs
    exactly that command of the wheel's own CLI, once (a head's network has no business calling out)."""
    base = os.environ.get("XDG_CONFIG_HOME") or os.path.join(os.path.expanduser("~"), ".config")
    path = Path(base) / "rerun" / "analytics.json"
    try:
        if json.loads(path.read_text()).get("analytics_enabled") is False:
            return
    except (OSError, ValueError, AttributeError):
        pass
    try:
        subprocess.run([sys.executable, "-m", "rerun_cli", "analytics", "disable"], stdin=subprocess.DEVNULL,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=60, check=True)
    except (OSError, subprocess.SubprocessError) as e:
        raise MissingExtra(f"cannot switch rerun's analytics off (`rerun analytics disable`): {e}") from None
    log.info("rerun analytics disabled for this user (%s)", path)


def import_rerun():
    """The rerun module with analytics off; MissingExtra (one line, how to install) without the extra."""
    try:
        import rerun_cli  # noqa: F401  (the wheel's CLI: analytics_off runs it)
    except ImportError:
        raise MissingExtra(f"rerun-sdk is not installed; install the viewer extra: {INSTALL_HINT}") from None
    analytics_off()
    import rerun as rr

    return rr


# the cockpit's views, one quantity each (time series: one axis, one unit): (origin, contents, name, y range)
SERIES = {
    "pan": ("pan", "$origin/**", "pan, degrees", None),
    "confidence": ("decision", ["$origin/confidence", "$origin/confident"], "confidence (0..1; confident 1/0)",
                   (0.0, 1.05)),
    "offset": ("decision/offset_px", "$origin", "offset, px", None),
    "window": ("decision/window", "$origin", "window, px", None),
    "depth": ("depth", "$origin/**", "depth, m", None),
    "latency": ("latency", "$origin/**", "latency, ms", None),
    "workers": ("workers", "$origin/**", "workers", None),
}


def blueprint(rr):
    """The cockpit's layout, every view open at once (no tabs): the two images with their boxes and the decision
    in large print above; the profile (relative to its best: the winner stands out), the pan and the offset in
    the middle; confidence, window, depth, latency and workers below, each on its own axis."""
    rrb = rr.blueprint

    def series(key):
        origin, contents, name, y = SERIES[key]
        return rrb.TimeSeriesView(origin=origin, contents=contents, name=name,
                                  axis_y=rrb.ScalarAxis(range=y) if y else None)

    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(rrb.Spatial2DView(origin="rig/master", name="master (fovea)"),
                           rrb.Spatial2DView(origin="rig/slave", name="slave (match)"),
                           rrb.Vertical(rrb.TextDocumentView(origin="rig/readout", name="decision"),
                                        rrb.TextLogView(origin="motor", name="motor status (faults in red)"),
                                        row_shares=[3, 2]),
                           column_shares=[3, 3, 2]),
            rrb.Horizontal(rrb.BarChartView(origin="rig/correlation",
                                            name="layer 4, winning row: 1 = best k, 0 = worst (x: offset, px)"),
                           series("pan"), series("offset"), column_shares=[2, 1, 1]),
            rrb.Horizontal(*(series(k) for k in ("confidence", "window", "depth", "latency", "workers"))),
            row_shares=[4, 3, 2]),
        collapse_panels=True)
