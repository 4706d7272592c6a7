"""vergence.head.frozen: the images' digests, and each camera's watch."""

from __future__ import annotations

import math
import zlib

import numpy as np
import pytest

from vergence.head.frozen import FROZEN_MASTER_S, IDENTICAL_MOVE_DEG, MASTER_LIVE, Master, Slave, digest


def test_the_digest_is_the_images_crc32_and_0_only_for_a_flat_image():
    img = np.arange(12, dtype=np.uint8).reshape(3, 4)
    assert digest(img) == zlib.crc32(img.tobytes())
    assert digest(img[:, ::2]) == zlib.crc32(np.ascontiguousarray(img[:, ::2]).tobytes())  # a view: its own bytes
    assert digest(np.zeros((3, 4), np.uint8)) == 0 and digest(np.full((3, 4), 9, np.uint8)) == 0
    assert digest(np.zeros((0, 4), np.uint8)) == 0
    # the band's rows only: y - reach .. y + reach (cut at the image's edge)
    assert digest(img, 2, 1) == zlib.crc32(img[1:4].tobytes())
    assert digest(img, 0, 3) == zlib.crc32(img[:4].tobytes())


def test_a_master_that_changed_every_frame_and_now_repeats_is_frozen_after_frozen_master_s():
    m, dt = Master(), 1 / 60
    seen = [m.see(k * dt, 100 + k) for k in range(MASTER_LIVE + 1)]  # a live camera: new bytes every frame
    assert seen == ["changed"] * (MASTER_LIVE + 1) and m.changes == MASTER_LIVE
    t0 = MASTER_LIVE * dt
    same = [m.see(t0 + k * dt, 100 + MASTER_LIVE) for k in range(1, 30)]
    frozen_at = t0 + (same.index("frozen") + 1) * dt
    assert frozen_at - t0 >= FROZEN_MASTER_S - 1e-9 and frozen_at - t0 < FROZEN_MASTER_S + dt
    assert m.see(1.0, 7) == "changed"  # and it changes again
    assert m.see(1.01, None) is None  # unknown: nothing said


@pytest.mark.parametrize("live", [False, True])
def test_a_fovea_moved_during_a_master_freeze_is_no_change_of_its_images(live):
    """A master frozen at frame 10 (its rows' bytes repeat), the fovea moved at frame 20 to other rows (their digest
    other, but repeated from there on): frozen FROZEN_MASTER_S after the freeze began (before, the new rows' first
    digest was a change: 0.3 s after the move, 0.56 s after the freeze on the outside draw Cones seed 7210); a live
    camera's new rows change every frame after the move: never frozen."""
    m, dt = Master(), 1 / 60
    seen = []
    for k in range(60):
        key = (320, 240) if k < 20 else (100, 300)
        digest = 100 + k if k < 10 or live else (7 if k < 20 else 8)
        seen.append(m.see(k * dt, digest, key))
    if live:
        assert "frozen" not in seen
    else:
        assert seen.index("frozen") * dt - 10 * dt == pytest.approx(FROZEN_MASTER_S, abs=dt / 2)


def test_a_master_that_never_changed_every_frame_is_never_frozen():
    m = Master()  # a still scene rendered clean: a few changes apart (the window growing), then the same bytes
    seen = [m.see(k / 60, 1 if k < 3 else (2 if k < 10 else 3)) for k in range(120)]
    assert "frozen" not in seen and m.changes < MASTER_LIVE


def test_a_slave_image_repeated_after_the_motor_moved_identical_move_deg_since_it_was_first_seen_is_frozen():
    """The same bytes while the motor stays (a still scene) are not; counted from the pan where they were first seen,
    not the last frame's (a slow drift adds up); new bytes start anew; an unknown digest says nothing."""
    s, step = Slave(), math.radians(IDENTICAL_MOVE_DEG) / 4
    assert [s.frozen(k / 60, 0.0, 7) for k in range(5)] == [False] * 5
    assert [s.frozen((5 + k) / 60, k * step, 7) for k in range(1, 6)] == [False, False, False, True, True]
    assert s.frozen(0.2, 5 * step, 8) is False and s.frozen(0.21, 9 * step, 8) is True
    assert s.frozen(0.22, 9 * step, None) is False


def test_a_slave_image_that_repeats_while_the_masters_change_is_frozen_though_the_motor_held():
    """The master's images change every frame (the scene, the sensor's noise: a live slave's would too) while the
    slave's repeat and the motor holds: after FROZEN_MASTER_S a frozen slave (a target that steps in depth meanwhile
    leaves the match nothing to find, and nothing moves). A still scene without noise, where neither changes, says
    nothing; nor a slave whose bytes change; nor fewer than MASTER_LIVE changes of the master."""
    s, dt = Slave(), 1 / 60
    got = [s.frozen(k * dt, 0.0, 7, master_changed=True) for k in range(40)]
    first = next(k for k, f in enumerate(got) if f)
    assert not any(got[:first]) and all(got[first:]) and first * dt == pytest.approx(FROZEN_MASTER_S, abs=dt)
    still = Slave()  # a noise-free still scene: neither camera's bytes change
    assert not any(still.frozen(k * dt, 0.0, 7, master_changed=False) for k in range(60))
    live = Slave()  # both change
    assert not any(live.frozen(k * dt, 0.0, 100 + k, master_changed=True) for k in range(60))
    few = Slave()  # the master changed a few times only (the rows a simulator renders as the window grows)
    assert not any(few.frozen(k * dt, 0.0, 7, master_changed=k in (3, 9, 20, 31)) for k in range(60))
