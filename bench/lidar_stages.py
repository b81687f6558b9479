"""Where the 3D fit's time goes: each stage of `fit_scan`'s 3D fit (`fit_mixture_voxels` at the
defaults) on BALM scans, warm and with cold caches; one thread.

- warm: the stage run again and again on the same scan, the median of `--runs`;
- cold: each run after 2 million random writes over 320 MB (what OctoMap's insertion of a scan does
  to the caches between two fits in bench/lidar.py), in place: writes through a temporary array
  would let glibc return heap pages, and the fit's next arrays would fault them in again (600 page
  faults a fit: the voxel sums 3.0 instead of 2.5 ms).

Stages: sums (`voxels._voxel_statistics`), cells (K from the occupied 1 m cells), rings
(`rings.ring_spacing` and `with_footprint`), edges (`voxel_merge._voxel_edges`), pieces, merge
(`voxel_merge._merge`); `fit` is the whole `fit_scan`, timed apart (what bench/lidar.py times).

    NUMBA_NUM_THREADS=1 .venv/bin/python bench/lidar_stages.py [--scans 3 4] [--runs 25]
"""

from __future__ import annotations

import os

for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[var] = "1"  # one core: numba, and numpy's BLAS (set before numpy is imported)

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lidar import read
from octomap_compare import machine_line

from gmm_core import fit_scan, rings, voxel_merge, voxels
from services.config import load_config

STAGES = ("sums", "cells", "rings", "edges", "pieces", "merge", "fit")


def stage_times(points: np.ndarray, config) -> list[float]:
    """Seconds of each of STAGES but the fit on one scan's points."""
    clock = [time.perf_counter()]
    shift = points[0].copy()
    finest, tiers, _ = voxels.voxel_tiers(config.voxel_size, config.voxel_fine_range, config.voxel_near_range)
    sums, keys = voxels._voxel_statistics(points, finest, shift, tiers)
    clock.append(time.perf_counter())
    ratio = round(config.component_size / finest)
    k = min(config.n_components_of_count(len(points), 3), voxels._count_cells(keys, 3, ratio))
    clock.append(time.perf_counter())
    costed = rings.with_footprint(sums, -shift, rings.ring_spacing(points))
    clock.append(time.perf_counter())
    eu, ev = voxel_merge._voxel_edges(keys, finest, tiers)
    clock.append(time.perf_counter())
    voxel_merge._pieces(len(keys), eu, ev)
    clock.append(time.perf_counter())
    voxel_merge._merge(costed, eu, ev, k, config.reg_covar)
    clock.append(time.perf_counter())
    return list(np.diff(clock))


def fit_time(points: np.ndarray, config) -> float:
    start = time.perf_counter()
    fit_scan(points, np.zeros((0, 3)), config)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scans", type=int, nargs="+", default=[3, 4], help="BALM scan numbers (0-14)")
    parser.add_argument("--runs", type=int, default=25)
    args = parser.parse_args()
    config = load_config().fit.for_dimension(3)
    scans = read("balm")
    scratch = np.zeros(40_000_000)  # 320 MB
    scattered = np.random.default_rng(0).integers(0, scratch.size, 2_000_000)
    print(machine_line())
    print("\n| BALM scan | caches | " + " | ".join(f"{s} ms" for s in STAGES) + " |")
    print("|---|---|" + "---|" * len(STAGES))
    for i in args.scans:
        points = np.ascontiguousarray(scans[i].hits)
        stage_times(points, config)  # compile
        fit_time(points, config)
        for cold in (False, True):
            runs = []
            for _ in range(args.runs):
                if cold:
                    np.add.at(scratch, scattered, 1.0)
                stages = stage_times(points, config)
                if cold:
                    np.add.at(scratch, scattered, 1.0)
                runs.append([*stages, fit_time(points, config)])
            median = 1e3 * np.median(runs, axis=0)
            label = "cold" if cold else "warm"
            print(f"| #{i} ({len(points):,} points) | {label} | " + " | ".join(f"{t:.2f}" for t in median) + " |")


if __name__ == "__main__":
    main()
