"""ROS message conversions on messages that rosbags serialised and deserialised (ROS 1 and ROS 2)."""

from __future__ import annotations

import numpy as np
import pytest

from gmm_core.pose import Pose
from services.datasets import DatasetError
from services.datasets.pcd import read_pcd_points
from services.datasets.ros_messages import (
    ODOMETRY,
    POSE_STAMPED,
    frame_name,
    laser_scan_beams,
    planar_pose,
    point_cloud_xyz,
    stamped_pose,
    tf_transforms,
)
from support.rosbags_written import LASER_SCAN, POINT_CLOUD2, POSE_COV, TF, RosMessages

FLOAT32, FLOAT64, INT16, UINT8 = 7, 8, 3, 2


def roundtrip(m: RosMessages, msg, msgtype: str):
    """The message as a reader sees it: serialised the way its ROS version does, then deserialised."""
    if m.kind == "ros1":
        return m.store.deserialize_ros1(m.store.serialize_ros1(msg, msgtype), msgtype)
    return m.store.deserialize_cdr(m.store.serialize_cdr(msg, msgtype), msgtype)


@pytest.fixture(params=["ros1", "sqlite3"], ids=["ros1", "ros2"])
def m(request) -> RosMessages:
    return RosMessages(request.param)


@pytest.fixture(scope="module")
def balm_points(data_dir) -> np.ndarray:
    """A real OS0 scan, every 40th point (about 2,000), with a few NaN points like a driver's."""
    pts = read_pcd_points(data_dir / "3d" / "balm-os0" / "000012.pcd.gz")[::40].copy()
    pts[::97] = np.nan
    return pts


def test_laser_scan_follows_rep_117(m):
    ranges = [1.0, np.inf, np.nan, -np.inf, 0.05, 90.0, 30.0, 0.1, 2.5]
    msg = roundtrip(m, m.laser_scan(7.25, "/laser", ranges, -1.0, 0.25, 0.1, 30.0), LASER_SCAN)
    hits, no_return = laser_scan_beams(msg)
    angles = np.float32(-1.0) + np.float32(0.25) * np.array([0, 6, 7, 8])  # the beams in [range_min, range_max]
    np.testing.assert_allclose(hits, np.array([1.0, 30, 0.1, 2.5])[:, None] * np.c_[np.cos(angles), np.sin(angles)])
    np.testing.assert_allclose(no_return, [[np.cos(-0.75), np.sin(-0.75)]])
    assert frame_name(msg.header.frame_id) == "laser"


# PointCloud2 layouts: fields (name, offset, numpy type, PointField datatype), point_step
LAYOUTS = {
    "f32 xyz pad intensity": (
        [
            ("x", 0, "<f4", FLOAT32),
            ("y", 4, "<f4", FLOAT32),
            ("z", 8, "<f4", FLOAT32),
            ("intensity", 16, "<f4", FLOAT32),
        ],
        32,
    ),  # PCL's PointXYZI, padded to 32 bytes
    "f64 after a ring byte": (
        [("ring", 0, "u1", UINT8), ("x", 3, "<f8", FLOAT64), ("y", 11, "<f8", FLOAT64), ("z", 19, "<f8", FLOAT64)],
        40,
    ),
    "i16 zyx": ([("z", 0, "<i2", INT16), ("y", 2, "<i2", INT16), ("x", 4, "<i2", INT16)], 6),
    "f32 big-endian": ([("x", 0, ">f4", FLOAT32), ("y", 4, ">f4", FLOAT32), ("z", 8, ">f4", FLOAT32)], 16),
}


def pack(points: np.ndarray, fields, step: int) -> bytes:
    dtype = np.dtype(
        {
            "names": [f[0] for f in fields],
            "formats": [f[2] for f in fields],
            "offsets": [f[1] for f in fields],
            "itemsize": step,
        }
    )
    rec = np.zeros(len(points), dtype)
    for k, a in enumerate("xyz"):
        rec[a] = points[:, k]
    return rec.tobytes()


@pytest.mark.parametrize("layout", LAYOUTS)
def test_point_cloud_layouts(m, balm_points, layout):
    fields, step = LAYOUTS[layout]
    points = balm_points
    if layout.startswith("i16"):  # integers (centimetres here) come back as they are: PointCloud2 has no scale
        points = np.round(points[np.isfinite(points).all(axis=1)] * 100).clip(-32768, 32767)
    point_fields = [(name, offset, datatype) for name, offset, _, datatype in fields]
    msg = m.point_cloud(3.0, "os", pack(points, fields, step), point_fields, step, len(points), big="big" in layout)
    got = point_cloud_xyz(roundtrip(m, msg, POINT_CLOUD2))
    want = points.astype(np.float32 if layout.startswith("f32") else np.float64).astype(np.float64)
    np.testing.assert_array_equal(got, want[np.isfinite(want).all(axis=1)])  # exact: the field types widen losslessly
    assert len(got) > 1500


