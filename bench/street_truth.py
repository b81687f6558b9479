"""The maps of bench/street_scans.py's street graded against the street itself, beside the raw grid.

bench/lidar.py grades a map against the raw counting grid of all points at 0.2 m: with every point
kept, that truth is the ray casting of the very points OctoMap casts. Here the same maps (GMM with
the defaults through `q`, OctoMap with maxrange 60 m, the raw grid of the kept points; points beyond
60 m dropped as there) are also graded against the geometry the scans were made from: on the cells
the raw grid of all points observed, occupied where the cell has volume in a solid (the ground,
z <= 0, or a box). AUROC both ways, at each keep fraction, and the share of the occupied cells each
map calls free (Eq. 12's classes, the configuration's sigma^2) both ways:

    .venv/bin/python bench/street_truth.py /tmp/street [--fractions 1.0 0.3]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from lidar import MAX_RANGE, RESOLUTION, SETS, evaluation_bbox, read
from octomap_compare import gmm_map, observed_centres, octomap_prob, octomap_tree

from gmm_core.metrics import auroc, called_free
from services.config import load_config
from services.replay import replay


def in_solid(centres: np.ndarray, boxes: np.ndarray, half: float) -> np.ndarray:
    """Whether each cell (its centre, half its side) has volume below the ground or in a box."""
    solid = centres[:, 2] - half < 0.0
    for lo, hi in boxes:
        solid |= np.all(centres - half < hi, axis=1) & np.all(centres + half > lo, axis=1)
    return solid


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("street", type=Path, help="bench/street_scans.py's directory")
    parser.add_argument("--fractions", type=float, nargs="+", default=[1.0, 0.3])
    args = parser.parse_args()
    settings = load_config()
    config, variance = settings.fit.for_dimension(3), settings.reconstruction.variance

    SETS["street"] = (args.street, {"fmt": "pcd", "poses": args.street / "poses.txt"})
    every = read("street")
    bbox = evaluation_bbox(every)
    truth = replay(every, resolution=RESOLUTION, bbox=bbox, method="raw", config=config)
    grid = truth.grid
    observed = (truth.hits + truth.misses) > 0
    raw_occupied = (truth.hits > truth.misses)[observed]
    solid = in_solid(observed_centres(grid, observed), np.load(args.street / "boxes.npy"), RESOLUTION / 2)
    del truth
    occupied = f"{raw_occupied.sum():,} in the raw grid, {solid.sum():,} in a solid"
    print(f"{observed.sum():,} cells observed; occupied: {occupied}")
    print(
        "| points kept | GMM / OctoMap / raw grid, against the raw grid of all points | against the street "
        "| occupied called free: of the raw grid's | of the street's |"
    )
    print("|---|---|---|---|---|")
    for fraction in args.fractions:
        scans = every if fraction == 1.0 else read("street", fraction)
        maps = {
            "GMM": gmm_map(scans, RESOLUTION, bbox, config, settings.reconstruction).prob[observed],
            "OctoMap": octomap_prob(octomap_tree(scans, RESOLUTION, MAX_RANGE), grid, observed)[observed],
            "raw": replay(scans, resolution=RESOLUTION, bbox=bbox, method="raw", config=config).prob[observed],
        }
        truths = (raw_occupied, solid)
        against = [" / ".join(f"{auroc(p, cells):.4f}" for p in maps.values()) for cells in truths]
        free = [" / ".join(f"{called_free(p, cells, variance):.1%}" for p in maps.values()) for cells in truths]
        print(f"| {fraction:.0%} | {against[0]} | {against[1]} | {free[0]} | {free[1]} |", flush=True)


if __name__ == "__main__":
    main()
