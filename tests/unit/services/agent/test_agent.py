"""The agent's pose-graph updates: only nodes whose scan a correction moves by more than the
tolerance (from the pose the server holds) go out."""

from __future__ import annotations

import sqlite3

import numpy as np

from gmm_core import Pose
from protocol import PoseGraphUpdate, decode
from services.agent.sources import simulated_nodes


def sent_updates(path) -> list[PoseGraphUpdate]:
    with sqlite3.connect(path) as db:
        rows = db.execute("SELECT raw FROM outbox WHERE kind = 'poses' ORDER BY id").fetchall()
    return [decode(raw, expect=PoseGraphUpdate) for (raw,) in rows]


def test_updates_carry_only_the_nodes_whose_scan_moves_beyond_the_tolerance(offline_agent, tmp_path):
    """Tolerance 1 cm; every scan's farthest hit is 5 m from its sensor, so a turn counts 5 m per rad."""
    hits = np.array([[5.0, 0.0], [1.0, 2.0], [0.0, -3.0]])
    poses = {n: Pose.from_xytheta(n, 0.0, 0.0) for n in range(4)}
    for n, pose in poses.items():
        assert offline_agent.add_scan(hits, None, pose, float(n), node=n) == n
    assert offline_agent.correct(poses) is None  # the server holds the scans' own poses
    creep = poses | {1: Pose.from_xytheta(1.009, 0.0, 0.0), 2: Pose.from_xytheta(2.0, 0.0, 0.0019)}
    assert offline_agent.correct(creep) is None  # 9 mm; 1.9 mrad * 5 m = 9.5 mm
    moved = creep | {1: Pose.from_xytheta(1.011, 0.0, 0.0), 3: Pose.from_xytheta(3.0, 0.0, 0.0021)}
    moved[7] = Pose.from_xytheta(7.0, 0.0, 0.0)  # a node this agent did not send: its reach is unknown
    assert offline_agent.correct(moved) == 1  # 11 mm; 2.1 mrad * 5 m = 10.5 mm; node 7
    back = moved | {1: Pose.from_xytheta(1.005, 0.0, 0.0)}  # 6 mm from the correction the server holds
    assert offline_agent.correct(back) == 2  # node 7 again: unknown reach counts as moved
    assert offline_agent.correct(back, anchor=Pose.from_xytheta(5, 5, 0)) == 3  # an anchor always goes out
    updates = sent_updates(tmp_path / "o.db")
    assert [[n for n, _ in u.poses] for u in updates] == [[1, 3, 7], [7], [7]]
    assert updates[0].poses[0][1].t.tolist() == [1.011, 0.0] and updates[2].anchor is not None


def test_a_scan_sent_again_keeps_the_correction_held(offline_agent):
    """A lost scan fitted again goes out with its old estimate, but the server keeps the correction
    it holds (node by node, by revision): the agent compares against that correction."""
    hits = np.array([[2.0, 0.0]])
    offline_agent.add_scan(hits, None, Pose.from_xytheta(0.0, 0.0, 0.0), 0.0, node=0)
    assert offline_agent.correct({0: Pose.from_xytheta(0.5, 0.0, 0.0)}) == 1
    offline_agent._send_scan(0, hits, np.empty((0, 2)), Pose.from_xytheta(0.0, 0.0, 0.0), 0.0)
    assert offline_agent.correct({0: Pose.from_xytheta(0.505, 0.0, 0.0)}) is None


def test_prepared_nodes_publish_the_bytes_a_live_fit_would(offline_agent, tmp_path):
    """A simulated robot fits its run ahead (Agent.prepare): the same messages go out, and no beams are kept."""
    nodes = list(simulated_nodes("sim:office:0:2:0", "0:3", 5.0, 50))
    prepared = offline_agent.prepare(nodes)
    assert all(len(n.scan.hits) == len(n.scan.no_return) == 0 for n in prepared)
    assert [n.scan.stamp for n in prepared] == [n.scan.stamp for n in nodes]
    for live, ahead in zip(nodes, prepared):
        offline_agent._send_node(live)
        offline_agent._send_node(ahead)
    with sqlite3.connect(tmp_path / "o.db") as db:
        rows = [raw for (raw,) in db.execute("SELECT raw FROM outbox WHERE kind = 'scan' ORDER BY id")]
    assert len(rows) == 3  # a node sent twice is held once
    assert rows == [n.message for n in prepared]
