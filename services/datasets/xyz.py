"""Plain point files (optionally .gz or .bz2): lines `x y z` in metres, one scan, sensor at `origin`.

Such files carry no pose and no no-return beams; the caller says where the sensor was (the
OctoMap `scan.dat` sensor sits near (0, 0, 0.49)) and, optionally, the range beyond which a
point stands for a beam with no return.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from gmm_core.pose import Pose

from .common import RangeScan, parse_rows, read_text, split_points


def read_xyz(
    path: str | Path, *, origin: Sequence[float] = (0.0, 0.0, 0.0), max_range: float | None = None
) -> Iterator[RangeScan]:
    """One scan: pose = translation to `origin`, hits = points - origin (sensor frame).

    Points at or beyond `max_range` from the origin become no-return directions.
    """
    path = Path(path)
    pose = Pose(np.eye(3), np.asarray(origin, dtype=np.float64))  # validates origin: 3 finite numbers
    points = parse_rows(read_text(path), path.name, 3) - pose.t
    hits, no_return = split_points(points, 0.0, max_range)
    return iter([RangeScan(index=0, stamp=0.0, pose=pose, odom_pose=None, hits=hits, no_return=no_return)])
