"""KITTI reader: a sequence built from the real BALM scans and poses with KITTI 00's Tr, and bad files."""

from __future__ import annotations

import shutil
from itertools import islice

import numpy as np
import pytest

from gmm_core.pose import Pose
from services.datasets import DatasetError, count_scans, guess_format, read_scans
from services.datasets.poses import read_poses
from support.balm import BALM, BALM_NUMBERS, balm_points

# KITTI odometry sequence 00's velodyne -> left camera transform, as its calib.txt writes it
TR_00 = (
    "4.276802385584e-04 -9.999672484946e-01 -8.084491683471e-03 -1.198459927713e-02 "
    "-7.210626507497e-03 8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 "
    "9.999738645903e-01 4.859485810390e-04 -7.206933692422e-03 -2.921968648686e-01"
)
P0_00 = "7.188560000000e+02 0 6.071928000000e+02 0 0 7.188560000000e+02 1.852157000000e+02 0 0 0 1 0"


def _matrix(pose: Pose) -> np.ndarray:
    return np.vstack([np.column_stack([pose.R, pose.t]), [0, 0, 0, 1]])


@pytest.fixture(scope="module")
def balm():
    """(points by number, BALM's velodyne poses of every poses.txt line, BALM's stamps)."""
    points = balm_points()
    lines = len(np.loadtxt(BALM / "poses.txt"))
    velodyne = read_poses(BALM / "poses.txt", list(range(lines)), np.arange(lines, dtype=float))
    return points, velodyne, np.loadtxt(BALM / "times.txt")


@pytest.fixture
def sequence(tmp_path, balm):
    """A KITTI sequence directory of the three BALM scans; poses.txt has a line for every BALM pose."""
    points, velodyne, _ = balm
    seq = tmp_path / "sequences" / "07"
    (seq / "velodyne").mkdir(parents=True)
    for k, xyz in points.items():
        reflectance = np.linspace(0, 1, len(xyz))
        np.column_stack([xyz, reflectance]).astype("<f4").tofile(seq / "velodyne" / f"{k:06d}.bin")
    calib = [f"P{i}: {P0_00}" for i in range(4)] + [f"Tr: {TR_00}"]
    (seq / "calib.txt").write_text("\n".join(calib) + "\n")
    tr = np.vstack([np.array(TR_00.split(), dtype=float).reshape(3, 4), [0, 0, 0, 1]])
    camera = [tr @ _matrix(p) @ np.linalg.inv(tr) for p in velodyne]  # P_cam = Tr P_velo Tr^-1
    np.savetxt(seq / "poses.txt", [m[:3].ravel() for m in camera], fmt="%.15e")
    shutil.copy(BALM / "times.txt", seq / "times.txt")
    return seq


def _assert_balm(scans, balm, stamps=True):
    points, _, times = balm
    pcd = list(islice(read_scans(BALM, "pcd", poses=BALM / "poses.txt"), 3))
    assert [s.index for s in scans] == [p.index for p in pcd] == list(BALM_NUMBERS)
    for s, p in zip(scans, pcd):
        assert s.stamp == (times[s.index] if stamps else s.index)
        np.testing.assert_allclose(s.pose.R, p.pose.R, atol=1e-9)
        np.testing.assert_allclose(s.pose.t, p.pose.t, atol=1e-9)
        xyz = points[s.index][np.linalg.norm(points[s.index], axis=1) > 0]
        np.testing.assert_array_equal(s.hits, xyz)  # the pcd reader's points, float32 exactly
        np.testing.assert_allclose(s.pose.apply(s.hits), p.pose.apply(xyz), atol=1e-8)


def test_balm_sequence_gives_balm_poses_points_and_stamps(sequence, balm):
    assert guess_format(sequence) == "kitti" and count_scans(sequence) == 3
    _assert_balm(list(read_scans(sequence)), balm)
    assert guess_format(sequence / "velodyne") == "kitti" and count_scans(sequence / "velodyne", "kitti") == 3
    _assert_balm(list(read_scans(sequence / "velodyne")), balm)  # calib.txt etc. beside velodyne/


def test_devkit_poses_file_and_no_poses(sequence, balm, tmp_path):
    devkit = tmp_path / "poses" / "07.txt"
    devkit.parent.mkdir()
    (sequence / "poses.txt").rename(devkit)
    (sequence / "times.txt").unlink()
    _assert_balm(list(read_scans(sequence, poses=devkit)), balm, stamps=False)
    for s in read_scans(sequence):
        np.testing.assert_array_equal(s.pose.R, np.eye(3))
        np.testing.assert_array_equal(s.pose.t, np.zeros(3))


def test_tum_poses_matched_by_times(sequence, balm):
    camera = read_poses(sequence / "poses.txt", list(BALM_NUMBERS), np.zeros(3))
    times = balm[2][list(BALM_NUMBERS)]
    rows = [[t, *p.t, *p.as_quaternion()[[1, 2, 3, 0]]] for t, p in zip(times, camera)]  # TUM: qx qy qz qw
    (sequence / "poses.txt").unlink()
    np.savetxt(sequence / "tum.txt", rows, fmt="%.15f")
    _assert_balm(list(read_scans(sequence, "kitti", poses=sequence / "tum.txt")), balm)


def test_bad_sequences_named(sequence):
    calib = sequence / "calib.txt"
    text = calib.read_text()
    calib.write_text(text.replace(TR_00, TR_00.rsplit(" ", 1)[0]))
    with pytest.raises(DatasetError, match=r"calib.txt:5: expected 12 numbers, found 11"):
        list(read_scans(sequence))
    calib.write_text(text.replace("Tr:", "Tr_imu:"))
    with pytest.raises(DatasetError, match=r"calib.txt: no 'Tr:' line"):
        list(read_scans(sequence))
    calib.unlink()
    with pytest.raises(DatasetError, match=r"calib.txt: missing; a KITTI sequence needs its Tr"):
        list(read_scans(sequence))
    calib.write_text(text)
    (sequence / "times.txt").write_text("0.0\n0.1\n")
    with pytest.raises(DatasetError, match=r"times.txt: 2 stamps, no line for scan 24"):
        list(read_scans(sequence))
    (sequence / "times.txt").unlink()
    bin12 = sequence / "velodyne" / "000012.bin"
    bin12.write_bytes(bin12.read_bytes()[:-4])
    scans = read_scans(sequence)
    next(scans)
    with pytest.raises(DatasetError, match=r"000012.bin: \d+ bytes, not a multiple of 16"):
        next(scans)
