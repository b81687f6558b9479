"""The rosbag reader on bags that rosbags' own writers made: the real Intel log as LaserScans
(poses from /odom and from /tf), real BALM scans as PointCloud2 (PoseStamped poses), bad bags."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from gmm_core.pose import Pose
from services.datasets import DatasetError, count_scans, guess_format, read_scans
from services.datasets.carmen import load_flaser, saturation_range
from services.replay import replay
from support.paths import ROOT
from support.rosbags_written import (
    KINDS,
    LASER_SCAN,
    ODOMETRY,
    POINT_CLOUD2,
    POSE_COV,
    POSE_STAMPED,
    TF,
    RosMessages,
    write_bag,
)

INTEL = "carmen/intel-corrected.log.gz"
LASER_HEIGHT = 0.3
# base_link -> laser as a robot's URDF would put it: ahead, to the left, up, turned 3 degrees
OFFSET = Pose.from_quaternion([0.12, 0.05, LASER_HEIGHT], [np.cos(np.radians(1.5)), 0, 0, np.sin(np.radians(1.5))])


def yaw_pose(x: float, y: float, z: float, yaw: float) -> Pose:
    return Pose.from_quaternion([x, y, z], [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)])


def monotonic(times: np.ndarray, step: float = 1e-3) -> np.ndarray:
    """Record times after the given ones and strictly increasing (the Intel stamps go back 4 times)."""
    out = np.array(times, dtype=np.float64)
    for k in range(1, len(out)):
        out[k] = max(out[k], out[k - 1] + step)
    return out


def tf_samples(stamps: np.ndarray, base: list[Pose]) -> tuple[np.ndarray, list[Pose]]:
    """The base trajectory half way between consecutive scans (in time order): what /tf holds."""
    order = np.argsort(stamps)
    t, rot = stamps[order], Rotation.from_matrix([base[k].R for k in order])
    trans = np.array([base[k].t for k in order])
    mid = (t[:-1] + t[1:]) / 2
    R = [Slerp(t[k : k + 2], rot[k : k + 2])(mid[k]).as_matrix() for k in range(len(mid))]
    return mid, [Pose(r, (trans[k] + trans[k + 1]) / 2) for k, r in enumerate(R)]


@pytest.fixture(scope="module")
def intel(data_dir):
    """The Intel log's scans, and per scan its ranges (+inf at saturation), stamp and base pose."""
    path = data_dir / INTEL
    log = load_flaser(path)
    saturation = saturation_range(np.concatenate(log.ranges))
    ranges = [np.where(r >= saturation, np.inf, r) for r in log.ranges]
    base = [yaw_pose(x, y, LASER_HEIGHT, th).compose(OFFSET.inverse()) for x, y, th in log.poses]
    return list(read_scans(path, "carmen")), ranges, log.stamps, base, saturation


@pytest.fixture(scope="module", params=KINDS)
def intel_bag(request, intel, tmp_path_factory):
    """/scan, /odom at the scan stamps, /tf odom -> base_link half way between them, /tf_static."""
    _, ranges, stamps, base, saturation = intel
    m = RosMessages(request.param)
    record = monotonic(stamps + 0.01)
    msgs = [("/tf_static", TF, stamps.min() - 1, m.tf([(stamps.min() - 1, "base_link", "laser", OFFSET)]))]
    for k, (r, s, b) in enumerate(zip(ranges, stamps, base)):
        msgs.append(
            ("/scan", LASER_SCAN, record[k], m.laser_scan(s, "laser", r, -np.pi / 2, np.pi / 180, 0.0, saturation))
        )
        msgs.append(("/odom", ODOMETRY, record[k] + 1e-4, m.odometry(s, "odom", "base_link", b)))
    for s, b in zip(*tf_samples(stamps, base)):
        msgs.append(("/tf", TF, s + 0.01, m.tf([(s, "odom", "base_link", b)])))
    msgs.sort(key=lambda msg: msg[2])
    return write_bag(tmp_path_factory.mktemp("intel") / "intel", request.param, msgs)


def test_intel_bag_with_odom_reads_as_the_log(intel, intel_bag):
    log_scans = intel[0]
    assert guess_format(intel_bag) == "rosbag"
    assert count_scans(intel_bag, "rosbag") == 910  # the only LaserScan topic: --scan-topic not needed
    bag_scans = list(read_scans(intel_bag, pose_topic="/odom"))
    assert len(bag_scans) == len(log_scans) == 910
    for b, c in zip(bag_scans, log_scans):
        assert b.index == c.index and b.stamp == pytest.approx(c.stamp, abs=1e-9)
        np.testing.assert_allclose(b.pose.R, c.pose.R, atol=1e-9)
        np.testing.assert_allclose(b.pose.t, c.pose.t, atol=1e-9)
        # LaserScan carries float32 ranges and angles: 6e-8 relative on ranges up to 82 m, 1e-7 rad on angles
        np.testing.assert_allclose(b.hits, c.hits, atol=2e-5)
        np.testing.assert_allclose(b.no_return, c.no_return, atol=1e-6)
        assert b.odom_pose is None


