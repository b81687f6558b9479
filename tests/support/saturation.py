"""Saturating a fleet map's tracers on purpose: every trace waits at a gate while requests queue."""

from __future__ import annotations

import threading
from contextlib import contextmanager

from services.map_server import tracers
from services.map_server.tracers import TracerPool
from support.net import wait_for


@contextmanager
def saturated_tracers(monkeypatch, fleet_map, cold_grids):
    """While the block runs, the tracers of `fleet_map` (one tracer thread) are saturated: a request
    per grid of `cold_grids` (tiles not cached) traces or queues, held at a gate, with the
    saturation bound set to the number queued. On leaving, the gate opens and those requests end."""
    assert fleet_map.trace_threads == 1
    monkeypatch.setattr(tracers, "SATURATED_QUEUE_PER_THREAD", len(cold_grids) - 1)
    gate = threading.Event()
    trace_part = TracerPool._trace_part

    def gated(pool, grid, entries):
        gate.wait(timeout=60)
        return trace_part(pool, grid, entries)

    monkeypatch.setattr(TracerPool, "_trace_part", gated)
    queued = [threading.Thread(target=fleet_map.occupancy, args=(grid,)) for grid in cold_grids]
    for thread in queued:
        thread.start()
    try:
        wait_for(lambda: fleet_map.cache_stats()["trace_queued"] == len(cold_grids) - 1, 20, "traces to queue")
        yield
    finally:
        gate.set()
        for thread in queued:
            thread.join(timeout=60)
