"""Numba's on-disk kernels made current before a test session.

Numba keys a cached kernel on its own source file only: a kernel that inlines or calls a function
of another module (the sampler's normals inside gmm_core.scan_trace's trace) keeps its old
machine code when only that other module changes, and tests then run the old code (numba's
documentation, "Notes on caching"). So every cached kernel of the repository is dropped when any
module that uses numba changed since the last session; numba compiles them again on first use.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

PACKAGES = ("gmm_core", "services", "protocol")


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
