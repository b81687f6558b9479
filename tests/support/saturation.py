"""Holding a fleet map's tracers on purpose: every part traced waits at a gate, so requests stay
in flight (saturating the tracers, or meeting a stop)."""

from __future__ import annotations

import threading
from contextlib import contextmanager

from services.map_server import tracers
from services.map_server.tracers import TracerPool
from support.net import wait_for


@contextmanager
def held_traces(monkeypatch):
    """While the block runs, every part a TracerPool traces waits at a gate before it starts; the
    list it yields holds the grid of each part that reached the gate. On leaving, the gate opens."""
    gate, held = threading.Event(), []
    trace_part = TracerPool._trace_part

    def gated(pool, grid, entries):
        held.append(grid)
        gate.wait(timeout=60)
        return trace_part(pool, grid, entries)

    monkeypatch.setattr(TracerPool, "_trace_part", gated)
    try:
        yield held
    finally:
        gate.set()


@contextmanager
def saturated_tracers(monkeypatch, fleet_map, cold_grids):
    """While the block runs, the tracers of `fleet_map` (one tracer thread) are saturated: a request
    per grid of `cold_grids` (tiles not cached) traces or queues, held at a gate, with the
    saturation bound set to the number queued. On leaving, the gate opens and those requests end."""
    assert fleet_map.trace_threads == 1
    monkeypatch.setattr(tracers, "SATURATED_QUEUE_PER_THREAD", len(cold_grids) - 1)
    queued = [threading.Thread(target=fleet_map.occupancy, args=(grid,)) for grid in cold_grids]
    try:
        with held_traces(monkeypatch):
            for thread in queued:
                thread.start()
            wait_for(lambda: fleet_map.cache_stats()["trace_queued"] == len(cold_grids) - 1, 20, "traces to queue")
            yield
    finally:
        for thread in queued:
            thread.join(timeout=60)
