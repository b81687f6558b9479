"""How soon a pose-graph correction of every Intel node is visible to the next query (issue 5).

Times, in one process: decoding the PoseGraphUpdate of all 910 nodes and applying it to the
FleetMap (which moves their boxes in the node index and marks the tiles they reach stale); then
a 512 x 512 tile at 5 cm: cold (a tile never asked for, nudged by one cell each round), the
update of the previously cached tile after the correction (every node subtracted at its old
pose and added at the new one), and cached.

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
    fleet.occupancy(tile)
    rows = []
    for revision in range(1, 6):
        shift = 0.01 * revision
        update = PoseGraphUpdate("bench", "r", revision, tuple(
            (s.index, Pose(s.pose.R, s.pose.t + [shift, 0.0])) for s in scans))
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
    print(f"update of {len(scans)} nodes, {len(raw)} bytes; medians over 5 corrections (ms):")
    print("| decode | apply | correction visible | 512x512 tile at 5 cm: cold | cached, after the correction "
          "| cached |")
    print("|---|---|---|---|---|---|")
    print("| " + " | ".join(f"{v:.1f}" for v in med) + " |")


if __name__ == "__main__":
    main()
