"""PLY reader: files the independent library plyfile writes from the real BALM scans, hand-made
variants (type names, big-endian lists), and bad files."""

from __future__ import annotations

import gzip
from itertools import islice

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from services.datasets import DatasetError, count_scans, guess_format, read_scans
from services.datasets.ply import read_ply_points
from support.balm import BALM, BALM_NUMBERS, balm_points

ASCII_HEAD = "ply\nformat ascii 1.0\ncomment hand-made\nelement vertex 3\nproperty float x\nproperty float y\n"


@pytest.fixture(scope="module")
def balm():
    return balm_points()


def _vertex(xyz: np.ndarray, **types) -> PlyElement:
    """A vertex element of the points (float32 unless `types` says) with intensity and normals around x y z."""
    rng = np.random.default_rng(len(xyz))
    dtype = [("intensity", "f4"), ("x", types.get("x", "f4")), ("y", types.get("y", "f4")), ("z", types.get("z", "f4"))]
    v = np.empty(len(xyz), dtype=[*dtype, ("nx", "f4"), ("ny", "f4"), ("nz", "f4")])
    v["x"], v["y"], v["z"] = xyz.T
    v["intensity"], v["nx"], v["ny"], v["nz"] = rng.random((4, len(xyz)))
    return PlyElement.describe(v, "vertex")


def _faces(n: int) -> PlyElement:
    """n faces of 3 to 6 vertex indices each (a two-byte count: byte order matters), and a scalar after the list."""
    f = np.empty(n, dtype=[("vertex_indices", "O"), ("flags", "u1")])
    for i in range(n):
        f["vertex_indices"][i] = np.arange(i, i + 3 + i % 4, dtype=np.int32)
    f["flags"] = np.arange(n) % 256
    return PlyElement.describe(f, "face", len_types={"vertex_indices": "u2"}, val_types={"vertex_indices": "i4"})


def _write(path, elements, text=False, byte_order="<"):
    PlyData(elements, text=text, byte_order=byte_order).write(str(path))
    return path


@pytest.mark.parametrize("faces_first", [True, False])
@pytest.mark.parametrize("text,byte_order", [(True, "="), (False, "<"), (False, ">")])
def test_plyfile_written_balm_scan(tmp_path, balm, text, byte_order, faces_first):
    xyz = balm[12]
    elements = [_faces(40), _vertex(xyz)] if faces_first else [_vertex(xyz), _faces(40)]
    got = read_ply_points(_write(tmp_path / "000012.ply", elements, text, byte_order))
    assert got.dtype == np.float64 and len(got) > 1000
    np.testing.assert_array_equal(got, xyz)  # float32 exactly, ascii included


def test_gz_and_non_finite_points_dropped(tmp_path, balm):
    xyz = balm[0].astype(np.float32)
    xyz[::9, 0], xyz[1::9, 2], xyz[2::9, 1] = np.nan, np.inf, -np.inf
    path = _write(tmp_path / "000000.ply", [_vertex(xyz)])
    gz = tmp_path / "000000.ply.gz"
    gz.write_bytes(gzip.compress(path.read_bytes()))
    keep = np.isfinite(xyz).all(axis=1)
    assert 0 < keep.sum() < len(xyz)
    np.testing.assert_array_equal(read_ply_points(gz), xyz[keep])


@pytest.mark.parametrize("text", [True, False])
def test_coordinate_types_and_sized_type_names(tmp_path, text):
    rng = np.random.default_rng(3)
    xyz = np.column_stack([rng.integers(-3000, 3000, 300), rng.normal(size=300), rng.integers(1, 250, 300)])
    path = _write(tmp_path / "000001.ply", [_faces(3), _vertex(xyz, x="i2", y="f8", z="u1")], text, ">")
    np.testing.assert_array_equal(read_ply_points(path), xyz)
    raw = path.read_bytes()
    head, body = raw.split(b"end_header\n", 1)
    for old, new in ((b"short x", b"int16 x"), (b"double y", b"float64 y"), (b"uchar z", b"uint8 z")):
        assert old in head
        head = head.replace(old, new)
    path.write_bytes(head + b"end_header\n" + body)
    np.testing.assert_array_equal(read_ply_points(path), xyz)


def test_ascii_values_take_the_declared_type(tmp_path):
    # "0.1" as a float property is float32(0.1), as plyfile (and a binary file) would have it
    path = tmp_path / "000004.ply"
    path.write_text(ASCII_HEAD + "property double z\nend_header\n0.1 0.2 0.3\n-1e-3 7 0.1\n2.5 1 1\n")
    theirs = PlyData.read(str(path))["vertex"]
    got = read_ply_points(path)
    np.testing.assert_array_equal(got, np.column_stack([theirs["x"], theirs["y"], theirs["z"]]))
    assert got[0, 0] == float(np.float32(0.1)) and got[0, 0] != 0.1 and got[0, 2] == 0.3


def _listed_vertices(n: int) -> np.ndarray:
    """Vertices with a list property (a ring of 0-2 ints) before x y z."""
    rng = np.random.default_rng(4)
    v = np.empty(n, dtype=[("ring", "O"), ("x", "f4"), ("y", "f4"), ("z", "f4")])
    for i in range(n):
        v["ring"][i] = np.arange(i % 3, dtype=np.int32)
    v["x"], v["y"], v["z"] = rng.normal(size=(3, n)).astype(np.float32)
    return v


