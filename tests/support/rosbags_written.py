"""ROS messages and bags made by rosbags' own typestores and writers: ROS 1 .bag, ROS 2 sqlite3 and mcap.

`RosMessages(kind)` builds message objects of that ROS version's types (ROS 1's Header has a
`seq`, the rest match); `write_bag` serialises them as that version does and writes the bag.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from gmm_core.pose import Pose

KINDS = ("ros1", "sqlite3", "mcap")
LASER_SCAN = "sensor_msgs/msg/LaserScan"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_COV = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF = "tf2_msgs/msg/TFMessage"
PATH = "nav_msgs/msg/Path"


def typestore(kind: str):
    if kind != "ros1":
        return get_typestore(Stores.LATEST)
    store = get_typestore(Stores.ROS1_NOETIC)  # Noetic's store lacks tf2_msgs: register it as ROS 1 defines it
    store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF))
    return store


def ns(stamp: float) -> int:
    return round(stamp * 1e9)


class RosMessages:
    """Message objects of one ROS version (kind: one of KINDS)."""

    def __init__(self, kind: str):
        self.kind = kind
        self.store = typestore(kind)
        self.t = self.store.types

    def header(self, stamp: float, frame: str):
        sec, nanosec = divmod(ns(stamp), 10**9)
        time = self.t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
        extra = {"seq": 0} if self.kind == "ros1" else {}
        return self.t["std_msgs/msg/Header"](stamp=time, frame_id=frame, **extra)

    def pose(self, pose: Pose):
        w, x, y, z = pose.as_quaternion()
        g = "geometry_msgs/msg/"
        return self.t[g + "Pose"](
            position=self.t[g + "Point"](*pose.t), orientation=self.t[g + "Quaternion"](x=x, y=y, z=z, w=w)
        )

    def transform(self, pose: Pose):
        w, x, y, z = pose.as_quaternion()
        g = "geometry_msgs/msg/"
        return self.t[g + "Transform"](
            translation=self.t[g + "Vector3"](*pose.t), rotation=self.t[g + "Quaternion"](x=x, y=y, z=z, w=w)
        )

    def laser_scan(self, stamp, frame, ranges, angle_min, angle_increment, range_min, range_max):
        ranges = np.asarray(ranges, dtype=np.float32)
        return self.t[LASER_SCAN](
            header=self.header(stamp, frame),
            angle_min=angle_min,
            angle_max=angle_min + angle_increment * (len(ranges) - 1),
            angle_increment=angle_increment,
            time_increment=0.0,
            scan_time=0.0,
            range_min=range_min,
            range_max=range_max,
            ranges=ranges,
            intensities=np.zeros(0, np.float32),
        )

    def odometry(self, stamp, frame, child, pose: Pose):
        g = "geometry_msgs/msg/"
        zero = self.t[g + "Vector3"](0.0, 0.0, 0.0)
        return self.t[ODOMETRY](
            header=self.header(stamp, frame),
            child_frame_id=child,
            pose=self.t[g + "PoseWithCovariance"](pose=self.pose(pose), covariance=np.zeros(36)),
            twist=self.t[g + "TwistWithCovariance"](twist=self.t[g + "Twist"](zero, zero), covariance=np.zeros(36)),
        )

    def pose_stamped(self, stamp, frame, pose: Pose):
        return self.t[POSE_STAMPED](header=self.header(stamp, frame), pose=self.pose(pose))

    def pose_with_covariance_stamped(self, stamp, frame, pose: Pose):
        cov = self.t["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(pose), covariance=np.eye(6).ravel())
        return self.t[POSE_COV](header=self.header(stamp, frame), pose=cov)

    def tf(self, transforms: list[tuple[float, str, str, Pose]]):
        """A TFMessage of (stamp, parent, child, pose of child in parent)."""
        stamped = self.t["geometry_msgs/msg/TransformStamped"]
        return self.t[TF](
            transforms=[
                stamped(header=self.header(s, parent), child_frame_id=child, transform=self.transform(p))
                for s, parent, child, p in transforms
            ]
        )

    def path(self, stamp: float, frame: str, poses: list[tuple[float, Pose]]):
        """A nav_msgs/Path of (stamp, pose) in `frame`, as a SLAM back end publishes its optimised poses."""
        return self.t[PATH](header=self.header(stamp, frame), poses=[self.pose_stamped(s, frame, p) for s, p in poses])

    def point_cloud(self, stamp, frame, data: bytes, fields, point_step, width, height=1, row_step=None, big=False):
        """fields: (name, offset, datatype) triples (sensor_msgs/PointField constants)."""
        field = self.t["sensor_msgs/msg/PointField"]
        return self.t[POINT_CLOUD2](
            header=self.header(stamp, frame),
            height=height,
            width=width,
            fields=[field(name=n, offset=o, datatype=d, count=1) for n, o, d in fields],
            is_bigendian=big,
            point_step=point_step,
            row_step=row_step if row_step is not None else point_step * width,
            data=np.frombuffer(data, dtype=np.uint8),
            is_dense=False,
        )


def write_bag(path: Path, kind: str, messages: list[tuple[str, str, float, object]]) -> Path:
    """Write (topic, type, log time in s, message) in that order; returns the bag (file or directory).

    path gets the suffix .bag for ROS 1; ROS 2 bags are directories at path.
    """
    store = typestore(kind)
    if kind == "ros1":
        path = path.with_suffix(".bag")
        writer, serialize = Writer1(path), store.serialize_ros1
    else:
        plugin = StoragePlugin.SQLITE3 if kind == "sqlite3" else StoragePlugin.MCAP
        writer, serialize = Writer2(path, version=9, storage_plugin=plugin), store.serialize_cdr
    connections = {}
    with writer:
        for topic, msgtype, log_time, msg in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connections[topic], ns(log_time), serialize(msg, msgtype))
    return path
