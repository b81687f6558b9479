"""The live source's handling of samples, in order, by a real Agent (offline: its outbox fills) on a
real Zenoh session; the samples are rosbags' CDR on rmw_zenoh keys, or put on a bridge's keys."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import zenoh

from gmm_core import Pose
from protocol import PoseGraphUpdate, ScanMessage, decode
from services.agent.agent import Agent
from services.agent.config import AgentConfig
from services.config import GmmapConfig
from services.datasets.keyframes import KeyframeConfig
from services.datasets.ros_messages import planar_pose
from services.ros2.config import Ros2Config
from services.ros2.live import LiveSource
from services.zenoh_config import zenoh_config
from support.net import free_port
from support.ros2_robot import MOUNT, RosRobot, rmw_zenoh_key
from support.rosbags_written import LASER_SCAN, ODOMETRY, PATH, POINT_CLOUD2, TF, RosMessages

M = RosMessages("sqlite3")
RANGES = np.linspace(1.0, 3.0, 90)


class Live:
    """A LiveSource on an agent whose server is absent, fed sample by sample."""

    def __init__(self, tmp_path, **ros):
        agent_config = AgentConfig(
            robot="r", outbox=str(tmp_path / "outbox.db"), zenoh_connect=(f"tcp/127.0.0.1:{free_port()}",)
        )
        config = GmmapConfig(agent=agent_config, keyframe=KeyframeConfig.every_scan(), ros2=Ros2Config(**ros))
        self.agent = Agent.open(config)
        self.session = zenoh.open(zenoh_config("peer"))
        self.source = LiveSource(self.agent, config.ros2, "/scan", self.session, "r")

    def put(self, topic: str, msgtype: str, message, attachment: bytes | None = None, key: str | None = None):
        payload = bytes(M.store.serialize_cdr(message, msgtype))
        role = {"/scan": "scan", "/odom": "odom", "/tf": "tf", "/tf_static": "tf_static", "/slam/path": "path"}[topic]
        if key is None and self.source.ros.mapping == "bridge":
            key = topic.strip("/")
        self.source.handle(role, key or rmw_zenoh_key(topic, msgtype), payload, attachment)

    def receive(self, count: int):
        """Handle the next `count` samples the source's subscribers queued, as its thread does."""
        for _ in range(count):
            self.source.handle(*self.source._inbox.get(timeout=10))

    def scan(self, stamp: float):
        self.put("/scan", LASER_SCAN, M.laser_scan(stamp, "laser", RANGES, -1.0, 0.02, 0.0, 30.0))

    def odom(self, stamp: float, x: float):
        body = Pose.from_quaternion([x, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])
        self.put("/odom", ODOMETRY, M.odometry(stamp, "odom", "base_link", body))

    def static(self):
        self.put("/tf_static", TF, M.tf([(0.0, "base_link", "laser", MOUNT)]))

    def scans(self) -> dict[int, ScanMessage]:
        return {
            n: decode(raw, expect=ScanMessage) for kind, n, _, raw in self.agent.outbox.unsent(1000) if kind == "scan"
        }

    def updates(self) -> list[PoseGraphUpdate]:
        return [
            decode(raw, expect=PoseGraphUpdate) for kind, _, _, raw in self.agent.outbox.unsent(1000) if kind == "poses"
        ]

    def close(self):
        self.source.close()
        self.session.close()
        self.agent.close()


@pytest.fixture
def live(tmp_path):
    made = []

    def make(**ros):
        folder = tmp_path / str(len(made))
        folder.mkdir()
        made.append(Live(folder, **ros))
        return made[-1]

    yield make
    for one in made:
        one.close()


def expected_laser(x: float) -> tuple[float, float, float]:
    """The laser's planar pose with the body at (x, 0, 0): the mount composed on."""
    return planar_pose(Pose.from_quaternion([x, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]).compose(MOUNT)).as_xytheta()


def test_a_scan_waits_for_its_pose_then_goes_out_posed_by_odometry_and_mount(live):
    ros = live(odom_topic="/odom")
    ros.static()
    ros.odom(10.0, 1.0)
    ros.scan(10.5)  # after the newest odometry: held
    assert ros.scans() == {} and ros.source.counts["nodes"] == 0
    ros.odom(11.0, 2.0)  # brackets it: interpolated at 10.5
    [(node, message)] = ros.scans().items()
    assert node == 0 and message.stamp == pytest.approx(10.5)
    np.testing.assert_allclose(message.pose.as_xytheta(), expected_laser(1.5), atol=1e-5)
    assert ros.source.counts["dropped_unposed"] == 0 and ros.source.counts["bad"] == 0


def test_bad_samples_are_counted_and_change_nothing(live):
    ros = live(odom_topic="/odom")
    ros.static()
    ros.odom(10.0, 1.0)
    ros.source.handle("scan", rmw_zenoh_key("/scan", LASER_SCAN), b"\x00\x01\x00\x00garbage", None)
    ros.put("/scan", ODOMETRY, M.odometry(10.0, "odom", "base_link", MOUNT))  # the key names another type
    bad_attachment = struct.pack("<qqB16s", 1, 2, 3, bytes(16))
    ros.put("/scan", LASER_SCAN, M.laser_scan(10.0, "laser", RANGES, -1.0, 0.02, 0.0, 30.0), bad_attachment)
    assert ros.source.counts["bad"] == 3
    ros.odom(11.0, 2.0)
    assert ros.scans() == {} and ros.source.counts["nodes"] == 0