@pytest.mark.filterwarnings("ignore:loadtxt")  # plyfile reading an empty ascii list
@pytest.mark.parametrize("text", [True, False])
def test_vertex_with_list_property(tmp_path, text):
    v = _listed_vertices(200)
    path = _write(tmp_path / "000002.ply", [PlyElement.describe(v, "vertex"), _faces(5)], text, "<")
    theirs = PlyData.read(str(path))["vertex"]
    expected = np.column_stack([theirs["x"], theirs["y"], theirs["z"]])
    np.testing.assert_array_equal(expected, np.column_stack([v["x"], v["y"], v["z"]]))
    np.testing.assert_array_equal(read_ply_points(path), expected)


def test_big_endian_vertex_with_list_property(tmp_path):
    # by hand: plyfile writes the scalars of a list-bearing element in native order whatever byte_order says
    v = _listed_vertices(50)
    head = "ply\nformat binary_big_endian 1.0\nelement vertex 50\nproperty list ushort int ring\n"
    head += "property float x\nproperty float y\nproperty float z\nend_header\n"
    body = b"".join(
        np.array(len(r), ">u2").tobytes() + r.astype(">i4").tobytes() + np.array([x, y, z], ">f4").tobytes()
        for r, x, y, z in v
    )
    path = tmp_path / "000003.ply"
    path.write_bytes(head.encode() + body)
    np.testing.assert_array_equal(read_ply_points(path), np.column_stack([v["x"], v["y"], v["z"]]))
    path.write_bytes(head.encode() + body[:-5])
    with pytest.raises(DatasetError, match="000003.ply: truncated"):
        read_ply_points(path)


def test_sequence_with_balm_poses_equals_pcd(tmp_path, balm):
    for k, xyz in balm.items():
        _write(tmp_path / f"{k:06d}.ply", [_vertex(xyz), _faces(4)])
    assert guess_format(tmp_path) == "ply" and count_scans(tmp_path) == 3
    scans = list(read_scans(tmp_path, poses=BALM / "poses.txt"))
    pcd = list(islice(read_scans(BALM, "pcd", poses=BALM / "poses.txt"), 3))
    assert [s.index for s in scans] == [s.index for s in pcd] == list(BALM_NUMBERS)
    for s, p in zip(scans, pcd):
        assert s.stamp == p.stamp
        np.testing.assert_array_equal(s.pose.R, p.pose.R)
        np.testing.assert_array_equal(s.pose.t, p.pose.t)
        np.testing.assert_array_equal(s.hits, balm[s.index][np.linalg.norm(balm[s.index], axis=1) > 0])
    one = tmp_path / "000012.ply"
    assert guess_format(one) == "ply" and count_scans(one, "ply") == 1
    (only,) = read_scans(one)
    np.testing.assert_array_equal(only.pose.R, np.eye(3))
    np.testing.assert_array_equal(only.pose.t, np.zeros(3))


@pytest.mark.parametrize(
    "text,match",
    [
        ("solid cube\n", r"000000.ply:1: not a PLY file"),
        ("ply\nformat ascii 1.0\nelemnt vertex 3\nend_header\n", r"000000.ply:3: bad header line 'elemnt vertex 3'"),
        ("ply\nformat ascii 1.0\nelement vertex 1\nproperty half x\nend_header\n", r"000000.ply:4: bad property"),
        ("ply\nformat ascii 1.0\nproperty float x\nend_header\n", r"000000.ply:3: bad header line"),
        ("ply\nformat ascii 2.0 extra\nend_header\n", r"000000.ply:2: bad header line"),
        (ASCII_HEAD + "property float z\n", r"000000.ply: header has no end_header"),
        (ASCII_HEAD + "property float intensity\nend_header\n1 2 3\n", r"000000.ply: vertex element has no x y z"),
        ("ply\nformat ascii 1.0\nelement face 0\nend_header\n", r"000000.ply: no vertex element \(has \['face'\]\)"),
        (ASCII_HEAD + "property float z\nend_header\n1 2 3\n4 5 6\n", r"000000.ply: truncated: 2 lines for 3 vertex"),
        (ASCII_HEAD + "property float z\nend_header\n1 2 3\n4 5 six\n7 8 9\n", r"000000.ply:10: non-numeric"),
        (ASCII_HEAD + "property float z\nend_header\n1 2 3\n4 5\n7 8 9\n", r"000000.ply:10: expected 3 numbers"),
    ],
)
def test_bad_files_named(tmp_path, text, match):
    (tmp_path / "000000.ply").write_text(text)
    with pytest.raises(DatasetError, match=match):
        list(read_scans(tmp_path, "ply"))


@pytest.mark.parametrize("faces_first", [True, False])
def test_truncated_binary_named(tmp_path, faces_first):
    xyz = np.ones((100, 3))
    elements = [_faces(10), _vertex(xyz)] if faces_first else [_vertex(xyz), _faces(10)]
    path = _write(tmp_path / "000007.ply", elements)
    path.write_bytes(path.read_bytes()[:-7])
    with pytest.raises(DatasetError, match=f"000007.ply: truncated: .* {'vertex' if faces_first else 'face'} elements"):
        read_ply_points(path)
