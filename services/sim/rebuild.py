"""The maps the server would have served without pose-graph updates, rebuilt offline with the
server's own reconstruction from the scan models it stored (render.MEASUREMENT_NOTES, "Maps").

The server's tiles are sums of each node's counts (gmm_core.scan_trace.GridCounts: float64 sums
of quantised weights, exact in any order) turned into p(occupied) by Eq. 11 in float32, as here.
Counts are additive, so each snapshot's map adds only the scans stored since the one before: a
scan is traced once per box of the graded grid, not once per snapshot.
"""

from __future__ import annotations

from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from gmm_core import Grid
from gmm_core.occupancy import monte_carlo_estimate
from gmm_core.sampling import ScanSamples, scan_samples, scan_seed
from gmm_core.scan_trace import GridCounts
from protocol import ScanMessage, decode
from services.host import cpu_cores
from services.sim.fleet import robot_name
from services.sim.record import RunRecord, blocks
from services.sim.trajectory import path_pose

BOX_CELLS = 4_000_000  # cells per box rebuilt at a time (its float64 counts: 64 MB)


def offline_maps(record: RunRecord, stored_at: list[dict[str, int]], progress) -> dict[str, list[np.ndarray]]:
    """The published-estimate and odometry maps of the scans stored by each snapshot (server code)."""
    messages = {key: decode(raw, expect=ScanMessage) for key, raw in record.stored.items()}
    r = record.config.reconstruction  # as the server reconstructs
    robots = {robot_name(i): i for i in range(record.fleet.robots)}
    poses = {
        "published_estimates": lambda robot, node, message: message.pose,
        "odometry": lambda robot, node, message: path_pose(record.fleet.odometry[robots[robot]][node]),
    }
    grid = record.grid
    samples: dict[tuple[str, int], ScanSamples] = {}
    out = {name: [np.empty(grid.array_shape, np.float32) for _ in stored_at] for name in poses}

    def rebuild(name: str, box: Grid, place: tuple[slice, ...]) -> None:
        counts = GridCounts(box)
        added: dict[str, int] = defaultdict(int)
        for j, stored in enumerate(stored_at):
            for robot, count in stored.items():
                for node in range(added[robot], count):
                    message = messages.get((robot, node))
                    if message is None:
                        continue
                    if (robot, node) not in samples:
                        seed = scan_seed(robot, node)  # the server's seed of the node
                        samples[robot, node] = scan_samples(message.model, grid.resolution, seed, r.samples_per_cell)
                    counts.add(samples[robot, node], poses[name](robot, node, message))
                added[robot] = max(added[robot], count)
            hits, misses = counts.arrays()
            out[name][j][place] = monte_carlo_estimate(hits, misses, r.samples_per_cell, r.prior)

    # The tracer runs outside the GIL: the maps are rebuilt on threads of their own, box by box.
    with ThreadPoolExecutor(min(len(poses), cpu_cores())) as pool:
        for box, place in blocks(grid, BOX_CELLS):
            for future in [pool.submit(rebuild, name, box, place) for name in poses]:
                future.result()
    progress(len(stored_at))
    return out
