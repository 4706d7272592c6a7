"""`vergence up` and `vergence router` on a port that is already taken: a clear error, nothing started."""

from __future__ import annotations

import subprocess
import sys

from procs import Procs


def test_busy_port_is_refused_with_a_hint(tmp_path):
    with Procs(tmp_path) as P:
        P.router()
        up = subprocess.run([sys.executable, "-m", "services.cli", "up", "--listen", P.endpoint],
                            capture_output=True, text=True, timeout=30)
        assert up.returncode == 2 and f"{P.endpoint} is already in use" in up.stderr
        assert "started" not in up.stderr  # no child was started
        router = subprocess.run([sys.executable, "-m", "services.cli", "router", "--listen", P.endpoint],
                                capture_output=True, text=True, timeout=30)
        assert router.returncode == 2
        assert router.stderr.startswith("vergence router: cannot start on")
        assert "Address already in use" in router.stderr
        assert "Traceback" not in router.stderr
