"""Tracing in processes (trace_workers.py): the same bits as the threads, a stop that ends them, and a
worker that died replaced by the next part."""

import os
import signal
import threading
import time

import numpy as np
import pytest

from gmm_core import Grid, Pose
from protocol import PoseGraphUpdate, encode
from services.map_server.fleet_map import FleetMap
from services.map_server.nodes import NodeKey
from services.map_server.store import Store
from services.map_server.trace_workers import BATCH_NODES, Traced, TraceWorker
from services.map_server.tracers import TRACER_NICE, TracingStopped
from support.fuzz import scan_message
from support.net import wait_for

GRID = Grid(np.array([-30.0, -30.0]), 0.25, (240, 240))


@pytest.fixture
def stored(tmp_path):
    """A store holding 2 * BATCH_NODES + 3 random 2D scans of robot_1 (more than one kernel batch),
    and the scans' messages."""
    rng = np.random.default_rng(11)
    messages = [scan_message(rng, 2, occupied=12, free=4, node=n) for n in range(2 * BATCH_NODES + 3)]
    store = Store(tmp_path)
    store.put_scans([(m, encode(m)) for m in messages])
    yield store, messages
    store.close()


def fleet_maps(store: Store, messages) -> tuple[FleetMap, FleetMap]:
    """The same scans in a map tracing in threads and in one tracing in processes (each nodes without bytes)."""
    maps = []
    for trace_store in (None, store.path):
        fleet_map = FleetMap(
            "fleet-a", trace_threads=2, stored_bytes=store.scan_reader("fleet-a"), trace_store=trace_store
        )
        fleet_map.add_scans([(m, len(encode(m)), encode(m)) for m in messages])
        maps.append(fleet_map)
    return maps[0], maps[1]


def test_processes_count_the_same_bits_as_threads(stored):
    store, messages = stored
    threads, processes = fleet_maps(store, messages)
    try:
        for a, b in zip(threads.counts(GRID), processes.counts(GRID)):
            assert a.any() and np.array_equal(a, b)
        assert np.array_equal(threads.occupancy(GRID), processes.occupancy(GRID))
        assert len(processes._tracers.worker_pids) >= 1 and threads._tracers.worker_pids == []
        for pid in processes._tracers.worker_pids:  # as low as the tracer threads, not lower
            assert os.getpriority(os.PRIO_PROCESS, pid) == min(19, os.getpriority(os.PRIO_PROCESS, 0) + TRACER_NICE)
        # a correction: the cached tiles update by tracing the moved nodes out and in again
        update = PoseGraphUpdate(
            "fleet-a", "robot_1", 1, tuple((n, Pose.from_xytheta(n * 0.1, 0.0, 0.2)) for n in range(9))
        )
        assert threads.apply_poses(update) and processes.apply_poses(update)
        assert np.array_equal(threads.occupancy(GRID), processes.occupancy(GRID))
    finally:
        threads.close()
        processes.close()


def test_close_ends_the_processes_and_a_trace_in_flight(stored):
    store, messages = stored
    fleet_map = FleetMap(
        "fleet-a",
        samples_per_cell=400.0,  # a trace of seconds
        trace_threads=1,
        stored_bytes=store.scan_reader("fleet-a"),
        trace_store=store.path,
    )
    fleet_map.add_scans([(m, len(encode(m)), encode(m)) for m in messages])
    outcome = []
    tracing = threading.Thread(target=lambda: outcome.append(_raised(fleet_map.counts, GRID)))
    tracing.start()
    wait_for(lambda: fleet_map._tracers.load().running and fleet_map._tracers.worker_pids, 60, "a trace in flight")
    (pid,) = fleet_map._tracers.worker_pids
    started = time.monotonic()
    fleet_map.close()
    tracing.join(5)
    assert outcome == [TracingStopped] and time.monotonic() - started < 2.0
    assert _gone(pid)


def test_a_worker_that_died_is_replaced_by_the_next_part(stored):
    store, messages = stored
    fleet_map = FleetMap("fleet-a", trace_threads=1, stored_bytes=store.scan_reader("fleet-a"), trace_store=store.path)
    fleet_map.add_scans([(m, len(encode(m)), encode(m)) for m in messages])
    try:
        expected = fleet_map.counts(GRID)
        (pid,) = fleet_map._tracers.worker_pids
        os.kill(pid, signal.SIGKILL)
        with pytest.raises(RuntimeError, match=f"tracer process {pid} ended"):
            fleet_map.counts(GRID)
        assert _gone(pid) and fleet_map._tracers.worker_pids == []  # reaped, forgotten
        again = fleet_map.counts(GRID)  # a new process, the same counts
        assert all(np.array_equal(a, b) for a, b in zip(expected, again))
        assert fleet_map._tracers.worker_pids not in ([], [pid])
    finally:
        fleet_map.close()


def test_a_node_missing_from_the_store_fails_its_part_and_the_worker_serves_on(stored):
    store, messages = stored
    worker = TraceWorker(store.path, "fleet-a", 4.0, nice=0)
    try:
        pose = Pose.from_xytheta(0.0, 0.0, 0.0)
        with pytest.raises(RuntimeError, match="LookupError: scan robot_1/999 of fleet 'fleet-a' is not in the store"):
            worker.trace(GRID, [Traced(1.0, NodeKey("robot_1", 999), 5, pose, None)])
        hits, misses = worker.trace(GRID, [])
        assert not hits.any() and not misses.any() and hits.shape == GRID.array_shape
    finally:
        worker.close()
    assert _gone(worker.pid)


def _raised(call, *args):
    try:
        call(*args)
    except Exception as error:
        return type(error)
    return None


def _gone(pid: int, timeout: float = 5.0) -> bool:
    """Whether process `pid` ended (and was reaped) within `timeout` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.05)
    return False
