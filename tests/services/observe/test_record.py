"""`vergence record` as a user runs it without a router (issue #28): it gives up within its wait or its
--duration, whichever is shorter, in one line, exit 1, and leaves no file. Recording a running pipeline, a full
disk and a slow one: tests/services/clients/test_replay.py (recorded, then replayed)."""

from __future__ import annotations

import pytest

from procs import gives_up_without_a_router

pytestmark = pytest.mark.slow  # every test here runs a real process


@pytest.mark.parametrize("argv,within", [(["--duration", "1"], 1), (["--wait", "1"], 1)], ids=["duration", "wait"])
def test_record_without_a_router_gives_up_and_leaves_no_file(tmp_path, argv, within):
    """It ran past --duration, waiting for a router forever, and left a 65-byte header claimed as a recording."""
    path = tmp_path / "x.vrec"
    gives_up_without_a_router("record", str(path), *argv, within=within)
    assert not path.exists()
