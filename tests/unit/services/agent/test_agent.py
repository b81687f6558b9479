"""The agent's pose-graph updates: only the nodes that moved since the pose last sent go out."""

from __future__ import annotations

import sqlite3

import pytest

from gmm_core import Pose
from protocol import PoseGraphUpdate, decode
from services.agent.agent import Agent
from services.agent.config import AgentConfig
from services.agent.outbox import Outbox
from services.agent.sources import simulated_nodes
from services.zenoh_config import zenoh_config
from support.net import free_port


@pytest.fixture
def offline_agent(tmp_path):
    """An agent whose server is not there: what it sends stays in its outbox."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    options = AgentConfig(robot="r", zenoh_connect=(endpoint,), pose_tolerance=1e-3)
    agent = Agent(options, Outbox(tmp_path / "o.db", "default", "r"), zenoh_config("client", connect=[endpoint]))
    yield agent
    agent.close()
    agent.outbox.close()


def sent_updates(path) -> list[PoseGraphUpdate]:
    with sqlite3.connect(path) as db:
        rows = db.execute("SELECT raw FROM outbox WHERE kind = 'poses' ORDER BY id").fetchall()
    return [decode(raw, expect=PoseGraphUpdate) for (raw,) in rows]


def test_updates_carry_only_the_nodes_that_moved_beyond_the_tolerance(offline_agent, tmp_path):
    poses = {n: Pose.from_xytheta(n, 0.0, 0.0) for n in range(4)}
    assert offline_agent.correct(poses) == 1
    creep = dict(poses) | {1: Pose.from_xytheta(1.0009, 0.0, 0.0)}  # under 1 mm: not sent
    assert offline_agent.correct(creep) is None
    # 1 mm more is 1.9 mm from the pose last sent: sent; a turn of 2 mrad too
    moved = creep | {1: Pose.from_xytheta(1.0019, 0.0, 0.0), 3: Pose.from_xytheta(3.0, 0.0, 0.002)}
    assert offline_agent.correct(moved) == 2
    assert offline_agent.correct(moved, anchor=Pose.from_xytheta(5, 5, 0)) == 3  # an anchor always goes out
    updates = sent_updates(tmp_path / "o.db")
    assert [[n for n, _ in u.poses] for u in updates] == [[0, 1, 2, 3], [1, 3], []]
    assert updates[2].anchor is not None


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
