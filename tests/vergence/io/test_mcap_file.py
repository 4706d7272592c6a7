"""vergence.io.mcap_file's writer fails as vergence.io.recording's does (#29): one RecordingError naming the file."""

import pytest

pytest.importorskip("mcap", reason="MCAP recordings need the [ros2] extra (pip install -e '.[test]' brings it)")

from vergence.io.mcap_file import McapWriter  # noqa: E402
from vergence.io.recording import RecordingError  # noqa: E402


def test_a_full_disk_is_one_error_naming_the_file():
    w = McapWriter("/dev/full", rig="r")
    with pytest.raises(RecordingError, match=r"cannot write recording '/dev/full': No space left on device"):
        for i in range(2000):  # the writer buffers: the disk is found full at a flush
            w.write("vergence/r/frame", 10**18 + i, b"x" * 1000)
        w.flush()
    w.close()  # closing a failed file raises nothing more


def test_a_file_removed_while_recording_is_an_error(tmp_path):
    path = tmp_path / "run.mcap"
    w = McapWriter(path, rig="r")
    w.write("vergence/r/frame", 10**18, b"x")
    w.check()
    path.unlink()
    with pytest.raises(RecordingError, match="removed or replaced"):
        w.check()
    w.close()
