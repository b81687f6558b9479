"""Range-data readers: the real logs in ../shared/data, and malformed files written here."""

from __future__ import annotations

import bz2
import gzip

import numpy as np
import pytest

from services.datasets import DatasetError, count_scans, guess_format, match_by_timestamp, read_scans
from services.datasets.carmen import load_flaser, saturation_range
from support.paths import DATA

INTEL = DATA / "carmen" / "intel-corrected.log.gz"
FREIBURG = DATA / "carmen" / "freiburg-079-corrected.log.gz"
INTEL_RAW = DATA / "radish" / "intel.clf.bz2"
KURT3D = DATA / "3d" / "kurt3d"
OCTOMAP = DATA / "3d" / "octomap" / "scan.dat.bz2"

needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"real data folder {DATA} is absent")


@pytest.fixture(scope="module")
def intel():
    return list(read_scans(INTEL))


@pytest.fixture(scope="module")
def kurt3d():
    return list(read_scans(KURT3D))


def flaser(ranges, pose=(0.0, 0.0, 0.0), stamp=1.0) -> str:
    numbers = " ".join(str(r) for r in ranges)
    x, y, th = pose
    return f"FLASER {len(ranges)} {numbers} {x} {y} {th} {x} {y} {th} {stamp} host {stamp}\n"


# --- real data ------------------------------------------------------------------------------


@needs_data
def test_intel_corrected(intel):
    assert len(intel) == count_scans(INTEL) == 910
    assert [s.index for s in intel] == list(range(910))
    assert all(len(s.hits) + len(s.no_return) == 180 for s in intel)  # no zero ranges in this log
    assert sum(len(s.no_return) for s in intel) == 4172
    first = intel[0]
    np.testing.assert_allclose(first.hits[0], [0.0, -1.09], atol=1e-12)  # r_1 = 1.09 at -90 deg
    assert first.stamp == pytest.approx(32.9068)
    assert first.pose.as_xytheta() == pytest.approx((0.600266, -0.0320327, -0.354665))
    hits = np.concatenate([s.hits for s in intel])
    assert np.linalg.norm(hits, axis=1).max() < 81.83
    no_return = np.concatenate([s.no_return for s in intel])
    np.testing.assert_allclose(np.linalg.norm(no_return, axis=1), 1.0)


@needs_data
def test_intel_saturation_is_detected():
    assert saturation_range(np.concatenate(load_flaser(INTEL).ranges)) == 81.83


@needs_data
def test_freiburg_has_360_beams_half_a_degree_apart():
    first = next(read_scans(FREIBURG))
    assert len(first.hits) + len(first.no_return) == 360
    assert count_scans(FREIBURG) == 4791
    angles = np.degrees(np.arctan2(first.hits[:, 1], first.hits[:, 0]))
    assert angles[0] == pytest.approx(-90.0)
    assert np.diff(angles).min() == pytest.approx(0.5)


@needs_data
def test_raw_intel_log_pairs_with_corrected_one(intel):
    raw = list(read_scans(INTEL_RAW))
    assert len(raw) == count_scans(INTEL_RAW) == 13631
    pairs = match_by_timestamp(intel, raw)
    assert len(pairs) == 910
    assert len({b.index for _, b in pairs}) == 910
    assert all(abs(a.stamp - b.stamp) < 5e-3 for a, b in pairs)  # corrected stamps: 6 digits
    assert all(np.array_equal(a.hits, b.hits) for a, b in pairs)
    # Timestamps alone mismatch: the raw log has scans microseconds apart, out of order.
    by_time = match_by_timestamp(intel, raw, same_beams=False)
    assert any(not np.array_equal(a.hits, b.hits) for a, b in by_time)


@needs_data
def test_kurt3d_scans(kurt3d):
    assert guess_format(KURT3D) == "kurt3d" and count_scans(KURT3D) == 3
    assert [s.index for s in kurt3d] == [0, 1, 2]
    assert [len(s.no_return) for s in kurt3d] == [1481, 1313, 1618]
    for s in kurt3d:
        assert s.hits.shape[1] == 3
        assert np.linalg.det(s.pose.R) == pytest.approx(1.0)
        ranges = np.linalg.norm(s.hits, axis=1)
        assert 0.48 <= ranges.min() and ranges.max() < 32.7  # metres, not centimetres
        assert np.median(ranges) < 3
    # scan 0 is the map frame; the robot then drove forward (x) about 1.57 m and 3.38 m
    np.testing.assert_allclose(kurt3d[0].pose.R, np.eye(3))
    np.testing.assert_allclose(kurt3d[1].pose.t, [1.56796, 0.036331, -0.0908315])
    np.testing.assert_allclose(kurt3d[2].pose.t, [3.37786, 0.0805008, -0.156539])
    # ICP moved the odometry guess by centimetres
    assert np.linalg.norm(kurt3d[2].pose.t - kurt3d[2].odom_pose.t) < 0.05


@needs_data
def test_kurt3d_keeps_every_line_without_range_limits():
    for s in read_scans(KURT3D, scans=[1], min_range=0.0):
        assert s.index == 1
        assert len(s.hits) + len(s.no_return) == 81360


@needs_data
def test_kurt3d_euler_pose_matches_3dtk_frame():
    # the first line of scan002.frames is the .pose guess as 3DTK turned it into a matrix
    row = np.loadtxt(KURT3D / "scan002.frames")[0]
    M = row[:16].reshape(4, 4).T
    C = np.array([[0, 0, 1], [-1, 0, 0], [0, 1, 0]])
    scan = next(read_scans(KURT3D, scans=[2]))
    np.testing.assert_allclose(scan.odom_pose.R, C @ M[:3, :3] @ C.T, atol=1e-6)
    np.testing.assert_allclose(scan.odom_pose.t, C @ M[:3, 3] / 100)


