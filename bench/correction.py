"""How soon a pose-graph correction of every Intel node is visible to the next query (issue 5).

Times, in one process: the first 512 x 512 tile at 5 cm of a fresh map (every node's samples
drawn); then, five times, decoding the PoseGraphUpdate of all 910 nodes and applying it to the
FleetMap (which moves their boxes in the node index and marks the tiles they reach stale), and
a tile at 5 cm: cold (a tile never asked for, nudged by one cell each round; samples already
drawn), the update of the first tile after the correction (traced afresh, since every node
moved), and cached.

    .venv/bin/python bench/correction.py
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from gmm_core import Grid, Pose, fit_scan
from protocol import PoseGraphUpdate, ScanMessage, decode, encode
from services.datasets import read_scans
from services.map_server.fleet_map import FleetMap

LOG = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "carmen" / "intel-corrected.log.gz"


def main() -> None:
    scans = list(read_scans(LOG))
    fleet = FleetMap("bench")
    for s in scans:
        fleet.add_scan(ScanMessage("bench", "r", s.index, s.stamp, fit_scan(s.hits, s.no_return), s.pose))
    tile = Grid(np.array([-12.8, -12.8]), 0.05, (512, 512))
    fleet.occupancy(Grid(np.zeros(2), 0.05, (1, 1)))  # numba's compile, on a tile no node reaches
    t0 = time.perf_counter()
    fleet.occupancy(tile)  # the first tile at 5 cm: every node's samples are drawn too
    first = time.perf_counter() - t0
    rows = []
    for revision in range(1, 6):
        shift = 0.01 * revision
        update = PoseGraphUpdate(
            "bench", "r", revision, tuple((s.index, Pose(s.pose.R, s.pose.t + [shift, 0.0])) for s in scans)
        )
        raw = encode(update)
        t0 = time.perf_counter()
        decoded = decode(raw)
        t1 = time.perf_counter()
        fleet.apply_poses(decoded)
        t2 = time.perf_counter()
        fleet.occupancy(Grid(tile.origin + 0.05 * revision, tile.resolution, tile.shape))
        t3 = time.perf_counter()
        fleet.occupancy(tile)
        t4 = time.perf_counter()
        fleet.occupancy(tile)
        t5 = time.perf_counter()
        rows.append([t1 - t0, t2 - t1, t2 - t0, t3 - t2, t4 - t3, t5 - t4])
    med = 1000 * np.median(rows, axis=0)
    print(f"the first 512x512 tile at 5 cm of a fresh map (samples drawn): {1000 * first:.1f} ms")
    print(f"update of {len(scans)} nodes, {len(raw)} bytes; medians over 5 corrections (ms):")
    print(
        "| decode | apply | correction visible | 512x512 tile at 5 cm: cold | cached, after the correction | cached |"
    )
    print("|---|---|---|---|---|---|")
    print("| " + " | ".join(f"{v:.1f}" for v in med) + " |")


if __name__ == "__main__":
    main()
