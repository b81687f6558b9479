"""The offline maps of a run, rebuilt box by box and snapshot by snapshot, equal the map server's."""

from dataclasses import replace

import numpy as np

from gmm_core import fit_scan
from protocol import ScanMessage, decode, encode
from services.config import GmmapConfig
from services.map_server.fleet_map import FleetMap
from services.sim import rebuild
from services.sim.fleet import SimulatedFleet
from services.sim.record import RunRecord, evaluation_grid
from services.sim.trajectory import path_pose


def test_offline_maps_equal_a_fleet_map_of_the_scans_stored_by_each_snapshot(monkeypatch):
    fleet = SimulatedFleet("office", 1, 10, 5.0, seed=2)
    config = GmmapConfig()
    stored = {}
    for scan in fleet.scans(0, 0):
        model = fit_scan(scan.hits, scan.no_return, config.fit.for_dimension(2))
        # Published at the true pose, an estimate centimetres from the odometry, so the two offline maps differ.
        stored["r0", scan.index] = encode(ScanMessage("default", "r0", scan.index, scan.stamp, model, scan.pose))
    del stored["r0", 3]  # a scan the store lacks
    record = RunRecord(config, fleet, evaluation_grid(fleet), 0, 0.0, stored=stored)
    monkeypatch.setattr(rebuild, "BOX_CELLS", record.grid.n_cells // 5)  # several boxes
    stored_at = [{"r0": 4}, {"r0": 10}]
    maps = rebuild.offline_maps(record, stored_at, lambda n: None)
    for j, stored_by in enumerate(stored_at):
        served = {name: FleetMap("default", samples_per_cell=config.reconstruction.samples_per_cell) for name in maps}
        for (robot, node), raw in stored.items():
            if node < stored_by[robot]:
                message = decode(raw, expect=ScanMessage)
                served["published_estimates"].add_scan(message)
                served["odometry"].add_scan(replace(message, pose=path_pose(fleet.odometry[0][node])))
        for name, fleet_map in served.items():
            assert np.array_equal(maps[name][j], fleet_map.occupancy(record.grid)), (name, j)
    assert not np.array_equal(maps["odometry"][1], maps["published_estimates"][1])
