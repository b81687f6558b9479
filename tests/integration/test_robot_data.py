"""`gmmap agent` on robot data (point-cloud sequences, bags) against a real map server."""

from __future__ import annotations

import numpy as np
from pypcd4 import PointCloud

from gmm_core import Pose
from protocol import ScanMessage, decode
from services.datasets import read_scans
from services.datasets.carmen import load_flaser, saturation_range
from services.datasets.keyframes import KeyframeConfig, KeyframeFilter
from support.balm import BALM, balm_points
from support.net import free_port
from support.processes import store_db, stored_nodes
from support.rosbags_written import LASER_SCAN, ODOMETRY, TF, RosMessages, write_bag


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


def test_agent_sends_a_ros2_bag_posed_by_odometry_and_tf_static(procs, data_dir, tmp_path):
    """The Intel log as a robot records it (LaserScan on /scan, base_link odometry on /odom, the laser
    mounted ahead and to the left on /tf_static), in a ROS 2 bag written by rosbags."""
    log = load_flaser(data_dir / "carmen" / "intel-corrected.log.gz")
    saturation = saturation_range(np.concatenate(log.ranges))
    mount = Pose.from_quaternion([0.12, 0.05, 0.3], [np.cos(np.radians(1.5)), 0, 0, np.sin(np.radians(1.5))])
    m = RosMessages("sqlite3")
    t0 = float(log.stamps[0])
    messages = [("/tf_static", TF, t0 - 1, m.tf([(t0 - 1, "base_link", "laser", mount)]))]
    for k in range(40):
        x, y, theta = log.poses[k]
        laser = Pose.from_quaternion([x, y, 0.3], [np.cos(theta / 2), 0, 0, np.sin(theta / 2)])
        stamp, ranges = float(log.stamps[k]), np.where(log.ranges[k] >= saturation, np.inf, log.ranges[k])
        messages.append(
            ("/scan", LASER_SCAN, stamp, m.laser_scan(stamp, "laser", ranges, -np.pi / 2, np.pi / 180, 0, 80))
        )
        messages.append(
            ("/odom", ODOMETRY, stamp, m.odometry(stamp, "odom", "base_link", laser.compose(mount.inverse())))
        )
    bag = write_bag(tmp_path / "run", "sqlite3", sorted(messages, key=lambda msg: msg[2]))

    zport, hport, data = free_port(), free_port(), tmp_path / "data"
    procs.server("server", data, zport, hport)
    agent = procs.start(
        "agent",
        "agent",
        "--robot",
        "ros",
        "--zenoh-connect",
        f"tcp/127.0.0.1:{zport}",
        "--source",
        f"rosbag:{bag}",
        "--scan-topic",
        "/scan",
        "--pose-topic",
        "/odom",
        "--outbox",
        str(tmp_path / "outbox.db"),
        "--timeout",
        "60",
    )
    assert procs.finish(agent, 120) == 0, procs.log(agent)
    carmen = list(read_scans(data_dir / "carmen" / "intel-corrected.log.gz"))[:40]
    decide = KeyframeFilter(KeyframeConfig())
    expect = {s.index: s for s in carmen if decide.keep(s.pose, s.stamp)}
    assert stored_nodes(data, "ros") == set(expect)
    with store_db(data) as db:
        for node, raw in db.execute("SELECT node, raw FROM scans WHERE robot = 'ros'"):
            message = decode(raw, expect=ScanMessage)
            # the laser's pose, through odometry and the static mount, as the CARMEN log has it (float32 on the wire)
            np.testing.assert_allclose(message.pose.as_xytheta(), expect[node].pose.as_xytheta(), atol=1e-4)
