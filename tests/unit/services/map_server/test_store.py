"""The durable pieces without a network: the server's SQLite store and ingest path, the agent's outbox."""

from __future__ import annotations

import sqlite3
import time

import numpy as np
import pytest

from gmm_core import Pose, fit_scan
from protocol import PoseGraphUpdate, ScanMessage, decode, encode, poses_key, scan_key
from services.map_server.fleet_map import FleetMap
from services.map_server.ingest import Ingest
from services.map_server.nodes import ScanEntry
from services.map_server.state import ServerState
from services.map_server.store import Store
from support.ingest import ingested, scan_of


@pytest.fixture(scope="module")
def model():
    rng = np.random.default_rng(1)
    return fit_scan(rng.normal(size=(40, 2)) * 0.2 + [2.0, 0.0], np.zeros((0, 2)))


def scan(model, robot="r", node=0, x=0.0):
    return ScanMessage("default", robot, node, float(node), model, Pose.from_xytheta(x, 0.0, 0.0))


def poses(robot, revision, items, anchor=None):
    return PoseGraphUpdate("default", robot, revision, tuple((n, Pose.from_xytheta(x, 0, 0)) for n, x in items), anchor)


def test_store_keeps_each_scan_once_and_survives_reopening(tmp_path, model):
    store = Store(tmp_path)
    first = scan(model, node=3)
    assert store.put_scan(first, encode(first)) is True
    assert store.put_scan(first, b"resent bytes are not stored") is False
    assert store.put_scans([(scan(model, node=1), encode(scan(model, node=1))), (first, encode(first))]) == [
        True,
        False,
    ]
    store.close()
    store = Store(tmp_path)
    assert store.scan_count("default") == 2 and store.nodes("default", "r") == {1, 3}
    assert store.scan_bytes("default", "r", 3) == encode(first)
    assert [r.message.node for r in store.load("default")] == [1, 3]
    assert list(store.load("other")) == []


def entry_values(entry):
    return (
        entry.robot,
        entry.node,
        entry.components,
        entry.size,
        entry.raw,
        entry.pose.t.tolist(),
        entry.pose.R.tolist(),
        *(a.tolist() for a in (entry.origin, entry.local_lo, entry.local_hi)),
    )


def test_a_scan_is_loaded_as_the_node_store_holds_it_without_decoding_or_from_an_older_row(tmp_path, model):
    """Store.load rebuilds each scan's ScanEntry from the row's entry columns (no decode), bit for bit
    what ScanEntry.of makes of the decoded message; rows of a store written before those columns
    existed (NULL) are decoded, and a store whose table lacks them gains them when opened."""
    messages = [decode(encode(scan(model, "r", n, x=0.1 * n))) for n in range(5)]  # as ingest holds them
    store = Store(tmp_path)
    store.put_scans([(m, encode(m)) for m in messages])
    expected = [entry_values(ScanEntry.of(m, len(encode(m)), encode(m))) for m in messages]
    assert [entry_values(r.message) for r in store.load("default")] == expected
    store._db.execute("UPDATE scans SET entry = NULL, components = NULL WHERE node % 2 = 0")
    assert [entry_values(r.message) for r in store.load("default")] == expected
    store.close()
    db = sqlite3.connect(tmp_path / "gmmap.db")  # the schema before: no entry columns
    db.execute("ALTER TABLE scans DROP COLUMN entry")
    db.execute("ALTER TABLE scans DROP COLUMN components")
    db.commit()
    db.close()
    store = Store(tmp_path)
    assert [entry_values(r.message) for r in store.load("default")] == expected
    extra = decode(encode(scan(model, "r", 9)))
    assert store.put_scan(extra, encode(extra))
    assert entry_values(list(store.load("default"))[-1].message) == entry_values(
        ScanEntry.of(extra, len(encode(extra)), encode(extra))
    )


def test_load_reads_scans_chunk_by_chunk_after_the_pose_graphs(tmp_path, model, monkeypatch):
    monkeypatch.setattr("services.map_server.store.SCAN_CHUNK", 2)  # 7 scans: chunks of 2, 2, 2, 1
    store = Store(tmp_path)
    keys = [("b", 0), ("a", 5), ("a", 1), ("b", 3), ("a", 2), ("c", 0), ("b", 1)]
    assert all(store.put_scans([(scan(model, r, n), encode(scan(model, r, n))) for r, n in keys]))
    assert store.put_poses(poses("b", 1, [(3, 1.0)]))
    loaded = [(r.message.robot, getattr(r.message, "node", None), r.size) for r in store.load("default")]
    size = len(encode(scan(model)))
    assert loaded == [("b", None, 0)] + [(r, n, size) for r, n in sorted(keys)]


