"""Numba's kernels compiled once, by the process that starts a fleet, before the fleet's processes start.

numba compiles a kernel at its first call in a process unless its cache already holds it. On a
machine where nothing had run yet, `gmmap demo`'s server and each of its three robots compiled
the same kernels at the same time: on 2 cores the map stayed empty for 45 s, with nothing said.
Compiled here once, every process after loads them from numba's cache.
"""

from __future__ import annotations

import time

from gmm_core import FitConfig, fit_scan
from protocol import ScanMessage, encode
from services.map_server.warmup import warm_kernels
from services.sim.fleet import SimulatedFleet


def warm_fleet_kernels(world: str, fit: FitConfig, encoding: str) -> float:
    """A map server's kernels (warm_kernels) and a simulated robot's (warm_robot_kernels); returns
    the seconds it took."""
    start = time.perf_counter()
    warm_kernels()
    warm_robot_kernels(world, fit, encoding)
    return time.perf_counter() - start


def warm_robot_kernels(world: str, fit: FitConfig, encoding: str) -> None:
    """A simulated robot's kernels in `world`: its sensor, the fit of one scan with `fit` and its encoding."""
    scan = next(SimulatedFleet(world, robots=1, scans=2).scans(0, correct_every=0))
    model = fit_scan(scan.hits, scan.no_return, fit.for_dimension(scan.pose.dim))
    encode(ScanMessage("warm-up", "r", 0, scan.stamp, model, scan.pose), encoding)
