"""`gmmap agent` on robot data (point-cloud sequences, bags) against a real map server."""

from __future__ import annotations

import numpy as np
from pypcd4 import PointCloud

from protocol import ScanMessage, decode
from services.datasets import read_scans
from services.datasets.keyframes import KeyframeConfig, KeyframeFilter
from support.balm import BALM, balm_points
from support.net import free_port
from support.processes import store_db, stored_nodes


def test_agent_sends_a_pcd_sequence_with_its_poses(procs, tmp_path):
    seq = tmp_path / "balm"
    seq.mkdir()
    for number, points in balm_points(step=20).items():  # written by pypcd4, not by us
        PointCloud.from_xyz_points(points.astype(np.float32)).save(seq / f"{number:06d}.pcd")
    zport, hport, data = free_port(), free_port(), tmp_path / "data"
    procs.server("server", data, zport, hport)
    agent = procs.start(
        "agent",
        "agent",
        "--robot",
        "lidar",
        "--zenoh-connect",
        f"tcp/127.0.0.1:{zport}",
        "--source",
        f"pcd:{seq}",
        "--poses",
        str(BALM / "poses.txt"),
        "--outbox",
        str(tmp_path / "outbox.db"),
        "--timeout",
        "60",
    )
    assert procs.finish(agent, 240) == 0, procs.log(agent)
    decide = KeyframeFilter(KeyframeConfig())  # the agent's default policy
    scans = {s.index: s for s in read_scans(seq, "pcd", poses=BALM / "poses.txt") if decide.keep(s.pose, s.stamp)}
    assert stored_nodes(data, "lidar") == set(scans) == {0, 24}  # node id = file number; the handheld start is slow
    with store_db(data) as db:
        for node, raw in db.execute("SELECT node, raw FROM scans WHERE robot = 'lidar'"):
            message = decode(raw, expect=ScanMessage)
            assert message.dim == 3 and message.model.occupied.n_components > 10
            np.testing.assert_allclose(message.pose.t, scans[node].pose.t, atol=1e-6)
