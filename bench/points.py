"""Occupancy at points: analytic evidence (Eq. 3-10 per cell) against Monte Carlo, cost per point.

    PYTHONPATH=. .venv/bin/python bench/points.py

Two maps in a FleetMap (one tracer thread): 2D, the Intel log's 910 scans (fitted here); 3D,
the mine sim's map (bench/mine_map.py). Points are drawn uniformly in the box of each map's node
origins. For n scattered points (each its own cell, as services/api/points.py plans them: one
Monte-Carlo grid per point) and for a lattice of 64 x 64 (2D) or 16 x 16 x 16 (3D) cell centres
(one grid), the time of `point_probabilities` with method analytic and mc; processor seconds,
the median of 3, after both kernels ran once. The mc runs on a fresh FleetMap each time, so the
node's sample descriptions are made each time, as in a cold query. The break-even, in points
per Monte-Carlo grid, is what services/api/points.py's `auto` uses.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import mine_map  # noqa: E402
from query3d import machine_line  # noqa: E402

from gmm_core import fit_scan  # noqa: E402
from protocol import ScanMessage, decode, encode  # noqa: E402
from services.api.points import plan, point_probabilities  # noqa: E402
from services.datasets import read_scans  # noqa: E402
from services.map_server.fleet_map import FleetMap  # noqa: E402

INTEL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "carmen" / "intel-corrected.log.gz"
RUNS = 3


def intel_messages() -> list[bytes]:
    scans = list(read_scans(INTEL))
    return [encode(ScanMessage("bench", "r", s.index, s.stamp, fit_scan(s.hits, s.no_return), s.pose)) for s in scans]


def fleet(messages: list[bytes], updates: list[bytes]) -> FleetMap:
    fleet_map = FleetMap(decode(messages[0], expect=ScanMessage).fleet, trace_threads=1)
    fleet_map.add_scans([(decode(raw, expect=ScanMessage), len(raw), raw) for raw in messages])
    for raw in updates:
        fleet_map.apply_poses(decode(raw))
    return fleet_map


def seconds(messages, updates, points, resolution, method) -> float:
    runs = []
    for _ in range(RUNS):
        fleet_map = fleet(messages, updates)
        start = time.process_time()
        point_probabilities(fleet_map, points, resolution, method=method)
        runs.append(time.process_time() - start)
    return float(np.median(runs))


def measure(name: str, messages: list[bytes], updates: list[bytes], resolution: float, lattice: int) -> None:
    fleet_map = fleet(messages, updates)
    dim = fleet_map.dim
    origins = np.concatenate([fleet_map.trajectory(r["robot"]) for r in fleet_map.robots()])
    lo, hi = origins.min(axis=0), origins.max(axis=0)
    rng = np.random.default_rng(0)
    for method in ("analytic", "mc"):  # compile or load the kernels
        point_probabilities(fleet_map, rng.uniform(lo, hi, (2, dim)), resolution, method=method)
    print(f"{name}: {len(messages)} nodes, cells of {resolution} m")
    per_point = {}
    for n in (1, 10, 100):
        points = rng.uniform(lo, hi, (n, dim))
        grids = len(plan(points, resolution))
        t = {m: seconds(messages, updates, points, resolution, m) for m in ("analytic", "mc")}
        per_point[n] = t
        print(
            f"  {n:4d} scattered points ({grids} grids): analytic {1e3 * t['analytic'] / n:8.2f} ms/point, "
            f"mc {1e3 * t['mc'] / n:8.2f} ms/point"
        )
    centre = (lo + hi) / 2
    cells = np.stack(np.meshgrid(*[np.arange(lattice)] * dim, indexing="ij"), -1).reshape(-1, dim)
    points = centre + (cells + 0.5) * resolution
    t = {m: seconds(messages, updates, points, resolution, m) for m in ("analytic", "mc")}
    print(
        f"  lattice of {len(points)} cell centres ({len(plan(points, resolution))} grid): "
        f"analytic {1e3 * t['analytic'] / len(points):8.3f} ms/point, mc {1e3 * t['mc'] / len(points):8.3f} ms/point"
    )
    t100 = per_point[100]
    print(f"  break-even: one point analytically costs {t100['analytic'] / t100['mc']:.2f} Monte-Carlo grids")


def main() -> None:
    print(machine_line())
    measure("2D Intel", intel_messages(), [], 0.05, 64)
    messages, updates, _ = mine_map.load()
    measure("3D mine sim", messages, updates, 0.1, 16)


if __name__ == "__main__":
    main()
