"""What the compiled kernels are given: each input array C-contiguous and read-only, whatever its caller had.

numba compiles a kernel once per type of its arguments, and an array's type includes whether it is writable: a
frame decoded from a message or a scene kept in memory is read-only, one computed here is not, and each mix of
the two was a compilation of its own (a first start compiled _sad, _half_sads and _features twice each: about
3 s of its 11). The kernels only read their inputs, so every input goes in as a read-only view (no copy)."""

from __future__ import annotations

import numpy as np

__all__ = ["readonly"]


def readonly(a: np.ndarray, dtype=None) -> np.ndarray:
    """a as a C-contiguous, read-only array (a view where a already is contiguous and of that dtype)."""
    a = np.ascontiguousarray(a, dtype=dtype)
    if a.flags.writeable:
        a = a.view()
        a.flags.writeable = False
    return a
