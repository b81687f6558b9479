"""3DTK (slam6d) Kurt3D scans: a directory of `scanNNN.3d(.gz)` files with their poses.

3DTK writes everything in centimetres in a LEFT-handed frame (x right, y up, z forward):

- `scanNNN.3d(.gz)`: lines `x y z`, one end point per beam, in the scanner frame. The tilting
  SICK writes about 3276 cm (its 16-bit maximum) for a beam with no return, and cannot measure
  closer than 48 cm (config.ini: max=3276, min=48).
- `scanNNN.pose`: `tx ty tz` then `rx ry rz` in degrees, the odometry guess; 3DTK builds
  R = Rx(rx) Ry(ry) Rz(rz).
- `scanNNN.frames`: one line per registration step: a 4x4 scanner-to-world matrix in
  column-major order, then an algorithm code. The last line is the registered (ICP) pose.

gmmap works in right-handed metres (x forward, y left, z up): p_rh = C p_lh / 100 with
C = [[0, 0, 1], [-1, 0, 0], [0, 1, 0]], i.e. x_rh = z, y_rh = -x, z_rh = y. C is a reflection
(det -1), so a left-handed rotation becomes R_rh = C R C^T (det +1 again) and t_rh = C t / 100.

`RangeScan.pose` is the registered pose (the .pose guess when there is no .frames file) and
`odom_pose` the .pose guess. 3DTK logs carry no time: `index` and `stamp` are the scan number NNN.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from gmm_core.pose import Pose

from .common import DatasetError, RangeScan, numbered_files, parse_rows, proper_rotation, read_text, split_points

LH_TO_RH = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
CM = 0.01
MIN_RANGE = 0.48  # metres; config.ini min=48
# The no-return value is 3275.9-3276.7 cm; real returns reach 3238 cm in scan000, so the
# threshold sits between the two.
NO_RETURN_RANGE = 32.7  # metres
SCAN_FILE = re.compile(r"scan(\d+)\.3d(\.gz)?")


def _scan_files(path: Path, scans: Iterable[int] | None) -> list[tuple[int, Path]]:
    """(scan number, point file) in scan order: every scan of a directory, or the one file given."""
    found = numbered_files(path, SCAN_FILE, "kurt3d", "scanNNN.3d or scanNNN.3d.gz")
    wanted = sorted(found) if scans is None else list(scans)
    missing = [i for i in wanted if i not in found]
    if missing:
        raise DatasetError(f"{path}: no scans {missing}; it has {sorted(found)}")
    return [(i, found[i]) for i in wanted]


def count_kurt3d(path: str | Path, *, scans: Iterable[int] | None = None) -> int:
    return len(_scan_files(Path(path), scans))


def _to_right_handed(R_lh: np.ndarray, t_lh_cm: np.ndarray, where: str) -> Pose:
    """A left-handed centimetre pose as a right-handed metre Pose; R_lh must be a rotation."""
    return Pose(LH_TO_RH @ proper_rotation(R_lh, where) @ LH_TO_RH.T, LH_TO_RH @ t_lh_cm * CM)


def _registered_pose(frames: Path) -> Pose:
    rows = parse_rows(read_text(frames), frames.name, 17)
    M = rows[-1, :16].reshape(4, 4).T  # column-major
    where = f"{frames.name}:{len(rows)}"
    if not np.allclose(M[3], [0, 0, 0, 1]):
        raise DatasetError(f"{where}: last matrix row is {M[3].tolist()}, expected [0, 0, 0, 1]")
    return _to_right_handed(M[:3, :3], M[:3, 3], where)


def _euler_pose(pose_file: Path) -> Pose:
    rows = parse_rows(read_text(pose_file), pose_file.name, 3)
    if rows.shape != (2, 3):
        raise DatasetError(f"{pose_file.name}: expected 2 lines (translation cm, Euler angles deg), found {len(rows)}")
    (cx, cy, cz), (sx, sy, sz) = np.cos(np.radians(rows[1])), np.sin(np.radians(rows[1]))
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return _to_right_handed(Rx @ Ry @ Rz, rows[0], pose_file.name)


def read_kurt3d(
    path: str | Path,
    *,
    scans: Iterable[int] | None = None,
    min_range: float = MIN_RANGE,
    no_return_range: float = NO_RETURN_RANGE,
) -> Iterator[RangeScan]:
    """The scans of a 3DTK directory (or one scanNNN.3d(.gz) file) in right-handed metres.

    `scans` picks scan numbers NNN; ranges (metres) below `min_range` are dropped, at or beyond
    `no_return_range` they are no-return directions.
    """
    files = _scan_files(Path(path), scans)  # eager, so a bad path fails at the call
    return _scans(files, min_range, no_return_range)


def _scans(files: list[tuple[int, Path]], min_range: float, no_return_range: float) -> Iterator[RangeScan]:
    for number, points_file in files:
        stem = points_file.name.split(".")[0]  # scanNNN
        pose_file = points_file.with_name(f"{stem}.pose")
        frames_file = points_file.with_name(f"{stem}.frames")
        odom = _euler_pose(pose_file) if pose_file.exists() else None
        if frames_file.exists():
            pose = _registered_pose(frames_file)
        elif odom is not None:
            pose = odom
        else:
            raise DatasetError(f"{points_file.name}: neither {frames_file.name} nor {pose_file.name} exists")
        points_lh_cm = parse_rows(read_text(points_file), points_file.name, 3)
        hits, no_return = split_points(points_lh_cm @ (LH_TO_RH * CM).T, min_range, no_return_range)
        yield RangeScan(index=number, stamp=float(number), pose=pose, odom_pose=odom, hits=hits, no_return=no_return)
