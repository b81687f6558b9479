"""Pose graphs in the durable store: per-node revisions survive a restart, so the restarted server
judges a late update as the live one would have; ingest acknowledges an update that changed nothing.
(Stores of older schemas: test_store_migration.py.)"""

import time

import numpy as np
import pytest

from gmm_core import fit_scan
from protocol import Ack, ScanMessage, decode, encode, poses_key
from services.map_server.fleet_map import FleetMap
from services.map_server.ingest import Ingest
from services.map_server.state import ServerState
from services.map_server.store import Store
from support.pose_graphs import FLEET, ReferenceGraph, pose, random_history, update


@pytest.fixture(scope="module")
def model():
    rng = np.random.default_rng(1)
    return fit_scan(rng.normal(size=(40, 2)) * 0.2 + [2.0, 0.0], np.zeros((0, 2)))


def replayed(data_dir) -> ServerState:
    """A server restarted on `data_dir`: a new FleetMap, filled by Ingest.replay from the store."""
    state = ServerState(FLEET, FleetMap(FLEET), Store(data_dir))
    Ingest(state, lambda *_: None).replay()
    return state


def graph_of(fleet_map: FleetMap):
    """The robot's graph in the model's terms, scans still on the way included, and its revision."""
    graph = fleet_map._nodes.robots["r"].graph
    nodes = {n: (rev, float(p.t[0])) for n, (rev, p) in graph.poses.items()}
    anchor = None if graph.anchor is None else (graph.anchor_revision, float(graph.anchor.t[0]))
    return nodes, anchor, graph.revision


def put(store: Store, message) -> bool:
    return store.put_poses(message)


def same_server(a: ServerState, b: ServerState) -> None:
    assert graph_of(a.fleet_map) == graph_of(b.fleet_map)
    assert np.array_equal(a.fleet_map.trajectory("r"), b.fleet_map.trajectory("r"))
    assert [r["pose_revision"] for r in a.fleet_map.robots()] == [r["pose_revision"] for r in b.fleet_map.robots()]


def test_a_restarted_server_judges_late_updates_as_the_live_one(tmp_path, model):
    for seed in range(25):
        rng = np.random.default_rng(seed)
        history = random_history(rng, nodes=6)
        live = ServerState(FLEET, FleetMap(FLEET), Store(tmp_path / str(seed)))
        for n in rng.permutation(6)[:4].tolist():  # the others' corrections wait for their scans
            message = ScanMessage(FLEET, "r", n, 0.0, model, pose(-1.0))
            live.store.put_scan(message, encode(message))
            live.fleet_map.add_scan(message)
        reference, cut = ReferenceGraph(), int(rng.integers(1, len(history)))
        for message in history[:cut]:  # as Ingest does: commit, then apply what changed something
            assert put(live.store, message) == reference.apply(message)
            live.fleet_map.apply_poses(message)
        live.store.close()
        restarted = replayed(tmp_path / str(seed))
        same_server(live, restarted)
        assert graph_of(live.fleet_map)[:2] == (reference.nodes, reference.anchor)
        for message in history[cut:]:
            changed = reference.apply(message)
            assert put(restarted.store, message) == changed, f"seed {seed}"
            assert restarted.fleet_map.apply_poses(message) == changed == live.fleet_map.apply_poses(message)
        same_server(live, restarted)
        restarted.store.close()
        same_server(live, replayed(tmp_path / str(seed)))


def test_ingest_acknowledges_an_update_that_changes_nothing(tmp_path):
    state = ServerState(FLEET, FleetMap(FLEET), Store(tmp_path))
    acks = []
    ingest = Ingest(state, lambda key, payload: acks.append(decode(payload, expect=Ack)))
    ingest.start()
    for message in (update(2, [(0, 1.0)]), update(1, [(0, 0.5)]), update(2, [(0, 1.0)])):
        ingest.submit(poses_key(FLEET, "r"), encode(message))
    deadline = time.monotonic() + 10
    while len(acks) < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    ingest.stop()
    assert [(a.kind, a.ids) for a in acks] == [("poses", (2,)), ("poses", (1,)), ("poses", (2,))]
    assert graph_of(state.fleet_map)[:2] == ({0: (2, 1.0)}, None)


def test_an_update_writes_the_rows_of_the_nodes_it_takes_and_its_robots_row(tmp_path):
    store = Store(tmp_path)
    assert put(store, update(1, [(n, 0.0) for n in range(1000)], anchor=0.0))
    written = store._db.total_changes
    assert put(store, update(3, [(5, 1.0), (6, 0.0), (7, 0.5)]))  # node 6: an equal pose, a newer revision
    assert store._db.total_changes - written == 3 + 1
    written = store._db.total_changes
    assert put(store, update(2, [(5, 0.0), (8, 1.5)]))  # node 5 is revision 3's: only node 8's row
    assert store._db.total_changes - written == 1 + 1
    store.close()
    held = Store(tmp_path).pose_graph(FLEET, "r")
    assert [(n, p.t[0]) for n, p in held.poses[4:10]] == [(4, 0.0), (5, 1.0), (6, 0.0), (7, 0.5), (8, 1.5), (9, 0.0)]
