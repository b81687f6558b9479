"""The embeddable agent (Agent.open / add_scan / correct / flush) against a real map server, and
the runnable example under examples/ that uses it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gmm_core import Pose
from protocol import ScanMessage, decode
from services.agent.agent import Agent
from services.agent.config import AgentConfig
from services.config import GmmapConfig
from services.datasets import read_scans
from services.datasets.keyframes import KeyframeConfig, KeyframeFilter
from services.map_server.store import read_graph
from support.net import free_port
from support.processes import store_db, stored_nodes

ROOT = Path(__file__).resolve().parents[2]


def test_the_example_publishes_keyframes_and_their_corrections(procs, data_dir, tmp_path):
    zport, hport, data = free_port(), free_port(), tmp_path / "data"
    procs.server("server", data, zport, hport)
    log = data_dir / "carmen" / "intel-corrected.log.gz"
    example = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "embedded_agent.py"), "--log", str(log)]
        + ["--connect", f"tcp/127.0.0.1:{zport}", "--outbox", str(tmp_path / "outbox.db"), "--timeout", "60"],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert example.returncode == 0, example.stderr[-3000:]
    # what the default policy keeps, judged on the odometry poses the example publishes
    decide = KeyframeFilter(KeyframeConfig())
    scans = list(read_scans(log))
    kept = [s for s in scans if decide.keep(s.odom_pose, s.stamp)]
    assert 0 < len(kept) < len(scans)
    assert stored_nodes(data, "embedded") == set(range(len(kept)))  # numbered 0, 1, ... as added
    # This log's odometry is its corrected pose: the server holds every node at the back end's pose
    # from its scan on, so the correction moves no beam end by agent.pose_tolerance and sends nothing.
    with store_db(data) as db:
        assert read_graph(db, "default", "embedded") is None
        raws = [raw for (raw,) in db.execute("SELECT raw FROM scans WHERE robot = 'embedded' ORDER BY node")]
    for raw, scan in zip(raws, kept, strict=True):
        assert np.allclose(decode(raw, expect=ScanMessage).pose.t, scan.pose.t, atol=1e-5)  # float32 on the wire


def test_add_scan_rejects_bad_input_and_a_restart_numbers_on(procs, data_dir, tmp_path):
    zport, hport, data = free_port(), free_port(), tmp_path / "data"
    procs.server("server", data, zport, hport)
    config = GmmapConfig(
        agent=AgentConfig(robot="emb", zenoh_connect=(f"tcp/127.0.0.1:{zport}",), outbox=str(tmp_path / "o.db")),
        keyframe=KeyframeConfig(distance=0.5, angle=0.0, period=0.0),
    )
    scans = list(read_scans(data_dir / "carmen" / "intel-corrected.log.gz"))[:40]
    with Agent.open(config) as agent:
        bad = scans[0].hits.copy()
        bad[3, 1] = np.nan
        with pytest.raises(ValueError, match="points: 1 rows are not finite"):
            agent.add_scan(bad, scans[0].no_return, scans[0].pose, scans[0].stamp)
        with pytest.raises(ValueError, match=r"no_return: expected an \(n, 2\) array"):
            agent.add_scan(scans[0].hits, np.ones((4, 3)), scans[0].pose, scans[0].stamp)
        assert agent.outbox.pending() == 0  # nothing was sent
        first = [agent.add_scan(s.hits, s.no_return, s.pose, s.stamp) for s in scans[:20]]
        assert first[0] == 0 and first[1] is None  # the second scan is not 0.5 m from the first
        assert agent.flush(60) == 0
        with pytest.raises(ValueError, match="pose: 3D, the nodes sent before were 2D"):  # one dimension a robot
            agent.add_scan(np.ones((5, 3)), None, Pose.from_quaternion([9.0, 0, 0], [1, 0, 0, 0]), 99.0)
        assert agent.outbox.pending() == 0
    with Agent.open(config) as agent:  # the robot process restarts with its outbox
        again = [agent.add_scan(s.hits, s.no_return, s.pose, s.stamp) for s in scans[20:]]
        revision = agent.correct({0: Pose.from_xytheta(0.0, 0.0, 0.0)})
        assert agent.flush(60) == 0
    ids = [n for n in first + again if n is not None]
    assert ids == list(range(len(ids))) and again[0] == max(n for n in first if n is not None) + 1
    assert stored_nodes(data, "emb") == set(ids) and revision == 1


def test_a_robot_of_the_other_dimension_is_told_why(procs, tmp_path):
    """A 3D robot in a 2D fleet: the server refuses its scans with a Rejection naming the dimension,
    so the robot stops sending and says why rather than wait for Acks that never come."""
    zport, hport, data = free_port(), free_port(), tmp_path / "data"
    procs.server("server", data, zport, hport)
    rng = np.random.default_rng(0)

    def config(robot: str) -> GmmapConfig:
        connect = (f"tcp/127.0.0.1:{zport}",)
        agent = AgentConfig(robot=robot, zenoh_connect=connect, outbox=str(tmp_path / f"{robot}.db"))
        return GmmapConfig(agent=agent, keyframe=KeyframeConfig.every_scan())

    with Agent.open(config("flat")) as agent:  # the map's first scan makes it 2D
        assert agent.add_scan(rng.normal(size=(100, 2)) + [3.0, 0.0], None, Pose.identity(2), 0.0) == 0
        assert agent.flush(60) == 0
    wall = rng.normal(size=(400, 3)) + [5.0, 0.0, 0.0]
    with Agent.open(config("solid")) as agent:
        assert agent.add_scan(wall, None, Pose.identity(3), 0.0) == 0
        assert agent.flush(60) == 0  # refused: nothing left to resend
        refused = agent.refused
        assert (refused.reason, refused.kind, refused.ids) == ("dimension", "scan", (0,))
        assert refused.detail == "this map is 2D, the message is 3D"
        moved = Pose.from_quaternion([1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])
        assert agent.add_scan(wall, None, moved, 1.0) is None  # nothing more would be taken: not sent
        assert agent.outbox.rejected() == [("scan", 0, "dimension", refused.detail)]
    assert stored_nodes(data, "solid") == set() and stored_nodes(data, "flat") == {0}