def test_scans_that_cannot_be_posed_are_dropped_and_counted(live):
    ros = live(odom_topic="/odom", hold_scans=2, hold_s=1.0)
    ros.static()
    ros.odom(10.0, 1.0)
    ros.scan(9.0)  # before the odometry: never posable
    assert ros.source.counts["dropped_unposed"] == 0  # the poses are not yet hold_s past it
    for stamp in (12.0, 13.0, 14.0):  # after the newest pose: held, two at most
        ros.scan(stamp)
    assert ros.source.counts["dropped_unposed"] == 2  # the 9.0 s one by the bound, then the 12 s one
    ros.odom(20.0, 3.0)
    assert sorted(m.stamp for m in ros.scans().values()) == [13.0, 14.0]


def test_poses_from_tf_and_a_point_cloud(live):
    ros = live()
    ros.static()
    odom_base = [(s, "odom", "base_link", Pose.from_quaternion([s, 0.0, 0.0], [1, 0, 0, 0])) for s in (1.0, 2.0)]
    ros.put("/tf", TF, M.tf(odom_base))
    points = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.5], [np.nan, 0.0, 0.0]], dtype=np.float32)
    xyz = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)]
    ros.put("/scan", POINT_CLOUD2, M.point_cloud(1.5, "laser", points.tobytes(), xyz, 12, 3))
    [message] = ros.scans().values()
    assert message.dim == 3
    expected = Pose.from_quaternion([1.5, 0.0, 0.0], [1, 0, 0, 0]).compose(MOUNT)
    np.testing.assert_allclose(message.pose.t, expected.t, atol=1e-5)


def test_a_path_corrects_the_nodes_it_has_and_only_what_moved(live):
    ros = live(odom_topic="/odom", path_topic="/slam/path")
    ros.static()
    for k in range(3):
        ros.odom(10.0 + k, float(k))
        ros.scan(10.0 + k)
    assert sorted(ros.scans()) == [0, 1, 2]
    body = Pose.from_quaternion([5.0, 1.0, 0.0], [1, 0, 0, 0])
    same = Pose.from_quaternion([1.0, 0.0, 0.0], [1, 0, 0, 0])  # node 1's body where odometry has it
    ros.put("/slam/path", PATH, M.path(12.0, "map", [(10.0, body), (11.0, same), (99.0, body)]))
    [update] = ros.updates()
    # node 1's body is where its scan has it (nothing to send); node 2's stamp is not on the path
    assert sorted(dict(update.poses)) == [0]
    expected = planar_pose(body.compose(MOUNT)).as_xytheta()
    np.testing.assert_allclose(dict(update.poses)[0].as_xytheta(), expected, atol=1e-9)
    ros.put("/slam/path", PATH, M.path(12.0, "map", [(10.0, body), (11.0, same)]))  # nothing moved since
    assert len(ros.updates()) == 1 and ros.source.counts["updates"] == 1


def test_bridge_keys_name_no_type_so_the_bytes_tell_laser_scan_from_point_cloud(live):
    cloud = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.5]], dtype=np.float32).tobytes()
    xyz = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)]
    samples = (
        (LASER_SCAN, M.laser_scan(2.0, "laser", RANGES, -1.0, 0.02, 0.0, 30.0), 2),
        (POINT_CLOUD2, M.point_cloud(2.0, "laser", cloud, xyz, 12, 2), 3),
    )
    for msgtype, message, dim in samples:  # a robot of each kind: an agent's nodes share one dimension
        ros = live(mapping="bridge")
        ros.static()
        ros.put("/tf", TF, M.tf([(s, "odom", "base_link", MOUNT) for s in (1.0, 3.0)]), key="tf")
        ros.put("/scan", msgtype, message, key="scan")
        assert [m.dim for m in ros.scans().values()] == [dim]
        ros.put("/scan", ODOMETRY, M.odometry(2.7, "odom", "base_link", MOUNT), key="scan")  # neither
        assert ros.source.counts["bad"] == 1


def test_a_bridge_with_a_namespace_puts_it_before_absolute_and_relative_names(live):
    """zenoh-bridge-ros2dds started with namespace bot1 routes a DDS robot's /scan, /odom and
    /tf_static as bot1/scan, bot1/odom and bot1/tf_static: the agent's /scan, /odom and (relative)
    tf_static with --ros-namespace bot1 are those keys."""
    ros = live(mapping="bridge", namespace="bot1", odom_topic="/odom")
    assert ros.source.describe() == "scan bot1/scan, tf_static bot1/tf_static, odom bot1/odom"
    robot = RosRobot(ros.session, "bridge", namespace="bot1")
    try:
        robot.publish("/tf_static", TF, M.tf([(0.0, "base_link", "laser", MOUNT)]))
        for stamp, x in ((10.0, 1.0), (11.0, 2.0)):
            body = Pose.from_quaternion([x, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])
            robot.publish("/odom", ODOMETRY, M.odometry(stamp, "odom", "base_link", body))
        robot.publish("/scan", LASER_SCAN, M.laser_scan(10.5, "laser", RANGES, -1.0, 0.02, 0.0, 30.0))
        ros.receive(4)
    finally:
        robot.close()
    [message] = ros.scans().values()
    np.testing.assert_allclose(message.pose.as_xytheta(), expected_laser(1.5), atol=1e-5)
    assert ros.source.counts["bad"] == 0


def test_a_long_run_keeps_its_poses_bounded_and_right(live):
    ros = live(odom_topic="/odom")
    ros.static()
    for k in range(3000):  # 300 s of odometry at 10 Hz
        ros.odom(0.1 * k, 0.01 * k)
    assert len(ros.source.poses._samples) <= 1000 + 10 * 2 * 60  # pruned to the last minute and a bit
    ros.scan(299.85)
    [message] = ros.scans().values()
    np.testing.assert_allclose(message.pose.as_xytheta(), expected_laser(29.985), atol=1e-5)