@pytest.mark.parametrize("intel_bag", ["sqlite3", "mcap"], indirect=True)
def test_ros2_storage_file_alone(intel_bag):
    [storage] = [f for f in intel_bag.iterdir() if f.suffix in (".db3", ".mcap")]
    assert guess_format(storage) == "rosbag"
    assert count_scans(storage, "rosbag", scan_topic="/scan") == 910


@pytest.mark.parametrize("intel_bag", ["ros1"], indirect=True)  # one map suffices: all kinds read the same scans
def test_intel_map_from_bag_equals_map_from_log(intel, intel_bag):
    log_scans = intel[0][:80]
    bag_scans = list(read_scans(intel_bag, "rosbag", scan_topic="/scan", pose_topic="/odom"))[:80]
    bbox = [-20.0, -20.0, 20.0, 20.0]
    # counted beams: the same map (measured: identical, float32 ranges notwithstanding)
    raw_log = replay(log_scans, resolution=0.1, bbox=bbox, method="raw")
    np.testing.assert_allclose(replay(bag_scans, resolution=0.1, bbox=bbox, method="raw").prob, raw_log.prob)
    # The GMM map is not a smooth function of its input: hits rounded to float32 alone move up to
    # 0.22 of a cell's probability (EM and the Monte Carlo samples take other paths), so compare
    # its classes. Measured: the bag flips 170 of the ~33,800 cells seen (0.5%), mean |dp| 7e-4;
    # shifting every pose by 2 cm flips 918 (2.7%), mean 2.9e-3.
    mc_log = replay(log_scans, resolution=0.1, bbox=bbox).prob
    mc_bag = replay(bag_scans, resolution=0.1, bbox=bbox).prob
    classes_log, classes_bag = np.digitize(mc_log, [0.3, 0.7]), np.digitize(mc_bag, [0.3, 0.7])
    seen = np.count_nonzero(classes_log != 1)
    assert (classes_log == 2).sum() > 500  # a real map: walls
    assert np.count_nonzero(classes_log != classes_bag) < 0.01 * seen
    assert np.abs(mc_bag - mc_log).mean() < 1.5e-3


def test_intel_bag_with_tf_interpolates(intel, intel_bag):
    log_scans, _, stamps, base, _ = intel
    with pytest.warns(UserWarning, match="skipped 2 of 910 scans on /scan"):
        bag_scans = list(read_scans(intel_bag, "rosbag"))
    # the first and last scans in time come before the first /tf sample and after the last one
    order = np.argsort(stamps)
    assert [s.index for s in bag_scans] == [k for k in range(910) if k not in (order[0], order[-1])]
    mid, samples = tf_samples(stamps, base)
    slerp = Slerp(mid, Rotation.from_matrix([p.R for p in samples]))
    trans = np.array([p.t for p in samples])
    errors = []
    for scan in bag_scans:
        # the reference: scipy's slerp and numpy's interp between the /tf samples, then base -> laser.
        # Both sides compute the same interpolation, from stamps that differ by float rounding only
        # (1e-12 s at these magnitudes, a picometre at the robot's speed): 1e-9 leaves room for it.
        t = [np.interp(scan.stamp, mid, trans[:, i]) for i in range(3)]
        want = Pose(slerp(scan.stamp).as_matrix(), t).compose(OFFSET)
        np.testing.assert_allclose(
            scan.pose.as_xytheta(), [*want.t[:2], np.arctan2(want.R[1, 0], want.R[0, 0])], atol=1e-9
        )
        errors.append(np.linalg.norm(scan.pose.t - log_scans[scan.index].pose.t))
    # and near the truth: the samples lie on the corrected path, but half a scan period (~1.7 s)
    # off, so the chord between two of them cuts the corner the path makes at the scan
    assert np.median(errors) < 0.06  # measured: median 3.9 cm, 36 cm at most (in turns)


@pytest.fixture(scope="module")
def balm(data_dir):
    """Three real BALM scans (every 20th point, some NaN as a driver writes them), poses, stamps."""
    seq = data_dir / "3d" / "balm-os0"
    scans = [next(s for s in read_scans(seq, "pcd", poses=seq / "poses.txt") if s.index == k) for k in (0, 12, 24)]
    times = np.loadtxt(seq / "times.txt")
    points = [s.hits[::20].copy() for s in scans]
    for p in points:
        p[::50] = np.nan
    return points, [s.pose for s in scans], [times[s.index] for s in scans]


