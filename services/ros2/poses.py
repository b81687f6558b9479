"""Live poses of a ROS 2 robot: /tf and /tf_static, or an odometry topic composed with the static
transform from its child frame to the scan's frame; the same composition as the rosbag reader
(services/datasets/rosbag.py), fed message by message and kept bounded."""

from __future__ import annotations

import math

from gmm_core.pose import Pose
from services.datasets.common import DatasetError
from services.datasets.ros_messages import stamped_pose, tf_transforms
from services.datasets.rosbag import BODY_FRAME
from services.datasets.tf import TimedPoses, TransformBuffer

KEEP_S = 60.0  # s of timed poses kept behind the newest (a held scan waits at most ros2.hold_s)


class LivePoses:
    def __init__(self, odometry: bool):
        self.tf = TransformBuffer()
        self.odometry = odometry
        self._samples: list[tuple[float, Pose]] = []
        self._timed: TimedPoses | None = None
        self._body: str | None = None  # the odometry's child frame
        self.newest = -math.inf  # the newest stamp of a timed pose (odometry or /tf)

    def add_tf(self, msg, static: bool) -> None:
        for stamp, parent, child, pose in tf_transforms(msg):
            if static:
                self.tf.add_static(parent, child, pose)
            else:
                self.tf.add(parent, child, stamp, pose)
                self._advance(stamp)

    def add_odometry(self, msg, msgtype: str) -> None:
        stamp, _, child, pose = stamped_pose(msg, msgtype)
        if child is not None:
            if self._body is not None and child != self._body:
                raise DatasetError(f"odometry of frame {child!r}, earlier of {self._body!r}")
            self._body = child
        self._samples.append((stamp, pose))
        self._timed = None
        self._advance(stamp)

    def _advance(self, stamp: float) -> None:
        if stamp > self.newest:
            self.newest = stamp
            if len(self._samples) > 1000 and self._samples[0][0] < stamp - 2 * KEEP_S:
                self._samples = [s for s in self._samples if s[0] >= stamp - KEEP_S]
                self._timed = None
                self.tf.forget_before(stamp - KEEP_S)

    def body(self, frame: str) -> str:
        """The frame whose poses the odometry (or a SLAM path) gives: the odometry's child frame,
        else base_link (REP 105) when the transforms know it, else the scan frame itself."""
        if self._body is not None:
            return self._body
        return BODY_FRAME if BODY_FRAME in self.tf.frames else frame

    def mount(self, frame: str, stamp: float) -> Pose:
        """The pose of the scan `frame` in the body frame at `stamp` (identity when they are one)."""
        body = self.body(frame)
        return Pose.identity(3) if body == frame else self.tf.lookup(body, frame, stamp)

    def sensor_pose(self, frame: str, stamp: float) -> Pose:
        """The 3D pose of `frame` at `stamp`; a DatasetError (Extrapolation) while it is not known (yet)."""
        if self.odometry:
            if not self._samples:
                raise DatasetError("no odometry yet")
            if self._timed is None:
                self._timed = TimedPoses.from_samples(self._samples, "odometry")
            return self._timed.at(stamp).compose(self.mount(frame, stamp))
        if frame not in self.tf.frames:
            raise DatasetError(f"scan frame {frame!r} is on neither /tf nor /tf_static yet")
        return self.tf.lookup(self.tf.root(frame), frame, stamp)
