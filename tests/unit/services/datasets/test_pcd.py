"""PCD reader and poses files: the real BALM scans, files pypcd4 / python-neo-lzf write, bad files."""

from __future__ import annotations

import lzf
import numpy as np
import pytest
from pypcd4 import Encoding, PointCloud

from services.datasets import DatasetError, count_scans, guess_format, read_scans
from services.datasets.pcd import lzf_decompress, read_pcd_points
from support.paths import DATA

BALM = DATA / "3d" / "balm-os0"


def test_balm_first_scans_with_kitti_poses():
    assert guess_format(BALM) == "pcd"
    assert count_scans(BALM, "pcd") == 15
    scans = read_scans(BALM, "pcd", poses=BALM / "poses.txt")
    first = [next(scans) for _ in range(3)]
    assert [s.index for s in first] == [0, 12, 24]
    for s in first:
        assert s.hits.shape[0] > 10_000 and np.isfinite(s.hits).all()
        assert 0.5 < np.median(np.linalg.norm(s.hits, axis=1)) < 100
    row12 = np.loadtxt(BALM / "poses.txt")[12].reshape(3, 4)
    np.testing.assert_allclose(first[1].pose.t, row12[:, 3])
    np.testing.assert_allclose(first[1].pose.R, row12[:, :3], atol=1e-5)


def test_without_poses_identity():
    s = next(iter(read_scans(BALM, "pcd")))
    np.testing.assert_array_equal(s.pose.R, np.eye(3))


@pytest.mark.parametrize("encoding", [Encoding.ASCII, Encoding.BINARY])
def test_pypcd4_written_with_extra_fields(tmp_path, encoding):
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(500, 3)).astype(np.float32) * 5
    intensity = rng.random(500).astype(np.float32)
    ring = rng.integers(0, 64, 500).astype(np.uint16)
    pc = PointCloud.from_points(
        [xyz[:, 0], xyz[:, 1], xyz[:, 2], intensity, ring],
        ("x", "y", "z", "i", "ring"),
        (np.float32, np.float32, np.float32, np.float32, np.uint16),
    )
    pc.save(tmp_path / "000003.pcd", encoding=encoding)
    got = read_pcd_points(tmp_path / "000003.pcd")
    np.testing.assert_allclose(got, xyz, atol=1e-6)


def _compressed_pcd(path, xyz, extra, width, height):
    """binary_compressed written by hand, compressed by python-neo-lzf (liblzf)."""
    n = len(xyz)
    header = (
        "VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
        f"WIDTH {width}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary_compressed\n"
    )
    cols = np.concatenate([xyz[:, 0], xyz[:, 1], xyz[:, 2], extra]).astype("<f4").tobytes()
    comp = lzf.compress(cols)
    path.write_bytes(header.encode() + np.array([len(comp), len(cols)], "<u4").tobytes() + comp)


def test_binary_compressed_organised_with_nans(tmp_path):
    rng = np.random.default_rng(1)
    xyz = np.round(rng.normal(size=(64 * 32, 3)), 1).astype(np.float32)  # repeats: real back references
    xyz[::7] = np.nan
    _compressed_pcd(tmp_path / "000000.pcd", xyz, rng.random(len(xyz)), 64, 32)
    got = read_pcd_points(tmp_path / "000000.pcd")
    keep = np.isfinite(xyz).all(axis=1)
    np.testing.assert_array_equal(got, xyz[keep].astype(np.float64))


def test_lzf_roundtrip_against_liblzf():
    data = bytes(np.random.default_rng(2).integers(0, 4, 100_000, dtype=np.uint8)) + b"abc" * 5000
    assert lzf_decompress(lzf.compress(data), len(data)) == data
    with pytest.raises(ValueError):
        lzf_decompress(b"\xff\xff\xff", 10)


def test_bad_files_named(tmp_path):
    (tmp_path / "000000.pcd").write_text(
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nPOINTS 2\nDATA ascii\n1 2 3\n1 2 oops\n"
    )
    with pytest.raises(DatasetError, match=r"000000.pcd:9: non-numeric"):
        list(read_scans(tmp_path, "pcd"))
    (tmp_path / "000000.pcd").write_text("VERSION 0.7\nFIELDS x y z\nDATA ascii\n")
    with pytest.raises(DatasetError, match="000000.pcd: bad or missing header"):
        list(read_scans(tmp_path, "pcd"))


def test_tum_and_bad_poses(tmp_path):
    xyz = np.ones((5, 3), np.float32)
    for k in (0, 1):
        PointCloud.from_xyz_points(xyz).save(tmp_path / f"{k:06d}.pcd")
    poses = tmp_path / "tum.txt"
    poses.write_text("0.1 1 2 3 0 0 0 1\n0.9 4 5 6 0 0 0.7071068 0.7071068\n")
    s = list(read_scans(tmp_path, "pcd", poses=poses))
    np.testing.assert_allclose(s[1].pose.t, [4, 5, 6])
    np.testing.assert_allclose(s[1].pose.R @ [1, 0, 0], [0, 1, 0], atol=1e-6)
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DatasetError, match="1 poses, no line for scan 1"):
        list(read_scans(tmp_path, "pcd", poses=poses))
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DatasetError, match="kitti.txt:2|tum.txt:2: not a proper rotation"):
        list(read_scans(tmp_path, "pcd", poses=poses))


def test_replay_three_balm_scans(tmp_path):
    from services.cli import main

    seq = tmp_path / "balm"
    seq.mkdir()
    for k in (0, 12, 24):
        (seq / f"{k:06d}.pcd.gz").symlink_to(BALM / f"{k:06d}.pcd.gz")
    out = tmp_path / "map.npz"
    args = ["replay", str(seq), "--format", "pcd", "--poses", str(BALM / "poses.txt"), "--resolution", "0.5"]
    assert main([*args, "--out", str(out)]) == 0
    m = np.load(out)
    occupied, free = (m["prob"] > 0.7).sum(), (m["prob"] < 0.3).sum()
    assert occupied > 500 and free > occupied  # walls seen, and the space the beams crossed is free


def test_agent_pcd_source_with_poses(tmp_path):
    from services.agent.sources import load_nodes, parse_source

    for k in (0, 1):
        PointCloud.from_xyz_points(np.ones((5, 3), np.float32)).save(tmp_path / f"{k:06d}.pcd")
    (tmp_path / "p.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 7 0 1 0 0 0 0 1 0\n")
    assert parse_source(f"pcd:{tmp_path}") == ("pcd", str(tmp_path))
    nodes = load_nodes(f"pcd:{tmp_path}", poses=str(tmp_path / "p.txt"))
    assert isinstance(nodes, list)
    np.testing.assert_allclose(nodes[1].estimate.t, [7, 0, 0])
