"""Stores written by the first two schemas (one merged PoseGraphUpdate per robot in `poses.raw`, with
or without per-node revisions) are converted when opened, and a restarted server on them judges a
late update as the server that wrote them did. The old files are made here with the old schema SQL."""

import sqlite3
import time

import numpy as np
import pytest

from gmm_core import fit_scan
from protocol import ScanMessage, encode
from services.map_server.check import check_store
from services.map_server.fleet_map import FleetMap
from services.map_server.ingest import Ingest
from services.map_server.pose_graph import PoseGraph
from services.map_server.state import ServerState
from services.map_server.store import DB_NAME, Store
from support.pose_graphs import FLEET, ReferenceGraph, pose, random_history, update

# The schema of the merged rows, as the code before per-node rows created it (v1 lacked the last two columns).
MERGED_SCHEMA = """
CREATE TABLE scans (
    fleet TEXT NOT NULL, robot TEXT NOT NULL, node INTEGER NOT NULL,
    stamp REAL NOT NULL, size INTEGER NOT NULL, received REAL NOT NULL, raw BLOB NOT NULL,
    PRIMARY KEY (fleet, robot, node)
) WITHOUT ROWID;
CREATE TABLE meta (name TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE poses (
    fleet TEXT NOT NULL, robot TEXT NOT NULL, revision INTEGER NOT NULL,
    received REAL NOT NULL, raw BLOB NOT NULL,
    node_revisions BLOB, anchor_revision INTEGER,
    PRIMARY KEY (fleet, robot)
) WITHOUT ROWID;
INSERT INTO meta VALUES ('store', 'an-old-store');
"""
V1_POSES = """
CREATE TABLE poses (
    fleet TEXT NOT NULL, robot TEXT NOT NULL, revision INTEGER NOT NULL,
    received REAL NOT NULL, raw BLOB NOT NULL,
    PRIMARY KEY (fleet, robot)
) WITHOUT ROWID;
"""


@pytest.fixture(scope="module")
def model():
    rng = np.random.default_rng(1)
    return fit_scan(rng.normal(size=(40, 2)) * 0.2 + [2.0, 0.0], np.zeros((0, 2)))


def write_merged(data_dir, graphs: dict[str, PoseGraph], as_sent: dict[str, bytes] | None = None) -> None:
    """A store as the merged-row code left it: per robot the graph's as_update and its node revisions,
    or (as_sent) the bytes of the one update that made the whole graph, with NULL revisions."""
    with sqlite3.connect(data_dir / DB_NAME) as db:
        db.executescript(MERGED_SCHEMA)
        for robot, graph in graphs.items():
            if robot in (as_sent or {}):
                row = (as_sent[robot], None, None)
            else:
                revisions = np.array([graph.poses[n][0] for n in sorted(graph.poses)], dtype="<u8").tobytes()
                anchor_revision = graph.anchor_revision if graph.anchor is not None else None
                row = (encode(graph.as_update(FLEET, robot)), revisions, anchor_revision)
            db.execute("INSERT INTO poses VALUES (?, ?, ?, ?, ?, ?, ?)", (FLEET, robot, graph.revision, 1.0, *row))
    db.close()


def state(graph: PoseGraph):
    nodes = {n: (rev, float(p.t[0])) for n, (rev, p) in graph.poses.items()}
    return nodes, None if graph.anchor is None else (graph.anchor_revision, float(graph.anchor.t[0])), graph.revision


