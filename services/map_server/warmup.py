"""Numba's compiled kernels loaded before a map server serves: a throwaway map of one small scan.

numba compiles (or loads from its cache) a kernel at its first call, under the interpreter lock:
in a fresh server the first decoded scans and the first tile waited about 0.6 s for it
(decoding, samplers, tracing, Eq. 11), while the robots' first scans queued behind them
(docs/RELIABILITY.md, "Eighth session"). `warm_kernels` makes those first calls on a map of its
own, before the server subscribes or listens: the same code paths as ingest and a tile (and its
picture), in 2D and 3D, with both scan encodings and a pose-graph update, and a point query by
either method (without it, a fresh server's first analytic point query compiled for 2 s).
"""

from __future__ import annotations

import time

import numpy as np

from gmm_core import Grid, Mixture, Pose, ScanModel
from protocol import PoseGraphUpdate, ScanMessage, decode, encode
from services.api.points import evaluate
from services.render import occupancy_png

from .fleet_map import FleetMap
from .nodes import ScanEntry

_FLEET, _ROBOT = "warm-up", "r"


def _scan(dim: int, node: int, encoding: str) -> tuple[ScanMessage, int, bytes]:
    """A scan of two components, one each side of the sensor, as ingest receives it (decoded, size, bytes)."""
    means = np.array([[1.0] * dim, [-1.0] * dim])
    mixture = Mixture(np.array([0.5, 0.5]), means, np.stack([0.01 * np.eye(dim)] * 2), 20)
    pose = Pose.identity(dim)
    raw = encode(
        ScanMessage(_FLEET, _ROBOT, node, float(node), ScanModel(mixture, mixture, np.zeros(dim), 5.0), pose), encoding
    )
    return decode(raw, expect=ScanMessage), len(raw), raw


def warm_kernels() -> float:
    """Run a scan's path through a throwaway FleetMap in 2D and 3D; returns the seconds it took."""
    start = time.perf_counter()
    for dim in (2, 3):
        # Its updates wait for numba's compiler on an empty cache: not a slow map worth a warning.
        fleet_map = FleetMap(_FLEET, trace_threads=1, report_slow_updates=False)
        try:
            scans = [_scan(dim, node, encoding) for node, encoding in enumerate(("q", "f32"))]
            # As ingest adds them: the entries, with the models it decoded.
            fleet_map.add_entries([ScanEntry.of(*scan) for scan in scans], [msg.model for msg, _, _ in scans])
            grid = Grid(np.full(dim, -2.0), 0.5, (8,) * dim)
            prob = fleet_map.occupancy(grid)
            occupancy_png(prob)  # a tile's picture ...
            occupancy_png(prob[1:, 1:])  # ... and a layer's window's (a strided view: compiled apart)
            moved = Pose(np.eye(dim), np.full(dim, 0.6))
            fleet_map.apply_poses(PoseGraphUpdate(_FLEET, _ROBOT, 1, ((0, moved), (1, moved))))
            fleet_map.occupancy(grid)  # the moved nodes traced out and in again
            for method in ("analytic", "mc"):  # a point query, as the HTTP API and the Zenoh queryable answer it
                evaluate(fleet_map, np.zeros((2, dim)), 0.5, None, method)
        finally:
            fleet_map.close()
    return time.perf_counter() - start
