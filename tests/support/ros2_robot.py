"""A ROS 2 robot on Zenoh without ROS: rosbags serialises the messages (CDR with its encapsulation
header) and hashes their types (RIHS01), and the keys and rmw attachment are written here from
rmw_zenoh's design notes and zenoh-bridge-ros2dds's layout, not from services/ros2.

Also the Intel log as such a robot's topics: LaserScan (REP 117 +inf for no return), Odometry of
base_link (the log's odometry), a base-to-laser /tf_static, and a SLAM back end's nav_msgs/Path
of the corrected poses.
"""

from __future__ import annotations

import struct
import time
from dataclasses import dataclass

import numpy as np
import zenoh
import zenoh.ext
from rosbags.typesys import Stores, get_typestore

from gmm_core import Pose
from services.datasets.carmen import load_flaser, saturation_range
from support.net import wait_for
from support.rosbags_written import LASER_SCAN, ODOMETRY, PATH, TF, RosMessages

JAZZY = get_typestore(Stores.ROS2_JAZZY)
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
# the laser ahead of and left of the robot body, 30 cm up, turned 1.5 degrees
MOUNT = Pose.from_quaternion([0.12, 0.05, 0.3], [np.cos(np.radians(0.75)), 0, 0, np.sin(np.radians(0.75))])


def rmw_zenoh_key(topic: str, msgtype: str, domain: int = 0) -> str:
    package, _, name = msgtype.split("/")
    return f"{domain}/{topic.strip('/')}/{package}::msg::dds_::{name}_/{JAZZY.hash_rihs01(msgtype)}"


class RosRobot:
    """Publishers of one robot's topics on a Zenoh session, in `mapping` 'rmw_zenoh' or 'bridge'; a
    bridge started with a `namespace` puts it before every key, absolute names' too."""

    def __init__(self, session: zenoh.Session, mapping: str, namespace: str = ""):
        self.session, self.mapping, self.namespace = session, mapping, namespace
        self.store = RosMessages("sqlite3").store
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._sequence = 0
        self.gid = bytes(range(16))

    def key(self, topic: str, msgtype: str) -> str:
        if self.mapping == "rmw_zenoh":
            return rmw_zenoh_key(topic, msgtype)
        return "/".join(p for p in (self.namespace, topic.strip("/")) if p)

    def publisher(self, topic: str, msgtype: str, timeout: float = 30.0) -> zenoh.Publisher:
        """The topic's publisher, once a subscriber matches it."""
        if topic not in self._publishers:
            publisher = self.session.declare_publisher(
                self.key(topic, msgtype), congestion_control=zenoh.CongestionControl.BLOCK
            )
            wait_for(lambda: publisher.matching_status.matching, timeout, f"a subscriber of {topic}")
            self._publishers[topic] = publisher
        return self._publishers[topic]

    def latch(self, topic: str, msgtype: str, message) -> None:
        """Publish transient local as rmw_zenoh does: an advanced publisher whose cache keeps the
        last sample for subscribers that come later (the session needs timestamping)."""
        publisher = zenoh.ext.declare_advanced_publisher(
            self.session, self.key(topic, msgtype), cache=zenoh.ext.CacheConfig(1), publisher_detection=True
        )
        self._sequence += 1
        attachment = struct.pack("<qqB16s", self._sequence, time.time_ns(), 16, self.gid)
        publisher.put(bytes(self.store.serialize_cdr(message, msgtype)), attachment=attachment)
        self._publishers[topic] = publisher

    def publish(self, topic: str, msgtype: str, message) -> float:
        """Put one message; the time.time() of the put."""
        payload = bytes(self.store.serialize_cdr(message, msgtype))
        publisher = self.publisher(topic, msgtype)
        attachment = None
        if self.mapping == "rmw_zenoh":  # sequence number, source timestamp (ns), GID length, GID
            self._sequence += 1
            attachment = struct.pack("<qqB16s", self._sequence, time.time_ns(), 16, self.gid)
        sent = time.time()
        publisher.put(payload, attachment=attachment)
        return sent

    def close(self) -> None:
        for publisher in self._publishers.values():
            publisher.undeclare()