def tables(data_dir) -> set[str]:
    with sqlite3.connect(data_dir / DB_NAME) as db:
        names = {name for (name,) in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    db.close()
    return names


def dump(data_dir) -> list[str]:
    """Schema and rows, as SQL."""
    db = sqlite3.connect(data_dir / DB_NAME)
    try:
        return list(db.iterdump())
    finally:
        db.close()


def test_merged_rows_become_node_rows_with_their_revisions(tmp_path):
    graph = PoseGraph()
    for message in (update(4, [(1, 1.0), (5, 0.5)], anchor=1.5), update(2, [(0, 0.0), (1, 0.5)]), update(9, [(5, 0)])):
        graph.apply(message)
    whole = update(3, [(0, 1.0), (2, 0.5)], anchor=0.0, robot="q")  # q's graph is one update, kept as sent
    write_merged(tmp_path, {"r": graph, "q": PoseGraph()}, as_sent={"q": encode(whole)})
    store = Store(tmp_path)
    assert store.identity == "an-old-store"  # robots must not take it for another store
    assert tables(tmp_path) == {"scans", "meta", "poses", "node_poses"}
    pieces = [(r.message.robot, r.message.revision, [n for n, _ in r.message.poses]) for r in store.load(FLEET)]
    assert pieces == [("q", 3, [0, 2]), ("r", 2, [0]), ("r", 4, [1]), ("r", 9, [5])]
    assert [r.message.anchor is not None for r in store.load(FLEET)] == [True, False, True, False]
    assert store.inventory(FLEET, "r").revision == 9 and store.inventory(FLEET, "q").revision == 3
    held = store.pose_graph(FLEET, "r")
    assert [(n, p.t[0]) for n, p in held.poses] == [(0, 0.0), (1, 1.0), (5, 0.0)] and held.anchor.t[0] == 1.5
    assert not store.put_poses(update(3, [(1, 2.0)], anchor=2.0))  # node 1 and the anchor are revision 4's
    assert store.put_poses(update(3, [(0, 2.0)]))  # node 0 is only revision 2's
    assert not store.put_poses(update(3, [(2, 0.5)], robot="q"))  # a resent part of q's revision 3
    store.close()
    store = Store(tmp_path)  # converted once; reopened, the rows are read as they are
    assert store.identity == "an-old-store"
    assert [(n, p.t[0]) for n, p in store.pose_graph(FLEET, "r").poses] == [(0, 2.0), (1, 1.0), (5, 0.0)]
    store.close()
    assert check_store(tmp_path).ok


def test_a_first_schema_row_puts_every_node_and_the_anchor_at_its_revision(tmp_path):
    merged = update(5, [(0, 1.0), (1, 1.0)], anchor=0.5)
    with sqlite3.connect(tmp_path / DB_NAME) as db:
        db.executescript(V1_POSES)
        db.execute("INSERT INTO poses VALUES (?, ?, ?, ?, ?)", (FLEET, "r", 5, time.time(), encode(merged)))
    db.close()
    store = Store(tmp_path)
    assert [(r.message.revision, len(r.message.poses), r.message.anchor is not None) for r in store.load(FLEET)] == [
        (5, 2, True)
    ]
    assert not store.put_poses(update(4, [(0, 0.0)], anchor=0.0))  # every node and the anchor are at revision 5
    assert store.put_poses(update(4, [(7, 0.0)]))  # a node v1 never had
    assert store.put_poses(update(5, [(1, 1.5)]))  # a later part of revision 5
    store.close()
    store = Store(tmp_path)
    pieces = [(r.message.revision, [(n, p.t[0]) for n, p in r.message.poses]) for r in store.load(FLEET)]
    assert pieces == [(4, [(7, 0.0)]), (5, [(0, 1.0), (1, 1.5)])]
    assert store.pose_graph(FLEET, "r").anchor.t[0] == 0.5


def test_a_store_that_cannot_be_converted_is_left_as_it_was(tmp_path):
    good = PoseGraph()
    good.apply(update(1, [(0, 1.0)]))
    write_merged(tmp_path, {"a": good, "b": PoseGraph()}, as_sent={"b": b"\x00not a pose graph"})
    before = dump(tmp_path)
    with pytest.raises(ValueError, match="poses of default/b: .*message"):
        Store(tmp_path)
    assert dump(tmp_path) == before


def test_a_server_restarted_on_a_converted_store_judges_late_updates_as_the_one_that_wrote_it(tmp_path, model):
    for seed in range(25):
        rng = np.random.default_rng(seed)
        data = tmp_path / str(seed)
        data.mkdir()
        history = random_history(rng, nodes=6)
        live, reference, cut = PoseGraph(), ReferenceGraph(), int(rng.integers(1, len(history)))
        for message in history[:cut]:
            live.apply(message)
            reference.apply(message)
        write_merged(data, {"r": live})
        with sqlite3.connect(data / DB_NAME) as db:
            scan = ScanMessage(FLEET, "r", 0, 0.0, model, pose(-1.0))
            db.execute("INSERT INTO scans VALUES (?, ?, ?, ?, ?, ?, ?)", (FLEET, "r", 0, 0.0, 1, 0.0, encode(scan)))
        db.close()
        restarted = ServerState(FLEET, FleetMap(FLEET), Store(data))
        assert Ingest(restarted, lambda *_: None).replay() == 1
        assert state(restarted.fleet_map._nodes.robots["r"].graph) == state(live)
        for message in history[cut:]:
            changed = reference.apply(message)
            assert live.apply(message).changed == changed
            assert restarted.store.put_poses(message) == changed, f"seed {seed}"
            assert restarted.fleet_map.apply_poses(message) == changed
        assert state(restarted.fleet_map._nodes.robots["r"].graph) == state(live)
        restarted.store.close()
        reopened = Store(data)
        assert state(reopened._held_graph(FLEET, "r")) == state(live)
        reopened.close()