def cloud(m: RosMessages, stamp: float, points: np.ndarray):
    """PCL's PointXYZI layout: x y z float32, 4 padding bytes, intensity, padded to 32 bytes."""
    rec = np.zeros(
        len(points),
        np.dtype({"names": ["x", "y", "z", "i"], "formats": ["<f4"] * 4, "offsets": [0, 4, 8, 16], "itemsize": 32}),
    )
    for k, a in enumerate("xyz"):
        rec[a] = points[:, k]
    fields = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7)]
    return m.point_cloud(stamp, "os_sensor", rec.tobytes(), fields, 32, len(points))


@pytest.mark.parametrize("kind", ["ros1", "mcap"])
def test_point_clouds_posed_by_pose_stamped(balm, tmp_path, kind):
    points, poses, stamps = balm
    m = RosMessages(kind)
    # bag 1: PoseStamped of the sensor itself (no base_link on /tf)
    msgs = [("/pose", POSE_STAMPED, s, m.pose_stamped(s, "map", p)) for p, s in zip(poses, stamps)]
    msgs += [("/os_cloud", POINT_CLOUD2, s + 0.05, cloud(m, s, pts)) for pts, s in zip(points, stamps)]
    bag1 = write_bag(tmp_path / "sensor", kind, sorted(msgs, key=lambda x: x[2]))
    # bag 2: poses of base_link (PoseStamped and PoseWithCovarianceStamped), base_link -> os_sensor on /tf_static
    base = [p.compose(OFFSET.inverse()) for p in poses]
    msgs = [("/tf_static", TF, stamps[0] - 1, m.tf([(stamps[0] - 1, "base_link", "os_sensor", OFFSET)]))]
    msgs += [("/pose", POSE_STAMPED, s, m.pose_stamped(s, "map", b)) for b, s in zip(base, stamps)]
    msgs += [("/amcl_pose", POSE_COV, s, m.pose_with_covariance_stamped(s, "map", b)) for b, s in zip(base, stamps)]
    msgs += [("/os_cloud", POINT_CLOUD2, s + 0.05, cloud(m, s, pts)) for pts, s in zip(points, stamps)]
    bag2 = write_bag(tmp_path / "base", kind, sorted(msgs, key=lambda x: x[2]))
    for bag, topic in [(bag1, "/pose"), (bag2, "/pose"), (bag2, "/amcl_pose")]:
        scans = list(read_scans(bag, "rosbag", pose_topic=topic))
        assert [s.index for s in scans] == [0, 1, 2]
        for scan, pts, pose, stamp in zip(scans, points, poses, stamps):
            assert scan.stamp == pytest.approx(stamp, abs=1e-6)  # 1.6e9 s: float64 holds 0.2 us
            want = pts[np.isfinite(pts).all(axis=1)].astype(np.float32).astype(np.float64)
            np.testing.assert_array_equal(scan.hits, want)
            assert scan.no_return.shape == (0, 3)
            np.testing.assert_allclose(scan.pose.R, pose.R, atol=1e-9)
            np.testing.assert_allclose(scan.pose.t, pose.t, atol=1e-9)


def small_bag(path, kind="ros1", n=4, scan_frame="laser", tf_child="laser", extra=(), edit=None):
    """n scans on /scan, /odom at their stamps, base_link -> tf_child on /tf_static."""
    m = RosMessages(kind)
    msgs = [("/tf_static", TF, 0.5, m.tf([(0.5, "base_link", tf_child, OFFSET)]))]
    for k in range(n):
        msgs.append(("/odom", ODOMETRY, 1.0 + k, m.odometry(1.0 + k, "odom", "base_link", yaw_pose(k, 0, 0, 0.1 * k))))
        scan = m.laser_scan(1.0 + k, scan_frame, [1.0, 2.0, np.inf], -0.5, 0.5, 0.1, 30.0)
        if edit is not None:
            edit(k, scan)
        msgs.append(("/scan", LASER_SCAN, 1.0 + k + 0.01, scan))
    msgs += [(topic, msgtype, t, build(m)) for topic, msgtype, t, build in extra]
    return write_bag(path, kind, sorted(msgs, key=lambda x: x[2]))


