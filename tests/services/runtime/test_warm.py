"""services/runtime/warm.py: whether numba's cache holds the kernels (a first start, or not), and the one compile
`vergence up` runs on a first start (the start itself: tests/scenarios/test_supervise.py)."""

from __future__ import annotations

from services.runtime import warm


def test_compiled_looks_in_numbas_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    assert warm.cache_dirs() == [tmp_path / "cache"]
    assert not warm.compiled()  # no such folder: a first start
    (tmp_path / "cache" / "vergence").mkdir(parents=True)
    (tmp_path / "cache" / "vergence" / "retina._gradients-91.py311.nbi").write_bytes(b"")
    assert not warm.compiled()  # another function's: the kernel is not there yet
    (tmp_path / "cache" / "vergence" / "kernel._sad-37.py311.nbi").write_bytes(b"")
    assert warm.compiled()
