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


def blueprint(rr):
    """The cockpit's layout: the two images with their boxes above, the curves below."""
    rrb = rr.blueprint
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(rrb.Spatial2DView(origin="rig/master", name="master (fovea)"),
                           rrb.Spatial2DView(origin="rig/slave", name="slave (match)")),
            rrb.Horizontal(rrb.BarChartView(origin="rig/correlation", name="layer 4 (winning row)"),
                           rrb.TimeSeriesView(origin="pan", name="pan, degrees"),
                           rrb.TimeSeriesView(origin="decision", name="decision")),
            row_shares=[3, 2]),
        rrb.TimeSeriesView(origin="depth", name="depth, m"), rrb.TimeSeriesView(origin="latency", name="latency"),
        rrb.TimeSeriesView(origin="workers", name="workers"),
        rrb.TextLogView(origin="motor", name="motor status (faults in red)"),
        collapse_panels=True)
