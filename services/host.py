"""What the machine a service runs on offers it."""

from __future__ import annotations

import ctypes
import ctypes.util
import os


def cpu_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS says, else all)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _libc_malloc_trim():
    """glibc's malloc_trim, or None where the C library has none (musl, macOS, Windows)."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


_MALLOC_TRIM = _libc_malloc_trim()


def release_free_memory() -> bool:
    """Hand memory the process freed back to the OS (glibc's malloc_trim(0)); False where it cannot.

    A map server frees and allocates arrays of every size from many threads for hours; glibc keeps
    the freed pages in its per-thread arenas, so without this its RSS keeps the high-water mark of
    each arena rather than what it holds."""
    return bool(_MALLOC_TRIM is not None and _MALLOC_TRIM(0) is not None)
