"""Sequences of point-cloud files, one scan a file (PCD, PLY, KITTI velodyne): files -> RangeScans.

Every file holds one scan's end points in the sensor frame and carries no time or pose itself;
its number NNNNNN orders the sequence and picks its line in a poses file (poses.read_poses).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

from gmm_core.pose import Pose

from .common import RangeScan, numbered_files, split_points
from .poses import read_poses

PointReader = Callable[[Path], np.ndarray]  # one file -> (n, 3) float64 end points, sensor frame


def point_files(path: Path, pattern: re.Pattern[str], fmt: str) -> list[tuple[int, Path]]:
    """(number, file) in number order: the numbered files of a directory, or the one file given."""
    return sorted(numbered_files(path, pattern, fmt, f"numbered {fmt}").items())


def point_scans(
    files: list[tuple[int, Path]],
    read_points: PointReader,
    stamps: np.ndarray,
    poses: Sequence[Pose] | None,
    min_range: float,
) -> Iterator[RangeScan]:
    """One RangeScan a file, read as it is reached; poses None: the identity for every scan."""
    for i, (number, f) in enumerate(files):
        hits, no_return = split_points(read_points(f), min_range, None)
        pose = Pose.identity(3) if poses is None else poses[i]
        yield RangeScan(index=number, stamp=float(stamps[i]), pose=pose, odom_pose=None, hits=hits, no_return=no_return)


def read_numbered_clouds(
    path: str | Path,
    pattern: re.Pattern[str],
    fmt: str,
    read_points: PointReader,
    poses: str | Path | None,
    min_range: float,
) -> Iterator[RangeScan]:
    """The scans of numbered point files whose stamp is their number (PCD, PLY), with the poses
    of a poses file (KITTI rows by number, TUM rows by nearest stamp) or identity poses."""
    files = point_files(Path(path), pattern, fmt)
    numbers = [k for k, _ in files]
    stamps = np.array(numbers, dtype=np.float64)
    pose_list = read_poses(Path(poses), numbers, stamps) if poses is not None else None
    yield from point_scans(files, read_points, stamps, pose_list, min_range)
