"""Rays per second: our Amanatides-Woo tracer vs OctoMap's insertPointCloud, side by side.

    .venv/bin/python bench/raytrace.py        (needs `.venv/bin/pip install -e .[bench]`)

Rays are 10 m long, from one sensor origin in uniformly random directions, all ending in a hit.
Ours: `gmm_core.raytrace.trace_rays` on the dense grid of a 20.5 m box around the origin, all
rays in one call (as a reconstruction does), numba compile excluded, median of 3 calls.
OctoMap (PyPI `octomap-python`): `OcTree.insertPointCloud(cloud, origin)` with default
maxrange, fed a prefix of the same rays as 3 scans of 10^5 points into a fresh tree, median of 3.
Per scan it ray-traces every point with computeRayKeys into a hash set of free keys plus a set of end-point
keys, then updates each distinct key once by descending its 16-level octree. That dedup makes its
rays/s depend on how densely a scan's rays overlap; ours adds to every crossed cell of every ray.
On grids too big for the cache ours sorts the rays by the block their end point falls in
(inside the timed call); "beam order" rows trace the same 3D rays sorted as a 64-ring spinning
lidar emits them (ring, then azimuth), for ours only.
"""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # this octomap wheel links no OpenMP; be sure anyway

import time

import numba
import numpy as np
import octomap
from tqdm import tqdm

from gmm_core.grid import Grid
from gmm_core.raytrace import trace_rays

LENGTH = 10.0
HALF_BOX = 10.25
N_OURS = 10**6
OCTOMAP_SCAN, OCTOMAP_SCANS = 10**5, 3
RUNS = 3


def machine_line() -> str:
    cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    return f"{cpu}, {os.cpu_count()} cores, load average {load}; {time.strftime('%Y-%m-%d')}"


def random_rays(n: int, dim: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    origin = rng.uniform(-0.5, 0.5, dim)
    d = rng.normal(size=(n, dim))
    return origin, origin + LENGTH * d / np.linalg.norm(d, axis=1, keepdims=True)


def beam_order(origin: np.ndarray, ends: np.ndarray) -> np.ndarray:
    d = (ends - origin) / LENGTH
    ring = np.floor((np.arcsin(d[:, 2]) / np.pi + 0.5) * 64)
    return ends[np.lexsort((np.arctan2(d[:, 1], d[:, 0]), ring))]


def ours(origin: np.ndarray, ends: np.ndarray, resolution: float, threads: int) -> tuple[float, float]:
    """(rays/s median of RUNS calls, cells crossed per ray)."""
    numba.set_num_threads(threads)
    n = len(ends)
    # The origin a third of a cell off the cell boundaries: a ray that starts on a corner is a
    # tie that any tracer may break either way.
    corner = origin - HALF_BOX - resolution / 3
    grid = Grid.from_bbox(corner, corner + 2 * HALF_BOX, resolution)
    args = (grid, origin[None], np.zeros(n, np.int64), ends, np.ones(n), np.ones(n, bool))
    hits, misses = trace_rays(*args)  # warm-up: compile (cached) and first-touch of the grid
    times = []
    for _ in range(RUNS):
        start = time.perf_counter()
        trace_rays(*args)
        times.append(time.perf_counter() - start)
    return n / np.median(times), float(hits.sum() + misses.sum()) / n


def octomap_rays_per_s(origin: np.ndarray, ends: np.ndarray, resolution: float) -> float:
    """rays/s, median of RUNS fresh trees, each fed OCTOMAP_SCANS scans."""
    scans = [np.ascontiguousarray(ends[s * OCTOMAP_SCAN : (s + 1) * OCTOMAP_SCAN]) for s in range(OCTOMAP_SCANS)]
    times = []
    for _ in range(RUNS):
        tree = octomap.OcTree(resolution)
        start = time.perf_counter()
        for scan in scans:
            tree.insertPointCloud(scan, origin)
        times.append(time.perf_counter() - start)
    return OCTOMAP_SCANS * OCTOMAP_SCAN / np.median(times)


def main():
    rng = np.random.default_rng(0)
    rays = {"3D": random_rays(N_OURS, 3, rng), "2D": random_rays(N_OURS, 2, rng)}
    rays["3D, beam order"] = rays["3D"][0], beam_order(*rays["3D"])
    cases = [
        ("3D", 0.25),
        ("3D", 0.1),
        ("3D, beam order", 0.25),
        ("3D, beam order", 0.1),
        ("2D", 0.25),
        ("2D", 0.1),
        ("2D", 0.05),
    ]
    rows = []
    for name, res in tqdm(cases, desc="ray tracing"):
        origin, ends = rays[name]
        one, cells = ours(origin, ends, res, 1)
        two, _ = ours(origin, ends, res, 2)
        octo = octomap_rays_per_s(origin, ends, res) if name == "3D" else None
        rows.append((name, res, cells, one, two, octo))

    print(f"\n{machine_line()}")
    print(
        f"{N_OURS:,} rays of {LENGTH:g} m for ours (one call, median of {RUNS}); "
        f"OctoMap: {OCTOMAP_SCANS} scans of {OCTOMAP_SCAN:,} of the same rays, median of {RUNS}\n"
    )
    print(
        "| rays | resolution | cells crossed / ray | ours, 1 core (M rays/s) | ours, 2 threads "
        "(M rays/s) | OctoMap, 1 core (M rays/s) | ours / OctoMap (1 core) |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, res, cells, one, two, octo in rows:
        octo_cols = f"{octo / 1e6:.3f} | {one / octo:.1f}x" if octo else "- | -"
        print(f"| {name} | {res:g} m | {cells:.0f} | {one / 1e6:.2f} | {two / 1e6:.2f} | {octo_cols} |")


if __name__ == "__main__":
    main()