def test_organised_point_cloud_with_row_padding(m, balm_points):
    width = len(balm_points) // 4
    rows = np.zeros((4, width * 16 + 8), np.uint8)  # 4 rows of `width` points, each row padded by 8 bytes
    xyz = balm_points[: 4 * width].astype("<f4").reshape(4, width, 3)
    rows[:, : width * 16].view("<f4").reshape(4, width, 4)[..., :3] = xyz
    f32 = [("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32)]
    msg = m.point_cloud(3.0, "os", rows.tobytes(), f32, 16, width, height=4, row_step=width * 16 + 8)
    want = xyz.reshape(-1, 3).astype(np.float64)
    np.testing.assert_array_equal(point_cloud_xyz(roundtrip(m, msg, POINT_CLOUD2)), want[np.isfinite(want).all(axis=1)])


def test_point_cloud_errors(m):
    xyz = np.zeros((3, 3), "<f4").tobytes()
    f32 = [("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32)]
    cases = [
        (m.point_cloud(0, "os", xyz, f32[:2], 12, 3), "no z field"),
        (m.point_cloud(0, "os", xyz, [*f32[:2], ("z", 8, 9)], 12, 3), "field z has unknown datatype 9"),
        (m.point_cloud(0, "os", xyz, [*f32[:2], ("z", 10, FLOAT32)], 12, 3), "offset 10 overruns point_step 12"),
        (m.point_cloud(0, "os", xyz[:-1], f32, 12, 3), "35 data bytes"),
        (m.point_cloud(0, "os", xyz, f32, 12, 3, row_step=30), "row_step 30"),
    ]
    for msg, error in cases:
        with pytest.raises(DatasetError, match=error):
            point_cloud_xyz(roundtrip(m, msg, POINT_CLOUD2))


def test_pose_messages_and_tf(m):
    p = Pose.from_quaternion([1.0, -2.0, 0.5], [np.cos(0.4), 0.0, 0.0, np.sin(0.4)])
    odom = roundtrip(m, m.odometry(4.5, "/odom", "base_link", p), ODOMETRY)
    stamp, frame, child, got = stamped_pose(odom, ODOMETRY)
    assert (stamp, frame, child) == (4.5, "odom", "base_link")
    np.testing.assert_allclose(got.R, p.R, atol=1e-15)
    np.testing.assert_allclose(got.t, p.t)
    for msg, msgtype in [
        (m.pose_stamped(1.0, "map", p), POSE_STAMPED),
        (m.pose_with_covariance_stamped(1.0, "map", p), POSE_COV),
    ]:
        assert stamped_pose(roundtrip(m, msg, msgtype), msgtype)[1:3] == ("map", None)
    tf = roundtrip(m, m.tf([(2.0, "odom", "base_link", p), (2.5, "base_link", "/laser", Pose.identity(3))]), TF)
    [(s0, a0, b0, p0), (s1, a1, b1, _)] = tf_transforms(tf)
    assert (s0, a0, b0, s1, a1, b1) == (2.0, "odom", "base_link", 2.5, "base_link", "laser")
    np.testing.assert_allclose(p0.t, p.t)
    zero = m.pose_stamped(1.0, "map", p)
    zero.pose.orientation.w = 0.0
    zero.pose.orientation.z = 0.0
    with pytest.raises(DatasetError, match="pose: quaternion norm 0.000"):
        stamped_pose(zero, POSE_STAMPED)


def test_planar_pose_allows_a_small_tilt_only():
    yaw, small = 0.7, np.radians(1.5)
    level = Pose.from_quaternion([1, 2, 0.3], [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)])
    tilted = level.compose(Pose.from_quaternion([0, 0, 0], [np.cos(small / 2), np.sin(small / 2), 0, 0]))
    np.testing.assert_allclose(planar_pose(level).as_xytheta(), [1, 2, yaw])
    np.testing.assert_allclose(planar_pose(tilted).as_xytheta(), [1, 2, yaw])  # a roll leaves the x axis alone
    steep = level.compose(Pose.from_quaternion([0, 0, 0], [np.cos(0.05), 0, np.sin(0.05), 0]))
    with pytest.raises(DatasetError, match="tilted 5.7 deg out of the map plane"):
        planar_pose(steep)
