"""Record a running pipeline, then replay its frames through new workers and a new reducer: the profiles
are the recorded ones, bit for bit (real processes, a real router, bounded waits)."""

from __future__ import annotations

import pytest

from procs import Procs, textured_pair, wait_for
from vergence.messages import Frame, Profile
from vergence.recording import read

pytestmark = pytest.mark.slow  # every test here runs real processes

FRAMES = 20


@pytest.fixture
def pair(tmp_path):
    cfg = tmp_path / "settings.toml"
    cfg.write_text("[network]\nmax_window = 0\n[capture]\npreview_hz = 0\n[reducer]\ndeadline_ms = 1000\n")
    return textured_pair(tmp_path, seed=5), str(cfg)


def test_record_then_replay_gives_the_same_profiles(tmp_path, pair):
    source, cfg = pair
    path = tmp_path / "run.vrec"
    with Procs(tmp_path) as P:
        P.router()
        first = [P.start("worker-a", "worker", "--config", cfg), P.start("worker-b", "worker", "--config", cfg),
                 P.start("reducer", "reducer", "--config", cfg)]
        s = P.session()
        P.wait_alive(s, "worker", 2)
        P.wait_alive(s, "reducer", 1)
        rec = P.start("record", "record", str(path), "--duration", "6")
        P.wait_alive(s, "record", 1)
        wait_for(lambda: "recording vergence/" in rec.text(), 15, "the recorder's subscription", logs=P.logs)
        cap = P.start("capture", "capture", "--source", source, "--rate", "20", "--frames", str(FRAMES),
                      "--config", cfg)
        assert cap.wait(20) == 0, cap.tail()
        assert rec.wait(20) == 0, rec.tail()
        header, records, truncated = read(path)
        assert header["rig"] == P.rig and not truncated
        frames = [Frame.from_bytes(r.payload) for r in records if r.key == P.key("frame")]
        recorded = {p.frame: p for p in (Profile.from_bytes(r.payload) for r in records
                                         if r.key == P.key("profile"))}
        # the reducer encodes profiles only once it knows of a subscriber (the recorder): the routes can take a
        # few frames to reach it on a loaded machine
        assert len(frames) >= FRAMES - 2 and len(recorded) >= FRAMES // 2
        old_workers = {w for f in frames for w, _, _ in f.plan}
        for p in first:
            p.stop()

        # a new run: only router + workers + reducer, fed by the replay
        # three workers where two recorded: another partition of k, the same layer 4
        [P.start("worker-c", "worker", "--config", cfg), P.start("worker-d", "worker", "--config", cfg),
         P.start("worker-e", "worker", "--config", cfg), P.start("reducer2", "reducer", "--config", cfg)]
        new_workers = set(P.wait_alive(s, "worker", 3))
        assert not new_workers & old_workers
        P.wait_alive(s, "reducer", 1)
        again = P.collect(s, P.key("profile"))
        rep = P.start("replay", "replay", str(path), "--only", "frame", "--speed", "0.5")
        assert rep.wait(20) == 0, rep.tail()
        again.wait(len(recorded) - 2, 10)
        replayed = {p.frame: p for p in (Profile.from_bytes(b) for _, b, _ in again.snapshot())}
        common = sorted(set(replayed) & set(recorded))
        assert len(common) >= len(recorded) - 2
        for fid in common:
            a, b = recorded[fid], replayed[fid]
            assert a.scores == b.scores, f"frame {fid}: layer 4 differs"
            assert (a.k, a.k_sub, a.v_shift, a.direction, a.magnitude, a.confidence, a.confident) == \
                (b.k, b.k_sub, b.v_shift, b.direction, b.magnitude, b.confidence, b.confident)
            assert set(b.workers) <= new_workers and len(b.workers) == 3
