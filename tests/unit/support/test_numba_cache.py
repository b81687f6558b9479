"""Cached numba kernels are dropped when a numba module changed since the last session, kept otherwise."""

from services.sim.warmup import kernels_cached
from support.numba_cache import drop_stale_kernels


def test_cached_kernels_are_dropped_only_when_a_numba_module_changed(tmp_path):
    kernels, plain = tmp_path / "gmm_core" / "kernels.py", tmp_path / "services" / "plain.py"
    for path in (kernels, plain):
        path.parent.mkdir(parents=True)
    kernels.write_text("from numba import njit\n")
    plain.write_text("x = 1\n")
    cached = [tmp_path / "gmm_core" / "__pycache__" / f"kernels.f-1.py311.{ext}" for ext in ("nbi", "nbc")]

    def cache_kernels():
        cached[0].parent.mkdir(exist_ok=True)
        for path in cached:
            path.write_bytes(b"kernel")

    cache_kernels()
    assert kernels_cached(tmp_path)
    digest = drop_stale_kernels(tmp_path, None)  # no earlier session: whatever is cached may be stale
    assert not any(path.exists() for path in cached) and not kernels_cached(tmp_path)
    cache_kernels()
    assert drop_stale_kernels(tmp_path, digest) == digest and all(path.exists() for path in cached)
    plain.write_text("x = 2\n")  # no numba in it: the kernels stay
    assert drop_stale_kernels(tmp_path, digest) == digest and all(path.exists() for path in cached)
    kernels.write_text("from numba import njit  # changed\n")
    assert drop_stale_kernels(tmp_path, digest) != digest and not any(path.exists() for path in cached)