def test_topic_errors_name_what_the_bag_has(tmp_path):
    bag = small_bag(tmp_path / "b")
    with pytest.raises(DatasetError, match=r"b.bag: no topic '/laser'; the bag has /odom \(nav_msgs/msg/Odometry, 4"):
        list(read_scans(bag, "rosbag", scan_topic="/laser"))
    with pytest.raises(DatasetError, match="topic /odom holds nav_msgs/msg/Odometry, expected one of sensor_msgs"):
        count_scans(bag, "rosbag", scan_topic="/odom")
    with pytest.raises(DatasetError, match="topic /scan holds sensor_msgs/msg/LaserScan, expected one of nav_msgs"):
        list(read_scans(bag, "rosbag", pose_topic="/scan"))
    second = ("/scan2", LASER_SCAN, 3.0, lambda m: m.laser_scan(3.0, "laser", [1.0], 0.0, 0.1, 0.1, 30.0))
    bag = small_bag(tmp_path / "two", extra=[second])
    with pytest.raises(
        DatasetError,
        match=r"2 LaserScan/PointCloud2 topics; name one with --scan-topic: "
        r"/scan \(sensor_msgs/msg/LaserScan, 4 messages\), /scan2 \(sensor_msgs/msg/LaserScan, 1 messages\)",
    ):
        list(read_scans(bag, "rosbag"))
    assert count_scans(bag, "rosbag", scan_topic="/scan2") == 1


def test_pose_errors(tmp_path):
    bag = small_bag(tmp_path / "lidar", tf_child="lidar")  # /tf_static names the sensor frame differently
    with pytest.raises(DatasetError, match="no transform between frames 'base_link' and 'laser'"):
        list(read_scans(bag, "rosbag", pose_topic="/odom"))
    with pytest.raises(DatasetError, match="scan frame 'laser' is on neither /tf nor /tf_static"):
        list(read_scans(bag, "rosbag"))
    m = RosMessages("ros1")
    bare = write_bag(
        tmp_path / "bare", "ros1", [("/scan", LASER_SCAN, 1.0, m.laser_scan(1.0, "l", [1.0], 0, 0.1, 0.1, 9))]
    )
    with pytest.raises(DatasetError, match="no /tf to pose the scans; name a pose topic with --pose-topic"):
        list(read_scans(bare, "rosbag"))
    late = small_bag(tmp_path / "late", edit=lambda k, scan: setattr(scan.header.stamp, "sec", 100 + k))
    span = r"/odom: no pose at 103.0+ s, outside its samples. \[1.0+, 4.0+\] s"
    with pytest.raises(DatasetError, match="none of the 4 scans on /scan can be posed from /odom: " + span):
        list(read_scans(late, "rosbag", pose_topic="/odom"))


def test_tilted_laser_and_malformed_message_are_located(tmp_path):
    tilted = (
        "/tf_static",
        TF,
        0.6,
        lambda m: m.tf([(0.6, "laser", "tilted", Pose.from_quaternion([0, 0, 0], [np.cos(0.1), np.sin(0.1), 0, 0]))]),
    )
    bag = small_bag(
        tmp_path / "t",
        "sqlite3",
        edit=lambda k, s: setattr(s.header, "frame_id", "tilted" if k == 2 else "laser"),
        extra=[tilted],
    )
    with pytest.raises(
        DatasetError, match=r"t: /scan message 2: LaserScan sensor tilted 11.5 deg out of the map plane"
    ):
        list(read_scans(bag, "rosbag", pose_topic="/odom"))
    bag = small_bag(
        tmp_path / "nan", "sqlite3", edit=lambda k, s: setattr(s, "angle_increment", np.nan if k == 1 else 0.5)
    )
    with pytest.raises(DatasetError, match=r"nan: /scan message 1: LaserScan: non-finite angle_min, angle_increment"):
        list(read_scans(bag, "rosbag", pose_topic="/odom"))


@pytest.mark.parametrize("kind", KINDS)
def test_truncated_bag_names_the_file(tmp_path, kind):
    bag = small_bag(tmp_path / "cut", kind, n=50)
    storage = bag if kind == "ros1" else next(f for f in bag.iterdir() if f.suffix in (".db3", ".mcap"))
    storage.write_bytes(storage.read_bytes()[: storage.stat().st_size // 2])
    with pytest.raises(DatasetError, match=rf"{storage.name}: cannot read"):
        list(read_scans(storage, "rosbag", pose_topic="/odom"))
    junk = tmp_path / f"junk{storage.suffix}"
    junk.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(DatasetError, match=rf"junk{storage.suffix}: cannot read as a ROS bag"):
        count_scans(junk)


def test_core_install_without_rosbags(tmp_path):
    """services.datasets imports without rosbags; reading a bag then says what to install."""
    bag = small_bag(tmp_path / "b")
    code = (
        "import sys; sys.modules['rosbags'] = None\n"
        "from services.datasets import read_scans, DatasetError\n"
        f"try: list(read_scans({str(bag)!r}))\n"
        "except DatasetError as e: print(e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    assert "pip install 'gmmap[ros]'" in out
