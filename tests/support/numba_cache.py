"""Numba's on-disk kernels made current before a test session.

Numba keys a cached kernel on its own source file only: a kernel that inlines or calls a function
of another module (the sampler's normals inside gmm_core.scan_trace's trace) keeps its old
machine code when only that other module changes, and tests then run the old code (numba's
documentation, "Notes on caching"). So every cached kernel of the repository is dropped when any
module that uses numba changed since the last session.

Then, before any test runs, the kernels a map server and a simulated robot use are compiled once,
in processes of their own side by side (`compile_kernels`). Left to the tests, each pytest-xdist
worker and each server a test starts compiled the same kernels at the same time: on a 2-core AMD
EPYC a fresh clone's suite ran 852 s instead of 649, and a server's warm-up outlasted the 60 s its
test waits for it to be ready (docs/BENCHMARKS.md, twenty-sixth session).
"""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

from services.sim.warmup import SERVER_WARM_UP, finish_warm_up, kernels_cached, start_warm_up

PACKAGES = ("gmm_core", "services", "protocol")
# Each compiles a share of the kernels in a process of its own, one a core: a map server's (2D and
# 3D: 60 s on an empty cache on a 2-core AMD EPYC) and a simulated robot's in a 2D world, then in a
# 3D one (45 s each alone, the simulator's kernels compiled once). A third process for the 3D
# robot compiled the simulator's kernels a second time, on no core of its own: 112-120 s against
# 92-97 s for the two (docs/BENCHMARKS.md, twenty-ninth session).
WARM_UPS = (
    SERVER_WARM_UP,
    "from gmm_core import FitConfig; from services.sim.warmup import warm_robot_kernels; "
    + "; ".join(f"warm_robot_kernels({world!r}, FitConfig(), 'q')" for world in ("office", "mine")),
)


def numba_sources_digest(root: Path) -> str:
    """A digest of the path and bytes of every module under PACKAGES that mentions numba."""
    digest = hashlib.sha256()
    for path in sorted(p for package in PACKAGES for p in (root / package).rglob("*.py")):
        text = path.read_bytes()
        if b"numba" in text:
            digest.update(path.relative_to(root).as_posix().encode() + b"\0" + text)
    return digest.hexdigest()


def drop_stale_kernels(root: Path, previous: str | None) -> str:
    """Delete the cached kernels (`__pycache__/*.nbi`, `*.nbc`) under PACKAGES unless the numba
    sources' digest equals `previous`, the one of the last session; returns the current digest."""
    current = numba_sources_digest(root)
    if current != previous:
        for package in PACKAGES:
            for cached in (root / package).rglob("__pycache__/*.nb[ic]"):
                cached.unlink(missing_ok=True)
    return current


def precompile_needed(root: Path, digest: str, precompiled: str | None) -> bool:
    """Whether a session with pytest-xdist's workers should compile_kernels first: the cache is empty,
    or the last precompile was for other sources (`precompiled`, the digest then). A session without
    workers after a change compiles only what its tests call and leaves the cache partial; the
    servers of the next session would compile the rest during their tests (116 s for one of them)."""
    return not kernels_cached(root) or precompiled != digest


def compile_kernels() -> float:
    """Run WARM_UPS side by side, so that numba's cache holds their kernels; returns the seconds it
    took. RuntimeError with a warm-up's output if one fails."""
    start = time.perf_counter()
    for process in [start_warm_up(code) for code in WARM_UPS]:
        finish_warm_up(process)
    return time.perf_counter() - start