@needs_data
def test_octomap_xyz():
    assert guess_format(OCTOMAP) == "xyz"
    (scan,) = read_scans(OCTOMAP, origin=(0, 0, 0.49))
    assert scan.hits.shape == (88206, 3) and len(scan.no_return) == 0
    np.testing.assert_allclose(scan.pose.t, [0, 0, 0.49])
    np.testing.assert_allclose(scan.hits[0], [-0.0434742, -4.82982, 0.499645 - 0.49])
    (far,) = read_scans(OCTOMAP, origin=(0, 0, 0.49), max_range=5.0)
    assert len(far.hits) + len(far.no_return) == 88206 and len(far.no_return) > 0
    assert np.linalg.norm(far.hits, axis=1).max() < 5.0


@needs_data
def test_keep_fraction_is_seeded(intel):
    sparse = list(read_scans(INTEL, keep_fraction=0.3, seed=7))
    kept = sum(len(s.hits) + len(s.no_return) for s in sparse)
    assert kept == pytest.approx(0.3 * 910 * 180, rel=0.01)
    again = list(read_scans(INTEL, keep_fraction=0.3, seed=7))
    assert all(
        np.array_equal(a.hits, b.hits) and np.array_equal(a.no_return, b.no_return) for a, b in zip(sparse, again)
    )
    other = next(read_scans(INTEL, keep_fraction=0.3, seed=8))
    assert not np.array_equal(other.hits, sparse[0].hits)
    full = {tuple(p) for p in intel[0].hits}
    assert all(tuple(p) in full for p in sparse[0].hits)  # a subset, not new beams


# --- synthetic files ------------------------------------------------------------------------


def test_carmen_gz_no_return_and_181_beams(tmp_path):
    ranges = [2.0] * 171 + [50.0] * 10  # 50 m ten times: the saturation value
    path = tmp_path / "tiny.log.gz"
    with gzip.open(path, "wt") as f:
        f.write("# comment\nPARAM laser 1\nODOM 0 0 0 0 0 0 1 h 1\n" + flaser(ranges, (1.0, 2.0, 0.5)))
    assert guess_format(path) == "carmen" and count_scans(path) == 1
    (scan,) = read_scans(path)
    assert len(scan.hits) == 171 and len(scan.no_return) == 10
    np.testing.assert_allclose(scan.no_return[-1], [0.0, 1.0], atol=1e-12)  # 181 beams: last at +90
    (given,) = read_scans(path, no_return_range=100.0)
    assert len(given.hits) == 181
    np.testing.assert_allclose(scan.pose.apply(scan.hits[:1]), [[1 + 2 * np.sin(0.5), 2 - 2 * np.cos(0.5)]])


def test_carmen_drops_bad_ranges_and_rare_maximum(tmp_path):
    path = tmp_path / "bad-ranges.clf.bz2"
    with bz2.open(path, "wt") as f:
        f.write(flaser([0.0, -1.0, float("nan"), float("inf"), 9.0] + [1.0] * 175))
    (scan,) = read_scans(path)
    assert len(scan.hits) == 176 and len(scan.no_return) == 0  # 9.0 occurs once: a real return


def test_truncated_flaser_line_names_the_line(tmp_path):
    path = tmp_path / "intel.log"
    path.write_text("# header\n" + flaser([1.0] * 180) + flaser([1.0] * 180)[:-40] + "\n")
    with pytest.raises(DatasetError, match=r"intel\.log:3: FLASER: expected 180 ranges"):
        list(read_scans(path))


def test_wrong_beam_count_names_the_line(tmp_path):
    path = tmp_path / "intel.log"
    path.write_text(flaser([1.0] * 180) + flaser([1.0] * 179))
    with pytest.raises(DatasetError, match=r"intel\.log:2: FLASER: unsupported beam count 179"):
        read_scans(path)
    # a count of 180 followed by only 179 ranges
    path.write_text(flaser([1.0] * 180).replace("FLASER 180 1.0", "FLASER 180", 1))
    with pytest.raises(DatasetError, match=r"intel\.log:1: .*expected 180 ranges"):
        read_scans(path)


def test_non_numeric_field_names_the_line(tmp_path):
    path = tmp_path / "intel.log"
    path.write_text("\n" + flaser([1.0] * 180).replace("1.0", "x", 1))
    with pytest.raises(DatasetError, match=r"intel\.log:2: FLASER: non-numeric"):
        read_scans(path)


def test_bad_xyz_line_names_the_line(tmp_path):
    path = tmp_path / "points.xyz"
    path.write_text("1 2 3\n4 5 6\n7 8\n")
    with pytest.raises(DatasetError, match=r"points\.xyz:3: expected 3 numbers"):
        read_scans(path)


def test_corrupt_archive_and_missing_file(tmp_path):
    path = tmp_path / "broken.log.gz"
    path.write_bytes(gzip.compress(flaser([1.0] * 180).encode())[:-20])
    with pytest.raises(DatasetError, match="broken.log.gz"):
        read_scans(path)
    with pytest.raises(FileNotFoundError, match="nothere.log"):
        read_scans(tmp_path / "nothere.log")
    with pytest.raises(FileNotFoundError, match="nothere"):
        read_scans(tmp_path / "nothere", fmt="kurt3d")
    with pytest.raises(DatasetError, match="no scanNNN"):
        read_scans(tmp_path, fmt="kurt3d")
    with pytest.raises(ValueError, match="unknown format"):
        read_scans(path, fmt="las")
