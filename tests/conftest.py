"""Fixtures for every test; the helpers behind them live in tests/support/.

Tests under tests/integration/ (processes, Zenoh, HTTP, Chromium, compose) are marked
`integration`: `pytest -m "not integration"` runs the unit tests alone."""

from __future__ import annotations

import os

# One BLAS and OpenMP thread a test process, set before numpy or scikit-learn load their libraries
# (and inherited by pytest-xdist's workers and every process a test starts): two workers on two
# cores, each with OpenBLAS's and scikit-learn's OpenMP threads waiting in spin loops, ran the fit
# tests that compare with scikit-learn in 95 s instead of 44 s (docs/BENCHMARKS.md, thirty-first
# session). An explicit setting wins.
for _threads in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_threads, "1")

import sys
from pathlib import Path

import pytest
import zenoh

from services.zenoh_config import zenoh_config
from support.numba_cache import compile_kernels, drop_stale_kernels, precompile_needed
from support.paths import DATA, ROOT
from support.processes import TestProcesses

INTEGRATION = Path(__file__).parent / "integration"
NUMBA_DIGEST = "gmmap/numba-sources"  # pytest's cache key: the numba modules' digest of the last session
PRECOMPILED = "gmmap/numba-precompiled"  # ... and the digest the kernels were last compiled before the tests for


def pytest_configure(config):
    config.addinivalue_line("markers", "integration: starts processes, Zenoh sessions, HTTP servers or a browser")
    cache = getattr(config, "cache", None)
    if cache is not None and not hasattr(config, "workerinput"):  # once, before pytest-xdist's workers start
        digest = drop_stale_kernels(ROOT, cache.get(NUMBA_DIGEST, None))
        cache.set(NUMBA_DIGEST, digest)
        # With pytest-xdist's workers (`make test`): alone, a process compiles only what its tests call.
        if getattr(config.option, "numprocesses", None) and precompile_needed(
            ROOT, digest, cache.get(PRECOMPILED, None)
        ):
            print(f"numba's kernels compiled before the tests in {compile_kernels():.0f} s", file=sys.stderr)
            cache.set(PRECOMPILED, digest)


def pytest_collection_modifyitems(items):
    for item in items:
        if INTEGRATION in Path(item.fspath).parents:
            item.add_marker(pytest.mark.integration)


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not DATA.is_dir():
        pytest.skip(f"real data folder {DATA} is absent (it sits beside the repository as ../shared/data)")
    return DATA


@pytest.fixture(scope="session")
def intel_scans(data_dir):
    from services.datasets import read_scans

    return list(read_scans(data_dir / "carmen" / "intel-corrected.log.gz"))


@pytest.fixture
def procs(tmp_path):
    """The test's `gmmap` subprocesses; every one still running is killed at the end."""
    p = TestProcesses(tmp_path)
    try:
        yield p
    finally:
        p.close()


@pytest.fixture
def session_to():
    """Open test-side Zenoh peers connected to a server; all closed at the end."""
    opened = []

    def open_(zport: int) -> zenoh.Session:
        s = zenoh.open(zenoh_config("peer", connect=[f"tcp/127.0.0.1:{zport}"]))
        opened.append(s)
        return s

    yield open_
    for s in opened:
        s.close()
