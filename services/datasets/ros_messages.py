"""ROS messages to numpy arrays and Poses: pure functions of deserialised message objects.

They read fields by their ROS names only, so they take rosbags' ROS 1 and ROS 2 messages alike
(and any CDR decoder's). A message that cannot be read raises DatasetError saying what is wrong;
the caller adds where the message came from (bag, topic, index).

- LaserScan (REP 117): `+inf` is a beam with no return; NaN, `-inf` and finite ranges outside
  [range_min, range_max] are dropped. Beam i points at angle_min + i * angle_increment.
- PointCloud2: x, y, z of any PointField datatype at any offsets and point_step, row padding
  (row_step), big-endian data; points with a non-finite coordinate are dropped.
- Frame names lose a leading "/" (ROS 1 bags often write "/base_link"; tf2 strips it too).
"""

from __future__ import annotations

import numpy as np

from gmm_core.pose import Pose

from .common import DatasetError, quaternion_pose

LASER_SCAN = "sensor_msgs/msg/LaserScan"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
SCAN_TYPES = (LASER_SCAN, POINT_CLOUD2)
POSE_TYPES = (ODOMETRY, POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED)
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")  # the second: ROS 1 bags before tf2

# sensor_msgs/PointField datatype constants -> numpy type codes (byte order added per message)
_POINT_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}

# A 2D map takes a LaserScan's beams to lie in the map plane; a sensor tilted by this much
# moves a beam end at 10 m by 35 cm in height but only 6 mm within the plane.
MAX_TILT_DEG = 2.0


def frame_name(frame_id: str) -> str:
    return frame_id.lstrip("/")


def stamp_seconds(header) -> float:
    """A std_msgs/Header's stamp in seconds."""
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def geometry_pose(pose, what: str) -> Pose:
    """A geometry_msgs/Pose (position, orientation) as a 3D Pose."""
    p, q = pose.position, pose.orientation
    return quaternion_pose(np.array([p.x, p.y, p.z]), np.array([q.w, q.x, q.y, q.z]), what)


def transform_pose(transform, what: str) -> Pose:
    """A geometry_msgs/Transform (translation, rotation) as a 3D Pose."""
    v, q = transform.translation, transform.rotation
    return quaternion_pose(np.array([v.x, v.y, v.z]), np.array([q.w, q.x, q.y, q.z]), what)


def tf_transforms(msg) -> list[tuple[float, str, str, Pose]]:
    """The (stamp, parent, child, pose of child in parent) of a tf2_msgs/TFMessage."""
    out = []
    for k, ts in enumerate(msg.transforms):
        parent, child = frame_name(ts.header.frame_id), frame_name(ts.child_frame_id)
        pose = transform_pose(ts.transform, f"transform {k} ({parent!r} -> {child!r})")
        out.append((stamp_seconds(ts.header), parent, child, pose))
    return out


def stamped_pose(msg, msgtype: str) -> tuple[float, str, str | None, Pose]:
    """(stamp, frame, child frame, pose) of an Odometry, PoseStamped or PoseWithCovarianceStamped.

    The child frame is Odometry's child_frame_id; the other two name none (None).
    """
    if msgtype == ODOMETRY:
        child, pose = frame_name(msg.child_frame_id), msg.pose.pose
    elif msgtype == POSE_STAMPED:
        child, pose = None, msg.pose
    elif msgtype == POSE_WITH_COVARIANCE_STAMPED:
        child, pose = None, msg.pose.pose
    else:
        raise DatasetError(f"a pose message must be one of {', '.join(POSE_TYPES)}, not {msgtype}")
    return stamp_seconds(msg.header), frame_name(msg.header.frame_id), child, geometry_pose(pose, "pose")


def laser_scan_beams(msg) -> tuple[np.ndarray, np.ndarray]:
    """(hits (n, 2), no-return directions (m, 2)) of a sensor_msgs/LaserScan, sensor frame."""
    ranges = np.asarray(msg.ranges, dtype=np.float64)
    limits = np.array([msg.angle_min, msg.angle_increment, msg.range_min, msg.range_max], dtype=np.float64)
    if not np.isfinite(limits).all():
        raise DatasetError(
            f"LaserScan: non-finite angle_min, angle_increment, range_min or range_max {limits.tolist()}"
        )
    angles = limits[0] + limits[1] * np.arange(len(ranges))
    directions = np.column_stack([np.cos(angles), np.sin(angles)])
    with np.errstate(invalid="ignore"):  # NaN compares False: dropped, as REP 117 asks
        hit = (ranges >= limits[2]) & (ranges <= limits[3])
    no_return = ranges == np.inf
    return directions[hit] * ranges[hit, None], directions[no_return]


def point_cloud_xyz(msg) -> np.ndarray:
    """The (n, 3) float64 x y z of a sensor_msgs/PointCloud2, non-finite points dropped."""
    fields = {f.name: f for f in msg.fields}
    missing = [a for a in "xyz" if a not in fields]
    if missing:
        raise DatasetError(f"PointCloud2: no {', '.join(missing)} field (has {sorted(fields)})")
    order = ">" if msg.is_bigendian else "<"
    formats = []
    for a in "xyz":
        code = _POINT_FIELD_TYPES.get(fields[a].datatype)
        if code is None:
            raise DatasetError(f"PointCloud2: field {a} has unknown datatype {fields[a].datatype}")
        formats.append(np.dtype(order + code))
        if fields[a].offset + formats[-1].itemsize > msg.point_step:
            raise DatasetError(
                f"PointCloud2: field {a} at offset {fields[a].offset} overruns point_step {msg.point_step}"
            )
    height, width, step, row_step = msg.height, msg.width, msg.point_step, msg.row_step
    if height * width == 0:
        return np.empty((0, 3))
    data = np.ascontiguousarray(msg.data, dtype=np.uint8)
    need = (height - 1) * row_step + width * step
    if row_step < width * step or len(data) < need:
        raise DatasetError(
            f"PointCloud2: {len(data)} data bytes, row_step {row_step}, for {height} x {width} points of {step} bytes"
        )
    offsets = [fields[a].offset for a in "xyz"]
    dtype = np.dtype({"names": list("xyz"), "formats": formats, "offsets": offsets, "itemsize": step})
    records = np.ndarray((height, width), dtype=dtype, buffer=data, strides=(row_step, step))
    points = np.column_stack([records[a].ravel().astype(np.float64) for a in "xyz"])
    return np.ascontiguousarray(points[np.isfinite(points).all(axis=1)])


def planar_pose(pose: Pose) -> Pose:
    """A 3D sensor pose projected to the map plane (x, y, yaw), for a 2D LaserScan.

    A sensor whose z axis is more than MAX_TILT_DEG off the vertical is a DatasetError: its
    beams do not lie in the plane.
    """
    tilt = np.degrees(np.arccos(np.clip(pose.R[2, 2], -1.0, 1.0)))
    if tilt > MAX_TILT_DEG:
        raise DatasetError(
            f"LaserScan sensor tilted {tilt:.1f} deg out of the map plane (a 2D scan allows {MAX_TILT_DEG} deg)"
        )
    return Pose.from_xytheta(pose.t[0], pose.t[1], np.arctan2(pose.R[1, 0], pose.R[0, 0]))
