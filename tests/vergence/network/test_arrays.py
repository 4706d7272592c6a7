"""vergence.network.arrays: every kernel input goes in C-contiguous and read-only, so numba compiles each kernel once,
not once per mix of writable and read-only arrays (a frame decoded from a message is read-only, a strip computed here
is not)."""

from __future__ import annotations

import numpy as np

from vergence.network import kernel, retina
from vergence.network.arrays import readonly


def test_readonly_is_a_read_only_view_where_it_can_be_and_a_contiguous_copy_where_not():
    a = np.arange(12, dtype=np.uint8).reshape(3, 4)
    r = readonly(a)
    assert not r.flags.writeable and np.shares_memory(r, a) and a.flags.writeable  # the caller's stays writable
    assert readonly(r) is r
    t = readonly(a.T)  # not contiguous: a contiguous copy, read-only too
    assert t.flags.c_contiguous and not t.flags.writeable and not np.shares_memory(t, a)
    assert readonly(a, np.int64).dtype == np.int64


def test_writable_and_read_only_inputs_run_one_compilation_of_each_kernel():
    rng = np.random.default_rng(3)
    strip = rng.integers(0, 256, (19, 80), np.uint8)
    frozen = strip.copy()
    frozen.flags.writeable = False  # as a frame decoded from a message is
    a, b = retina.planes(strip), retina.planes(frozen)
    assert np.array_equal(a, b)
    fovea = a[:, :15, :15].copy()
    weights = np.ones((15, 15), np.uint8)
    for f, band, w in ((fovea, a[:, :15], weights), (readonly(fovea), b[:, :15], readonly(weights)),
                       (fovea, b[:, :15], None)):
        s = kernel.portable_sad(f, band, 0, 20, weights=w)
        h = kernel.half_sads(f, band[:, :15], 0, 20, weights=w)
        assert s.shape == (1, 20) and h.shape == (4, 20)
    assert [len(k.signatures) for k in (kernel._sad, kernel._half_sads, retina._features)] == [1, 1, 1]
