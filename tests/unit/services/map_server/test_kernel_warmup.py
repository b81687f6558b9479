"""The warm-up's throwaway map (services/map_server/warmup.py)."""

import logging

import numpy as np

from gmm_core import Grid
from services.map_server import tile_updates
from services.map_server.fleet_map import FleetMap
from services.map_server.warmup import _scan, warm_kernels


def test_the_warm_up_logs_no_slow_tile_update(monkeypatch, caplog):
    """On an empty numba cache its updates wait seconds for the compiler: a demo on a fresh machine
    printed "a tile update took 5.1 s" before any robot ran. A served map still logs them."""
    monkeypatch.setattr(tile_updates, "SLOW_UPDATE_S", -1.0)  # every update counts as slow
    slow = lambda: [r for r in caplog.records if r.getMessage().startswith("a tile update took")]  # noqa: E731
    with caplog.at_level(logging.WARNING, logger="gmmap.server"):
        warm_kernels()
        assert not slow()
        served = FleetMap("f", trace_threads=1)
        try:
            served.add_scan(*_scan(2, 0, "q"))
            served.occupancy(Grid(np.full(2, -2.0), 0.5, (8, 8)))
        finally:
            served.close()
        assert len(slow()) == 1