def test_store_merges_pose_graphs_node_by_node(tmp_path):
    store = Store(tmp_path)
    anchor = Pose.from_xytheta(10, 0, 0)
    update = poses("r", 2, [(0, 1.0), (1, 1.0)], anchor)
    assert store.put_poses(update)
    assert store.put_poses(poses("r", 1, [(0, 5.0)])) is False  # node 0 was set by revision 2
    older = poses("r", 1, [(0, 5.0), (4, 5.0)], Pose.identity(2))  # node 4: no newer revision listed it
    assert store.put_poses(older)
    newer = poses("r", 3, [(1, 2.0), (2, 2.0)])  # lists only the nodes it moves, no anchor
    assert store.put_poses(newer)
    held = store.pose_graph("default", "r")
    assert held.revision == 3
    assert {n: p.t[0] for n, p in held.poses} == {0: 1.0, 1: 2.0, 2: 2.0, 4: 5.0}
    assert held.anchor is not None and held.anchor.t[0] == 10
    by_revision = [(r.message.revision, [n for n, _ in r.message.poses]) for r in store.load("default")]
    assert by_revision == [(1, [4]), (2, [0]), (3, [1, 2])]
    assert store.inventory("default", "r").revision == 3


def run_ingest(state, *phases):
    """Submit each phase's (key, payload) items, waiting for the previous phase's first answer (an Ack
    or a Rejection listing ids: one that only lists scans still queued answers nothing)."""
    acks = []

    def answered(key: str, payload: bytes) -> None:
        answer = decode(payload)
        if answer.ids:
            acks.append((key, answer))

    ingest = Ingest(state, answered)
    ingest.replay()
    ingest.start()
    for items in phases:
        seen = len(acks)
        for key, payload in items:
            ingest.submit(key, payload)
        deadline = time.monotonic() + 10
        while len(acks) == seen and time.monotonic() < deadline:
            time.sleep(0.01)
    ingest.stop()
    return acks


def test_ingest_acks_after_commit_and_rejects_what_does_not_belong(tmp_path, model):
    state = ServerState("default", FleetMap("default"), Store(tmp_path))
    good = scan(model, node=0)
    three_d = ScanMessage(
        "default",
        "r",
        9,
        0.0,
        fit_scan(np.random.default_rng(0).normal(size=(30, 3)) + 3, np.zeros((0, 3))),
        Pose.identity(3),
    )
    acks = run_ingest(
        state,
        [
            (scan_key("default", "r", 0), encode(good)),
            (scan_key("default", "r", 0), encode(good)),  # a resend in the same batch: stored once, acked once
            (scan_key("default", "x", 0), encode(good)),  # key names another robot
            (scan_key("default", "r", 5), encode(good)),  # key names another node
            (poses_key("default", "r"), encode(good)),  # a scan on the pose key
            (scan_key("default", "r", 1), b"\x00garbage"),
            ("gmmap/other/r/scan/1", encode(good)),  # another fleet
        ],
        # A 3D scan into the 2D map: refused, and told (a phase of its own: the Rejection comes before
        # the commit, and a phase ends at its first answer).
        [(scan_key("default", "r", 9), encode(three_d))],
    )
    assert [(k, type(a).__name__, a.kind, a.ids) for k, a in acks] == [
        ("gmmap/default/r/ack", "Ack", "scan", (0,)),  # the resend: acked once
        ("gmmap/default/r/ack", "Rejection", "scan", (9,)),
    ]
    assert state.store.nodes("default", "r") == {0}
    text = state.metrics.render().decode()
    for reason in ("key.robot", "key.node", "dimension", "type", "message", "key"):
        assert f'reason="{reason}"' in text, reason
    assert state.metrics.rejected_total() == 6


def test_a_correction_that_arrives_before_its_scan_is_applied_to_it(tmp_path, model):
    state = ServerState("default", FleetMap("default"), Store(tmp_path))
    update = poses("r", 1, [(0, 4.0), (1, 6.0)])
    acks = run_ingest(
        state,
        [
            (scan_key("default", "r", 0), encode(scan(model, node=0, x=0.0))),
            (poses_key("default", "r"), encode(update)),
        ],
        [(scan_key("default", "r", 1), encode(scan(model, node=1, x=0.0)))],
    )  # after its pose
    assert [(a.kind, a.ids) for _, a in acks] == [("scan", (0,)), ("poses", (1,)), ("scan", (1,))]
    assert state.fleet_map.trajectory("r")[:, 0].tolist() == [4.0, 6.0]
    # A restart replays the same map.
    restarted = ServerState("default", FleetMap("default"), Store(tmp_path))
    assert Ingest(restarted, lambda *_: None).replay() == 2
    assert restarted.fleet_map.trajectory("r")[:, 0].tolist() == [4.0, 6.0]


def test_a_restart_gives_each_robot_the_time_it_was_last_seen_before(tmp_path):
    """The time its newest scan or pose-graph revision was stored, not the time of the replay."""
    state = ServerState("default", FleetMap("default"), Store(tmp_path))
    started = time.time()
    ingested(state, [scan_of(2, 0, robot="a"), scan_of(2, 0, robot="b")])
    time.sleep(0.01)
    corrected = time.time()
    ingested(state, [poses("b", 1, [(0, 1.0)])])
    live = {row["robot"]: row["last_seen"] for row in state.fleet_map.robots()}
    time.sleep(0.01)
    replayed = time.time()
    restarted = ServerState("default", FleetMap("default"), Store(tmp_path))
    Ingest(restarted, lambda *_: None).replay()
    seen = {row["robot"]: row["last_seen"] for row in restarted.fleet_map.robots()}
    assert started <= seen["a"] <= live["a"] < corrected <= seen["b"] <= live["b"] < replayed
