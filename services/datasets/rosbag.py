"""ROS bags: ROS 1 `.bag`, ROS 2 `.db3` / `.mcap` files or ROS 2 bag directories (metadata.yaml).

Read with the `rosbags` library (pure Python, no ROS install; `pip install 'gmmap[ros]'`).

Scans: the messages of `scan_topic`, which may be omitted when the bag has exactly one
sensor_msgs/LaserScan or PointCloud2 topic. A LaserScan gives a 2D scan (see ros_messages for
REP 117), a PointCloud2 a 3D one. `index` is the message's position on the scan topic (0-based,
in bag order), `stamp` its header stamp in seconds; `odom_pose` is None.

Poses: the pose of the scan's header frame_id at the scan's header stamp.
- With `pose_topic` (nav_msgs/Odometry, geometry_msgs/PoseStamped or PoseWithCovarianceStamped):
  the topic gives the pose of a frame F in its header frame_id, interpolated at the stamp
  (translation linearly, rotation by slerp), composed with the transform from F to the scan
  frame on /tf_static or /tf. For Odometry F is its child_frame_id. PoseStamped and
  PoseWithCovarianceStamped name no frame; as localisers (AMCL, SLAM toolboxes) publish the
  robot's pose, F is `base_link` (REP 105's robot body) when /tf or /tf_static has that frame,
  and the scan frame itself otherwise (a pose topic of the sensor).
- Without it: the scan frame's pose in the root of its /tf tree (e.g. map or odom), through
  every transform on the way (timed ones on /tf interpolated at the stamp).
A 2D scan's 3D sensor pose is projected to the plane (ros_messages.planar_pose).

Scans whose stamp lies outside the time span of the poses (or of a timed transform they need)
are skipped with a warning saying how many; if none can be posed, a DatasetError.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from gmm_core.pose import Pose

from .common import DatasetError, RangeScan, split_points
from .ros_messages import (
    LASER_SCAN,
    POSE_TYPES,
    SCAN_TYPES,
    TF_TYPES,
    frame_name,
    laser_scan_beams,
    planar_pose,
    point_cloud_xyz,
    stamp_seconds,
    stamped_pose,
    tf_transforms,
)
from .tf import Extrapolation, TimedPoses, TransformBuffer

ROSBAG_SUFFIXES = {".bag", ".db3", ".mcap"}
# What rosbags raises on a corrupt or truncated file varies with the byte hit: its own errors,
# sqlite's and apsw's, struct.error, KeyError, UnicodeDecodeError, AssertionError... so every
# Exception from opening, reading or deserialising is the file's fault, named as such.
_CORRUPT = Exception
TF_TOPICS = ("/tf", "/tf_static")
BODY_FRAME = "base_link"


def is_rosbag(path: Path) -> bool:
    """A ROS 1 or ROS 2 bag file, or a ROS 2 bag directory."""
    return path.suffix in ROSBAG_SUFFIXES if path.is_file() else (path / "metadata.yaml").is_file()


@contextmanager
def _open_bag(path: Path):
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ModuleNotFoundError:
        raise DatasetError(f"{path.name}: reading ROS bags needs rosbags: pip install 'gmmap[ros]'") from None
    if not path.exists():
        raise FileNotFoundError(f"rosbag: no such file or directory: {path}")
    # the typestore serves ROS 2 bags that embed no message definitions (those before Iron)
    try:
        bag = AnyReader([path], default_typestore=get_typestore(Stores.LATEST))
        bag.open()
    except _CORRUPT as e:
        raise DatasetError(f"{path.name}: cannot read as a ROS bag: {type(e).__name__}: {e}") from None
    try:
        yield bag
    finally:
        bag.close()


@contextmanager
def _located(where: str):
    """Prefix `where` (bag, topic, message) to the errors of reading one message."""
    try:
        yield
    except Extrapolation:
        raise
    except ValueError as e:  # DatasetError, and Pose's own checks on message values
        raise DatasetError(f"{where}: {e}") from None


def _messages(bag, path: Path, topics: list[str]) -> Iterator[tuple[str, str, str, object]]:
    """(where, topic, type, message) of the topics' messages in bag order, deserialised."""
    connections = [c for c in bag.connections if c.topic in topics]
    if not connections:  # rosbags reads every topic when given none
        return
    counts = dict.fromkeys(topics, 0)
    stream = bag.messages(connections=connections)
    while True:
        try:
            item = next(stream, None)
        except _CORRUPT as e:
            raise DatasetError(f"{path.name}: cannot read the bag: {type(e).__name__}: {e}") from None
        if item is None:
            return
        connection, _, raw = item
        where = f"{path.name}: {connection.topic} message {counts[connection.topic]}"
        counts[connection.topic] += 1
        try:
            msg = bag.deserialize(raw, connection.msgtype)
        except _CORRUPT as e:
            raise DatasetError(f"{where}: cannot deserialise {connection.msgtype}: {type(e).__name__}: {e}") from None
        yield where, connection.topic, connection.msgtype, msg


def _listing(topics: dict) -> str:
    return ", ".join(f"{name} ({info.msgtype}, {info.msgcount} messages)" for name, info in sorted(topics.items()))


