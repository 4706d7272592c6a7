"""The test tree mirrors the code: tests/vergence/ tests the library (vergence/*.py, motors/, sim/), tests/services/
the services (processes, the CLI, the deployment); tests/ itself holds the project-wide checks (lint, install,
layout) and the helpers the test files share (procs, emulators, middlebury, cdp, deploy_helpers, references,
samples), imported by their bare names.

pytest runs in importlib mode (pyproject.toml), so two test files may share a name in different folders (e.g.
tests/vergence/test_monitor.py and tests/services/test_monitor.py) and no test folder is a package; this file puts
tests/ on sys.path for the helpers. The real vergence and vergence_services are imported first: on sys.path,
the folder tests/vergence/ would otherwise be a namespace-package candidate for the name `vergence`."""

from __future__ import annotations

import sys
from pathlib import Path

import vergence  # noqa: F401  (before tests/ is on sys.path: see above)
import vergence_services  # noqa: F401

HERE = str(Path(__file__).resolve().parent)
if HERE not in sys.path:
    sys.path.insert(0, HERE)
