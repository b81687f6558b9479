"""Numba's kernels compiled once, by the process that starts a fleet, before the fleet's processes start.

numba compiles a kernel at its first call in a process unless its cache already holds it. On a
machine where nothing had run yet, `gmmap demo`'s server and each of its three robots compiled
the same kernels at the same time: on 2 cores the map stayed empty for 45 s, with nothing said.
Compiled here once, every process after loads them from numba's cache. On an empty cache the map
server's kernels compile in a process of their own beside the robot's: on a slow 2-core AMD EPYC
they took 61-67 s and the robot's 39-54 s, one after the other (docs/BENCHMARKS.md, twenty-sixth
session).
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import gmm_core
from gmm_core import FitConfig, fit_scan
from protocol import ScanMessage, encode
from services.map_server.warmup import warm_kernels
from services.sim.fleet import SimulatedFleet

SERVER_WARM_UP = "from services.map_server.warmup import warm_kernels; warm_kernels()"  # python -c


def kernels_cached(root: Path = Path(gmm_core.__file__).parents[1]) -> bool:
    """Whether numba's cache beside the core under `root` holds kernels: false on a machine where
    nothing ran yet, or after a change of a numba module dropped them (tests/support/numba_cache.py)."""
    return any((root / "gmm_core").rglob("__pycache__/*.nbi"))


def warm_fleet_kernels(world: str, fit: FitConfig, encoding: str) -> float:
    """A map server's kernels (warm_kernels) and a simulated robot's (warm_robot_kernels), the
    server's in a process of its own meanwhile when the cache is empty; returns the seconds it took.
    RuntimeError with that process's output if it fails."""
    start = time.perf_counter()
    server = None if kernels_cached() else start_warm_up(SERVER_WARM_UP)
    warm_robot_kernels(world, fit, encoding)
    if server is not None:
        finish_warm_up(server)
    warm_kernels()  # loaded from the cache where that process compiled them
    return time.perf_counter() - start


def start_warm_up(code: str) -> subprocess.Popen:
    """`python -c code` in a process of its own (a warm-up: its kernels go to numba's cache)."""
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


def finish_warm_up(process: subprocess.Popen) -> None:
    """Wait for a start_warm_up process; RuntimeError with its command and output if it failed."""
    output, _ = process.communicate()
    if process.returncode != 0:
        raise RuntimeError(
            f"warm-up {process.args!r} failed ({process.returncode}):\n{output.decode(errors='replace')}"
        )


def warm_robot_kernels(world: str, fit: FitConfig, encoding: str) -> None:
    """A simulated robot's kernels in `world`: its sensor, the fit of one scan with `fit` and its encoding."""
    scan = next(SimulatedFleet(world, robots=1, scans=2).scans(0, correct_every=0))
    model = fit_scan(scan.hits, scan.no_return, fit.for_dimension(scan.pose.dim))
    encode(ScanMessage("warm-up", "r", 0, scan.stamp, model, scan.pose), encoding)