def _topic(path: Path, topics: dict, name: str | None, types: tuple[str, ...], flag: str) -> str:
    """The topic `name` after checking its type; None picks the only topic of those types."""
    if name is None:
        candidates = {t: info for t, info in topics.items() if info.msgtype in types}
        if len(candidates) == 1:
            return next(iter(candidates))
        kinds = "/".join(t.rsplit("/", 1)[-1] for t in types)
        which = f"{len(candidates)} {kinds} topics" if candidates else f"no {kinds} topic"
        raise DatasetError(f"{path.name}: {which}; name one with {flag}: {_listing(candidates or topics)}")
    if name not in topics:
        raise DatasetError(f"{path.name}: no topic {name!r}; the bag has {_listing(topics)}")
    if topics[name].msgtype not in types:
        raise DatasetError(
            f"{path.name}: topic {name} holds {topics[name].msgtype}, expected one of {', '.join(types)}"
        )
    return name


@dataclass(frozen=True)
class _Poses:
    """Where scans get their poses: the transform tree, and the pose topic's samples if one is named."""

    tf: TransformBuffer
    topic: TimedPoses | None
    body: str | None  # the frame the pose topic's poses are of; None: the scan's own frame

    def sensor_pose(self, frame: str, stamp: float) -> Pose:
        """The 3D pose of `frame` at `stamp`; Extrapolation outside the poses' time span."""
        if self.topic is None:
            if frame not in self.tf.frames:
                known = sorted(self.tf.frames)
                raise DatasetError(f"scan frame {frame!r} is on neither /tf nor /tf_static (frames there: {known})")
            return self.tf.lookup(self.tf.root(frame), frame, stamp)
        body = self.body or frame
        return self.topic.at(stamp).compose(self.tf.lookup(body, frame, stamp))


def _load_poses(bag, path: Path, pose_topic: str | None) -> _Poses:
    """Pass one over the bag: /tf, /tf_static and the pose topic."""
    topics = bag.topics
    tf_topics = [t for t in TF_TOPICS if t in topics]
    for t in tf_topics:
        _topic(path, topics, t, TF_TYPES, "")
    if pose_topic is not None:
        _topic(path, topics, pose_topic, POSE_TYPES, "--pose-topic")
    elif not tf_topics:
        pose_topics = {t: info for t, info in topics.items() if info.msgtype in POSE_TYPES}
        raise DatasetError(
            f"{path.name}: no /tf to pose the scans; name a pose topic with --pose-topic"
            f" ({_listing(pose_topics) if pose_topics else 'the bag has none'})"
        )
    tf, samples, frames = TransformBuffer(), [], set()
    for where, topic, msgtype, msg in _messages(bag, path, tf_topics + ([pose_topic] if pose_topic else [])):
        with _located(where):
            if topic == pose_topic:
                stamp, frame, child, pose = stamped_pose(msg, msgtype)
                samples.append((stamp, pose))
                frames.add((frame, child))
            else:
                for stamp, parent, child, pose in tf_transforms(msg):
                    if topic == "/tf_static":
                        tf.add_static(parent, child, pose)
                    else:
                        tf.add(parent, child, stamp, pose)
    if pose_topic is None:
        return _Poses(tf, None, None)
    if not samples:
        raise DatasetError(f"{path.name}: pose topic {pose_topic} has no messages")
    if len(frames) > 1:
        raise DatasetError(
            f"{path.name}: pose topic {pose_topic} mixes frames (frame, child): {sorted(frames, key=str)}"
        )
    [(_, child)] = frames
    body = child if child is not None else (BODY_FRAME if BODY_FRAME in tf.frames else None)
    return _Poses(tf, TimedPoses.from_samples(samples, pose_topic), body)


def count_rosbag(path: str | Path, *, scan_topic: str | None = None, pose_topic: str | None = None) -> int:
    """Messages on the scan topic, from the bag's index (none deserialised)."""
    path = Path(path)
    with _open_bag(path) as bag:
        topics = bag.topics
        return topics[_topic(path, topics, scan_topic, SCAN_TYPES, "--scan-topic")].msgcount


def read_rosbag(
    path: str | Path, *, scan_topic: str | None = None, pose_topic: str | None = None
) -> Iterator[RangeScan]:
    """The posed scans of a bag, in bag order (see the module docstring)."""
    path = Path(path)
    with _open_bag(path) as bag:
        scan_topic = _topic(path, bag.topics, scan_topic, SCAN_TYPES, "--scan-topic")
        poses = _load_poses(bag, path, pose_topic)
        total, skipped, last_miss = 0, 0, None
        for where, _, msgtype, msg in _messages(bag, path, [scan_topic]):
            index, total = total, total + 1
            with _located(where):
                stamp, frame = stamp_seconds(msg.header), frame_name(msg.header.frame_id)
                try:
                    pose = poses.sensor_pose(frame, stamp)
                except Extrapolation as e:
                    skipped, last_miss = skipped + 1, e
                    continue
                if msgtype == LASER_SCAN:
                    hits, no_return = laser_scan_beams(msg)
                    pose = planar_pose(pose)
                else:
                    hits, no_return = split_points(point_cloud_xyz(msg), 0.0, None)
            yield RangeScan(index=index, stamp=stamp, pose=pose, odom_pose=None, hits=hits, no_return=no_return)
        source = pose_topic or "/tf"
        if total and skipped == total:
            raise DatasetError(
                f"{path.name}: none of the {total} scans on {scan_topic} can be posed from {source}: {last_miss}"
            )
        if skipped:
            warnings.warn(
                f"{path.name}: skipped {skipped} of {total} scans on {scan_topic}, outside the time span of"
                f" {source} (e.g. {last_miss})",
                stacklevel=2,
            )
