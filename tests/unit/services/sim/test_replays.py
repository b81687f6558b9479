"""The beam replays of a run: each robot's, in worker processes, equal the plain replay; the cells
each snapshot had observed, from the first-seen counts, equal the counting grid of every scan
stored by then, traced over the whole grid."""

import importlib.util

import numpy as np

from gmm_core import FitConfig
from gmm_core.reconstruct import count_beams
from services.config import GmmapConfig
from services.sim.byte_models import never, observed_masks, replay_robot
from services.sim.fleet import SimulatedFleet
from services.sim.record import RunRecord, evaluation_grid
from services.sim.replays import BeamReplays


def test_replays_in_workers_give_the_plain_replay_and_the_observed_cells_of_each_snapshot():
    fleet = SimulatedFleet("office", 2, 9, 5.0, seed=3)
    grid = evaluation_grid(fleet)
    published = {"r0": 9, "r1": 7}  # r1's last two scans never sent
    record = RunRecord(GmmapConfig(), fleet, grid, 4, 0.0, published=published)
    replays = BeamReplays(record)
    per_scan, first_seen = replays.results(lambda n: None)
    for index, name in enumerate(("r0", "r1")):
        sizes, first = replay_robot(fleet, grid, 4, index, published[name], 1)
        assert np.array_equal(first, first_seen[name])
        assert sizes.keys() == per_scan[name].keys()
        assert all(np.array_equal(sizes[key], per_scan[name][key]) for key in sizes)
        assert len(sizes["raw"]) == published[name] and (sizes["grid"] > 0).all()
        assert ("octomap" in sizes) == (importlib.util.find_spec("octomap") is not None)
        assert first.dtype == np.uint16 and first.max() == never(published[name])

    scans = {name: list(fleet.scans(i, 4))[: published[name]] for i, name in enumerate(("r0", "r1"))}
    stored_at = [{"r0": 0}, {"r0": 1, "r1": 0}, {"r0": 4, "r1": 5}, {"r0": 9, "r1": 7}]
    max_range = FitConfig().max_range
    for stored, mask in zip(stored_at, observed_masks(grid, first_seen, stored_at), strict=True):
        expected = np.zeros(grid.array_shape, bool)
        for name, count in stored.items():
            if count:
                beams = [(s.hits, s.no_return, s.pose) for s in scans[name][:count]]
                hits, misses = count_beams(grid, beams, max_range)
                expected |= (hits + misses) > 0
        assert np.array_equal(mask, expected), stored
    assert not observed_masks(grid, first_seen, stored_at)[0].any()
    assert never(65_534).dtype == np.uint16 and never(65_535).dtype == np.uint32


def test_replays_closed_before_grading_begins_end_without_replaying():
    fleet = SimulatedFleet("office", 1, 3, 5.0, seed=3)
    record = RunRecord(GmmapConfig(), fleet, evaluation_grid(fleet), 4, 0.0, published={"r0": 3})
    replays = BeamReplays(record)
    replays.close()  # returns (a worker waiting for `begin` is let go, or ended with its thread)
    futures = list(replays._futures.values())
    assert len(futures) == 1 and futures[0].done()
