"""Ingest under load: scans waiting in the queue are announced to their robots (Ack.queued), and
the map's tracers wait while a batch is ingested (ingest first); a map asked for before its first
scan still takes, acknowledges and counts that scan; what a failed batch stored counts toward the quota."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from gmm_core import Grid, Pose, fit_scan
from protocol import Ack, PoseGraphUpdate, ScanMessage, decode, encode, scan_key
from services.map_server import ingest as ingest_module
from services.map_server.fleet_map import FleetMap
from services.map_server.ingest import Ingest
from services.map_server.state import ServerState
from services.map_server.store import Store
from services.map_server.tracers import TracerPool
from support.ingest import ingested, key_of, scan_of, stored_bytes


@pytest.fixture(scope="module")
def model():
    rng = np.random.default_rng(1)
    return fit_scan(rng.normal(size=(40, 2)) * 0.2 + [2.0, 0.0], np.zeros((0, 2)))


def scan(model, node: int) -> ScanMessage:
    return ScanMessage("default", "r", node, float(node), model, Pose.from_xytheta(0.0, 0.0, 0.0))


class SlowStore(Store):
    """A store whose commits wait for `release`: a server that has fallen behind."""

    def __init__(self, path):
        super().__init__(path)
        self.committing = threading.Event()
        self.release = threading.Event()

    def put_scans(self, batch, entries=None):
        self.committing.set()
        self.release.wait(10)
        return super().put_scans(batch, entries)


def wait_for(condition, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_scans_waiting_in_the_queue_are_announced_until_stored(tmp_path, model, monkeypatch):
    monkeypatch.setattr(ingest_module, "QUEUED_ACK_S", 0.2)
    store = SlowStore(tmp_path)
    answers: list[Ack] = []
    ingest = Ingest(ServerState("default", FleetMap("default"), store), lambda _, raw: answers.append(decode(raw)))
    ingest.start()
    try:
        ingest.submit(scan_key("default", "r", 0), encode(scan(model, 0)))
        assert store.committing.wait(10)  # scan 0 is being stored; 1 and 2 wait behind it
        for node in (1, 2):
            ingest.submit(scan_key("default", "r", node), encode(scan(model, node)))
        wait_for(lambda: any(a.queued == (0, 1, 2) for a in answers))
        assert all(a.ids == () for a in answers)  # nothing is acknowledged before its commit
        store.release.set()
        wait_for(lambda: sorted(n for a in answers for n in a.ids) == [0, 1, 2])
        after = len(answers)
        time.sleep(0.5)  # stored: no longer announced
        assert len(answers) == after
    finally:
        store.release.set()
        ingest.stop()


def test_tracers_wait_while_a_batch_is_ingested(model, monkeypatch):
    """A trace begun while ingest holds the tracers waits at its first node until the batch is done,
    then ends with the counts it would have had. Its kernels are compiled (or loaded) by the same trace
    before the hold, and the hold is timed from the moment the tracer reaches it: compiling on a cold
    numba cache took longer than the 10 s this test once gave the whole trace."""
    fleet = FleetMap("default", trace_threads=1)
    for node in range(4):
        fleet.add_scan(scan(model, node))
    grid = Grid.from_bbox([0.0, -2.0], [4.0, 2.0], 0.1)
    unheld = fleet.counts(grid)
    held, done, answers = threading.Event(), threading.Event(), []
    wait_for_ingest = TracerPool._wait_for_ingest

    def reached(pool):
        held.set()
        wait_for_ingest(pool)

    monkeypatch.setattr(TracerPool, "_wait_for_ingest", reached)
    with fleet.ingest_first():
        threading.Thread(target=lambda: (answers.append(fleet.counts(grid)), done.set()), daemon=True).start()
        assert held.wait(60)  # the tracer is at the hold ...
        assert not done.wait(0.5)  # ... and stays there while the batch is ingested (traced, it takes ms)
    assert done.wait(60)
    np.testing.assert_array_equal(answers[0], unheld)


def test_a_batch_holds_the_tracers_only_when_its_oldest_message_waited(tmp_path, model, monkeypatch):
    """Ingest holds the tracers for a batch whose oldest message waited over HOLD_TRACERS_AFTER_S in
    the queue (it is falling behind); a server that keeps up lets them trace."""
    fleet = FleetMap("default")
    holds = []
    hold = fleet.ingest_first

    def counted_hold():
        holds.append(1)
        return hold()

    monkeypatch.setattr(fleet, "ingest_first", counted_hold)
    answers: list[Ack] = []
    ingest = Ingest(ServerState("default", fleet, Store(tmp_path)), lambda _, raw: answers.append(decode(raw)))
    ingest.start()
    try:
        ingest.submit(scan_key("default", "r", 0), encode(scan(model, 0)))
        wait_for(lambda: any(a.ids == (0,) for a in answers))
        assert holds == []  # kept up
        monkeypatch.setattr(ingest_module, "HOLD_TRACERS_AFTER_S", -1.0)  # every message has waited longer
        ingest.submit(scan_key("default", "r", 1), encode(scan(model, 1)))
        wait_for(lambda: any(a.ids == (1,) for a in answers))
        assert holds == [1]
    finally:
        ingest.stop()


@pytest.mark.parametrize("asked, scanned", [(2, 3), (3, 2)])
def test_a_tile_asked_for_before_the_first_scan_leaves_ingest_and_the_quota_working(tmp_path, asked, scanned):
    """A map with no scan yet answers a grid of either dimension (a viewer, a robot's MapQuery at
    start-up); the first scans, of the other dimension, are then stored, acknowledged and counted."""
    state = ServerState("default", FleetMap("default"), Store(tmp_path))
    state.fleet_map.occupancy(Grid.from_bbox([-20.0] * asked, [20.0] * asked, 0.5))
    messages = [scan_of(scanned, node) for node in (0, 1)]
    answers = ingested(state, messages, quota_bytes=1 << 20)
    assert [(type(a).__name__, a.ids) for a in answers] == [("Ack", (0, 1))]
    assert stored_bytes(state, "r") == sum(len(encode(m)) for m in messages)


def test_scans_stored_by_a_batch_that_then_fails_count_toward_the_quota(tmp_path, monkeypatch):
    """Such scans are not acknowledged: their robot resends them and finds them held, so their bytes
    count when they are committed or never."""
    state = ServerState("default", FleetMap("default"), Store(tmp_path))
    first, second = scan_of(2, 0), scan_of(2, 1)
    size = len(encode(first))
    answers: list = []
    ingest = Ingest(state, lambda _, raw: answers.append(decode(raw)), quota_bytes=size + len(encode(second)) // 2)
    add_entries, failed = state.fleet_map.add_entries, threading.Event()

    def failing(*args):
        failed.set()
        raise RuntimeError("the map failed after the commit")

    monkeypatch.setattr(state.fleet_map, "add_entries", failing)
    ingest.start()
    try:
        ingest.submit(key_of(first), encode(first))
        assert failed.wait(60)
        wait_for(lambda: state.store.nodes("default", "r") == {0})
        assert stored_bytes(state, "r") == size and not any(a.ids for a in answers)  # none acknowledged
        monkeypatch.setattr(state.fleet_map, "add_entries", add_entries)
        for message in (first, second):  # the resend, and a scan the quota has no room for
            ingest.submit(key_of(message), encode(message))
        wait_for(lambda: len([a for a in answers if a.ids]) == 2)
    finally:
        ingest.stop()
    assert sorted((type(a).__name__, a.ids) for a in answers if a.ids) == [("Ack", (0,)), ("Rejection", (1,))]
    assert stored_bytes(state, "r") == size


@pytest.mark.parametrize("dim", [2, 3])
def test_a_message_of_the_other_dimension_is_refused_with_a_rejection_naming_it(tmp_path, dim):
    state = ServerState("default", FleetMap("default"), Store(tmp_path))
    other = 5 - dim
    update = PoseGraphUpdate("default", "r3", 4, ((0, scan_of(other, 0).pose),))
    answers = ingested(state, [scan_of(dim, 0), scan_of(other, 1, robot="r3"), update])
    assert [(type(a).__name__, a.robot, a.kind, a.ids) for a in answers] == [
        ("Rejection", "r3", "scan", (1,)),
        ("Rejection", "r3", "poses", (4,)),
        ("Ack", "r", "scan", (0,)),
    ]
    detail = f"this map is {dim}D, the message is {other}D"
    assert [(a.reason, a.detail) for a in answers[:2]] == [("dimension", detail)] * 2
    assert answers[0].store == state.store.identity
    assert state.metrics.rejected_total() == 2 and state.store.nodes("default", "r3") == set()