class MapSubscriber:
    """What a ROS 2 subscriber of `topic` receives: rosbags decodes each sample, the rmw attachment
    is checked; history from the publisher's cache for a late joiner (transient local)."""

    def __init__(self, session: zenoh.Session, mapping: str, topic: str, msgtype: str):
        key = f"0/{topic.strip('/')}/*/*" if mapping == "rmw_zenoh" else topic.strip("/")
        self.mapping, self.msgtype = mapping, msgtype
        self.received: list[tuple[float, object]] = []
        self.errors: list[Exception] = []
        self.subscriber = zenoh.ext.declare_advanced_subscriber(
            session, key, self._on_sample, history=zenoh.ext.HistoryConfig(detect_late_publishers=True)
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:  # an exception here would only be logged by Zenoh: kept for `settled` to raise
            if self.mapping == "rmw_zenoh":
                assert str(sample.key_expr) == rmw_zenoh_key(self.topic_of(sample), self.msgtype), sample.key_expr
                sequence, stamp, length, _ = struct.unpack("<qqB16s", sample.attachment.to_bytes())
                assert sequence > 0 and length == 16 and abs(stamp / 1e9 - time.time()) < 60, (sequence, stamp)
            self.received.append((time.time(), JAZZY.deserialize_cdr(sample.payload.to_bytes(), self.msgtype)))
        except Exception as error:  # noqa: BLE001
            self.errors.append(error)

    @staticmethod
    def topic_of(sample: zenoh.Sample) -> str:
        return "/" + "/".join(str(sample.key_expr).split("/")[1:-2])

    def settled(self, after: float, quiet: float = 1.5, timeout: float = 90.0):
        """The last message, once one arrived after time.time() `after` and none for `quiet` s."""

        def last():
            if self.errors:
                raise self.errors[0]
            if not self.received or self.received[-1][0] < after or time.time() - self.received[-1][0] < quiet:
                return None
            return self.received[-1][1]

        return wait_for(last, timeout, f"a settled {self.msgtype}")

    def first(self, after: float, accept, timeout: float = 90.0):
        """The first message received after time.time() `after` for which `accept(message)` holds.
        A publisher that sends on change may have sent the awaited state before the caller saw the
        change happen, so the caller passes the time of its own cause (e.g. its put), not of its look."""
        looked = 0

        def found():
            nonlocal looked
            if self.errors:
                raise self.errors[0]
            fresh, looked = self.received[looked:], len(self.received)
            return next((message for stamp, message in fresh if stamp >= after and accept(message)), None)

        return wait_for(found, timeout, f"a {self.msgtype} as expected")


@dataclass(frozen=True)
class IntelTopics:
    """The first `count` scans of the Intel log as a ROS 2 robot's messages."""

    static: tuple  # (topic, type, stamp, message) of /tf_static
    steps: list  # per scan: [(topic, type, stamp, message) of /odom, then of /scan]
    path: tuple  # (topic, type, stamp, message) of the corrected poses of every scan
    odometry: np.ndarray  # (count, 3) laser x y theta of odometry
    corrected: np.ndarray  # (count, 3) laser x y theta, SLAM-corrected
    stamps: np.ndarray


def laser_3d(x: float, y: float, theta: float) -> Pose:
    return Pose.from_quaternion([x, y, 0.3], [np.cos(theta / 2), 0, 0, np.sin(theta / 2)])


def intel_topics(data_dir, count: int) -> IntelTopics:
    """The first `count` scans of the corrected Intel log, each with its raw log's odometry and stamp
    (the same scan: stamps within 10 ms and identical ranges, as services.datasets.match_by_timestamp)."""
    raw = load_flaser(data_dir / "radish" / "intel.clf.bz2")
    fixed = load_flaser(data_dir / "carmen" / "intel-corrected.log.gz")
    saturation = saturation_range(np.concatenate(fixed.ranges))
    matched = []
    for k in range(count):
        near = np.flatnonzero(np.abs(raw.stamps - fixed.stamps[k]) <= 1e-2)
        matched.append(next(j for j in near if np.array_equal(raw.ranges[j], fixed.ranges[k])))
    stamps = raw.stamps[matched].astype(np.float64)
    m = RosMessages("sqlite3")
    static = ("/tf_static", TF, float(stamps[0]) - 1, m.tf([(float(stamps[0]) - 1, "base_link", "laser", MOUNT)]))
    steps = []
    for k, j in enumerate(matched):
        stamp, ranges = float(stamps[k]), np.where(raw.ranges[j] >= saturation, np.inf, raw.ranges[j])
        body = laser_3d(*raw.poses[j]).compose(MOUNT.inverse())
        steps.append(
            [
                ("/odom", ODOMETRY, stamp, m.odometry(stamp, "odom", "base_link", body)),
                ("/scan", LASER_SCAN, stamp, m.laser_scan(stamp, "laser", ranges, -np.pi / 2, np.pi / 180, 0, 80)),
            ]
        )
    bodies = [(float(s), laser_3d(*p).compose(MOUNT.inverse())) for s, p in zip(stamps, fixed.poses[:count])]
    path = ("/slam/path", PATH, float(stamps[-1]), m.path(float(stamps[-1]), "map", bodies))
    return IntelTopics(static, steps, path, raw.poses[matched], np.array(fixed.poses[:count]), stamps)
