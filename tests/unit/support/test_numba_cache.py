"""Cached numba kernels are dropped when a numba module changed since the last session, kept otherwise."""

from services.sim.warmup import kernels_cached
from support.numba_cache import drop_stale_kernels, precompile_needed


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


def test_kernels_are_compiled_first_unless_they_were_for_these_sources(tmp_path):
    kernels = tmp_path / "gmm_core" / "__pycache__" / "kernels.f-1.py311.nbi"
    assert precompile_needed(tmp_path, "a", "a")  # an empty cache
    kernels.parent.mkdir(parents=True)
    kernels.write_bytes(b"kernel")
    assert not precompile_needed(tmp_path, "a", "a")
    assert precompile_needed(tmp_path, "b", "a")  # a partial cache: a session without workers since a change
    assert precompile_needed(tmp_path, "a", None)  # never compiled first here
