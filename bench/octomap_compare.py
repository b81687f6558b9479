"""What the benches that set the GMM beside OctoMap share (bench/auroc_balm.py, bench/lidar.py,
bench/street_truth.py): the machine line, the evaluation box, the GMM's map as they grade it,
OctoMap's trees and their occupancy on our grid, a timer.

OctoMap through octomap-python (the [bench] extra): `OcTree(resolution).insertPointCloud` of each
scan's points in the world frame from its sensor origin, read at the grid's cell centres with
`search` (a voxel it never saw: 0.5)."""

from __future__ import annotations

import os
import time

import numpy as np
import octomap

from gmm_core import FitConfig, Grid
from gmm_core.reconstruct import ReconstructionConfig
from services.datasets import RangeScan
from services.replay import ReplayMap, replay


def machine_line() -> str:
    cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    return f"{cpu}, {os.cpu_count()} cores, load average {load}; {time.strftime('%Y-%m-%d')}"


def aligned_bbox(lo, hi, resolution: float) -> list[float]:
    """[lo..., hi...] moved outward to multiples of `resolution`, so that grid cells are OctoMap's voxels."""
    lo = np.floor(np.asarray(lo, float) / resolution) * resolution
    hi = np.ceil(np.asarray(hi, float) / resolution) * resolution
    return [float(v) for v in np.round(np.concatenate([lo, hi]), 6)]


def observed_centres(grid: Grid, observed: np.ndarray) -> np.ndarray:
    """(n, 3) x, y, z centres of the cells where `observed` (array order [iz, iy, ix]) is True."""
    iz, iy, ix = np.nonzero(observed)
    return grid.origin + (np.stack([ix, iy, iz], axis=1) + 0.5) * grid.resolution


def gmm_map(
    scans: list[RangeScan],
    resolution: float,
    bbox: list[float],
    config: FitConfig,
    reconstruction: ReconstructionConfig,
) -> ReplayMap:
    """The GMM's map of `scans` as a server builds it: `replay` by Monte Carlo (seed 0), every scan
    model through the `q` codec, with the fit and reconstruction settings given."""
    return replay(
        scans,
        resolution=resolution,
        bbox=bbox,
        method="mc",
        config=config,
        seed=0,
        reconstruction=reconstruction,
        encoding="q",
    )


def insert_scan(tree: octomap.OcTree, scan: RangeScan, maxrange: float) -> None:
    cloud = np.ascontiguousarray(scan.pose.apply(scan.hits), dtype=np.float64)
    tree.insertPointCloud(cloud, np.ascontiguousarray(scan.pose.t, dtype=np.float64), maxrange=maxrange)


def octomap_tree(scans: list[RangeScan], resolution: float, maxrange: float) -> octomap.OcTree:
    tree = octomap.OcTree(resolution)
    for s in scans:
        insert_scan(tree, s, maxrange)
    return tree


def octomap_prob(tree: octomap.OcTree, grid: Grid, observed: np.ndarray) -> np.ndarray:
    """OctoMap's occupancy at the centres of the observed cells, 0.5 elsewhere (those cells are not scored)."""
    values = np.full(int(observed.sum()), 0.5)
    # The binding answers one point per call; the cells the ground truth never saw need no answer.
    for i, centre in enumerate(observed_centres(grid, observed)):
        try:
            values[i] = tree.search(centre).getOccupancy()
        except octomap.NullPointerException:  # a voxel OctoMap never saw: unknown
            pass
    prob = np.full(grid.array_shape, 0.5)
    prob[observed] = values
    return prob


def timed(f, *args, **kwargs):
    start = time.perf_counter()
    out = f(*args, **kwargs)
    return out, time.perf_counter() - start
