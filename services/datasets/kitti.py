"""KITTI odometry sequences: `velodyne/NNNNNN.bin` scans with `calib.txt`, `poses.txt`, `times.txt`.

- `velodyne/NNNNNN.bin`: float32 little-endian `x y z reflectance` a point, in the velodyne
  frame; points with a non-finite coordinate are dropped.
- `calib.txt`: lines `KEY: numbers`; `Tr:` is 12 numbers, row-major [R|t], velodyne -> left
  camera (x_cam = Tr x_velo). Required: KITTI's poses are the camera's.
- `poses.txt` (or `--poses FILE`, e.g. the devkit's `poses/XX.txt` outside the sequence): line k
  is the left camera's pose of scan file k in the world (camera 0) frame; a TUM-layout file is
  matched to the scans by stamp instead. Either way its poses are the camera's, and the scan's
  (velodyne) pose is Tr^-1 P Tr: the world frame seen as the velodyne's, so that
  pose.apply(hits) = Tr^-1 P Tr x_velo places the points. Without a poses file: identity poses.
- `times.txt` (optional): line k is scan k's stamp in seconds; without it the stamp is the number.

`index` is the file number. The path may be the sequence directory, its velodyne directory, or a
directory of NNNNNN.bin files with calib.txt beside them.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from gmm_core.pose import Pose

from .common import DatasetError, RangeScan, parse_rows, proper_rotation, read_bytes, read_text
from .point_files import point_files, point_scans
from .poses import read_poses

VELODYNE_FILE = re.compile(r"(\d+)\.bin")
_POINT = np.dtype("<f4")
_POINT_BYTES = 4 * _POINT.itemsize  # x y z reflectance


def read_velodyne_points(path: Path) -> np.ndarray:
    """The (n, 3) float64 x y z of one velodyne .bin file, non-finite points dropped."""
    raw = read_bytes(path)
    if len(raw) % _POINT_BYTES:
        raise DatasetError(f"{path.name}: {len(raw)} bytes, not a multiple of {_POINT_BYTES} (float32 x y z r)")
    points = np.frombuffer(raw, dtype=_POINT).reshape(-1, 4)[:, :3].astype(np.float64)
    return np.ascontiguousarray(points[np.isfinite(points).all(axis=1)])


def read_calib_tr(path: Path) -> Pose:
    """calib.txt's `Tr:` line as the velodyne -> left camera Pose."""
    if not path.is_file():
        raise DatasetError(f"{path}: missing; a KITTI sequence needs its Tr (velodyne to camera)")
    for lineno, line in enumerate(read_text(path).splitlines(), 1):
        key, _, numbers = line.partition(":")
        if key.strip() == "Tr":
            M = parse_rows(numbers, path.name, 12, lineno).reshape(3, 4)
            return Pose(proper_rotation(M[:, :3], f"{path.name}:{lineno}"), M[:, 3])
    raise DatasetError(f"{path.name}: no 'Tr:' line (velodyne to camera)")


def _layout(path: Path) -> tuple[Path, Path]:
    """(velodyne scans: a directory or one file, sequence directory with calib.txt)."""
    scans = path / "velodyne" if (path / "velodyne").is_dir() else path
    folder = scans if scans.is_dir() else scans.parent
    return scans, folder.parent if folder.name == "velodyne" else folder


def _stamps(times: Path, numbers: list[int]) -> np.ndarray:
    """times.txt's line k for scan number k."""
    rows = parse_rows(read_text(times), times.name, 1)[:, 0]
    if numbers[-1] >= len(rows):
        raise DatasetError(f"{times.name}: {len(rows)} stamps, no line for scan {numbers[-1]}")
    return rows[numbers]


def count_kitti(path: str | Path) -> int:
    return len(point_files(_layout(Path(path))[0], VELODYNE_FILE, "kitti"))


def read_kitti(path: str | Path, *, poses: str | Path | None = None, min_range: float = 0.0) -> Iterator[RangeScan]:
    """The scans of a KITTI odometry sequence, in file number order (see the module docstring)."""
    scans, sequence = _layout(Path(path))
    files = point_files(scans, VELODYNE_FILE, "kitti")
    tr = read_calib_tr(sequence / "calib.txt")
    numbers = [k for k, _ in files]
    times = sequence / "times.txt"
    stamps = _stamps(times, numbers) if times.is_file() else np.array(numbers, dtype=np.float64)
    if poses is None and (sequence / "poses.txt").is_file():
        poses = sequence / "poses.txt"
    velodyne_poses = None
    if poses is not None:
        tr_inv = tr.inverse()
        velodyne_poses = [tr_inv.compose(cam).compose(tr) for cam in read_poses(Path(poses), numbers, stamps)]
    yield from point_scans(files, read_velodyne_points, stamps, velodyne_poses, min_range)
