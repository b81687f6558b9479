"""What the machine a service runs on offers it, and what it gave a run."""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys
import time


def cpu_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS says, else all)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def cpu_ticks() -> tuple[int, int, int] | None:
    """Clock ticks all the machine's CPUs spent (busy, idle, stolen) since boot: Linux /proc/stat;
    None where it does not say. Stolen: the hypervisor ran another guest while this one had work
    (a shared VM under load gives a run fewer cores than it has)."""
    try:
        with open("/proc/stat") as stat:
            fields = [int(v) for v in stat.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    if len(fields) < 8:
        return None
    user, nice, system, idle, iowait, irq, softirq, steal = fields
    return user + nice + system + irq + softirq, idle + iowait, steal


def cpu_shares(before: tuple[int, int, int] | None, after: tuple[int, int, int] | None) -> dict[str, float] | None:
    """The fractions of the machine's CPU time that were busy, idle and stolen between two
    `cpu_ticks` readings (None where either is missing or no tick passed)."""
    if before is None or after is None:
        return None
    ticks = [b - a for a, b in zip(before, after)]
    total = sum(ticks)
    if total <= 0:
        return None
    return {name: round(t / total, 3) for name, t in zip(("busy", "idle", "steal"), ticks)}


def loop_rate(seconds: float = 0.25) -> float:
    """Millions of iterations per second of a bare Python loop on the calling thread, for about
    `seconds`: how fast one core runs this interpreter now. On a shared VM it halves when other
    guests load the host's memory and caches, which /proc/stat's stolen time does not show
    (docs/RELIABILITY.md, twelfth session); measure it while the machine is otherwise at rest."""
    count, start = 0, time.perf_counter()
    end = start + seconds
    while (now := time.perf_counter()) < end:
        for _ in range(10_000):
            count += 1
    return count / (now - start) / 1e6


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


def child_pids(pid: int) -> list[int]:
    """The children of every thread of process `pid` (a map server's tracer thread starts its own
    process); Linux /proc, empty where it does not say."""
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return []
    children = []
    for task in tasks:
        try:
            with open(f"/proc/{pid}/task/{task}/children") as listed:
                children += [int(child) for child in listed.read().split()]
        except OSError:
            continue
    return children


def die_with_parent(parent: int) -> None:
    """In a child (before exec, or first thing in a spawned process): SIGTERM when the parent dies,
    even by SIGKILL (Linux PR_SET_PDEATHSIG), so that a killed `gmmap sim` or `demo` leaves no
    server tracing on and no tile client asking a server that is gone, and a killed server no
    tracer process. `parent`: the pid that started the child; one that died before the request
    took hold (a child scheduled late under load) is never signalled for, so the child ends at once.
    The signal follows the thread that started the child, not the process: start it from a thread
    that lives as long as the child should."""
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() != parent:
            os.kill(os.getpid(), signal.SIGTERM)


PR_SET_PDEATHSIG = 1
