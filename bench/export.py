"""`gmmap export`'s writers on a real 3D map: the .bt tree beside OctoMap building the same leaves
(octomap-python's updateNodes, C++, then its own writeBinary), and the .ot, PGM and PLY writers.

The map: the raw counting grid of the three Kurt3D scans (`replay(method="raw")`, no fitting) on a
box whose corners are multiples of the resolution, so that each cell is one OctoMap voxel and
both trees must be the same bytes (checked). Times: the best of `--repeat` runs, classification
(Eq. 12 at sigma^2 0.21) included in ours, OctoMap's from the cell centres it is given.

    python bench/export.py [--resolution 0.1] [--repeat 3]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import octomap
from octomap_compare import aligned_bbox, machine_line

from gmm_core.occupancy import FREE, OCCUPIED, classify
from services.datasets import read_scans
from services.export.octomap_tree import bt_bytes, ot_bytes
from services.export.pgm import pgm_bytes
from services.export.ply import ply_bytes
from services.render import top_down_classes
from services.replay import replay

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "3d" / "kurt3d"
VARIANCE = 0.21


def best_of(repeat: int, work):
    times, result = [], None
    for _ in range(repeat):
        start = time.perf_counter()
        result = work()
        times.append(time.perf_counter() - start)
    return min(times), result


def octomap_bt(prob, grid) -> bytes:
    classes = classify(prob, VARIANCE)
    tree = octomap.OcTree(grid.resolution)
    for cls, occupied in ((OCCUPIED, True), (FREE, False)):
        iz, iy, ix = np.nonzero(classes == cls)
        centres = grid.origin + (np.stack([ix, iy, iz], axis=1) + 0.5) * grid.resolution
        tree.updateNodes(np.ascontiguousarray(centres), occupied, True)  # lazy: inner nodes once, below
    tree.updateInnerOccupancy()
    return tree.writeBinary()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", type=float, default=0.1)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    scans = list(read_scans(DATA))
    bbox = aligned_bbox([-12, -12, -4], [36, 12, 10], args.resolution)
    result = replay(scans, resolution=args.resolution, bbox=bbox, method="raw")
    grid, prob = result.grid, result.prob
    classes = classify(prob, VARIANCE)
    print(f"# {machine_line()}")
    print(
        f"# Kurt3D raw grid {'x'.join(map(str, grid.shape))} = {grid.n_cells:,} cells at {grid.resolution} m: "
        f"{(classes == OCCUPIED).sum():,} occupied, {(classes == FREE).sum():,} free"
    )
    ours_s, ours = best_of(args.repeat, lambda: bt_bytes(prob, grid, VARIANCE))
    theirs_s, theirs = best_of(args.repeat, lambda: octomap_bt(prob, grid))
    assert ours == theirs, "the .bt differs from OctoMap's own"
    ot_s, ot = best_of(args.repeat, lambda: ot_bytes(prob, grid, VARIANCE))
    pgm_s, _ = best_of(args.repeat, lambda: pgm_bytes(top_down_classes(prob, VARIANCE)))
    ply_s, ply = best_of(args.repeat, lambda: ply_bytes(prob, grid, VARIANCE))
    print("| writer | seconds | bytes |")
    print("|---|---|---|")
    print(f"| .bt, services.export.octomap_tree | {ours_s:.3f} | {len(ours):,} |")
    print(f"| .bt, octomap-python updateNodes + writeBinary (same bytes) | {theirs_s:.3f} | {len(theirs):,} |")
    print(f"| .ot (MAP log-odds, unpruned) | {ot_s:.3f} | {len(ot):,} |")
    print(f"| PGM (top-down classes) | {pgm_s:.3f} | {grid.shape[0] * grid.shape[1]:,} pixels |")
    print(f"| PLY | {ply_s:.3f} | {len(ply):,} |")
    print(f"# ratio OctoMap / ours for the .bt: {theirs_s / ours_s:.2f}")


if __name__ == "__main__":
    main()
