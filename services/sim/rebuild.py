"""The maps the server would have served without pose-graph updates, rebuilt offline with the
server's own code (FleetMap) from the scan models it stored (render.MEASUREMENT_NOTES, "Maps")."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import replace

import numpy as np

from protocol import ScanMessage, decode
from services.map_server.fleet_map import FleetMap
from services.sim.fleet import robot_name
from services.sim.record import RunRecord, slabs
from services.sim.trajectory import path_pose


def offline_maps(record: RunRecord, stored_at: list[dict[str, int]], progress) -> dict[str, list[np.ndarray]]:
    """The published-estimate and odometry maps of the scans stored by each snapshot (server code)."""
    messages = {key: decode(raw, expect=ScanMessage) for key, raw in record.stored.items()}
    r = record.config.reconstruction  # as the server reconstructs
    maps = {
        name: FleetMap(record.options.fleet, samples_per_cell=r.samples_per_cell, prior=r.prior)
        for name in ("published_estimates", "odometry")
    }
    robots = {robot_name(i): i for i in range(record.fleet.robots)}
    added: dict[str, int] = defaultdict(int)
    out: dict[str, list[np.ndarray]] = {name: [] for name in maps}
    for stored in stored_at:
        for robot, count in stored.items():
            for node in range(added[robot], count):
                message = messages.get((robot, node))
                if message is None:
                    continue
                odometry = path_pose(record.fleet.odometry[robots[robot]][node])
                maps["published_estimates"].add_scan(message)
                maps["odometry"].add_scan(replace(message, pose=odometry))
            added[robot] = max(added[robot], count)
        for name, fleet_map in maps.items():
            out[name].append(np.concatenate([fleet_map.occupancy(slab) for slab in slabs(record.grid)]))
        progress(1)
    return out
