"""Pose files for point-cloud sequences: KITTI layout or TUM layout, sensor to world.

- KITTI: 12 numbers a line, row-major [R|t]; line k (0-based) is the pose of the scan file
  numbered k, so the file may have more lines than there are scans.
- TUM: `stamp tx ty tz qx qy qz qw` a line; each scan gets the pose whose stamp is nearest
  to its own (for PCD/PLY sequences the stamp is the file number).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gmm_core.pose import Pose

from .common import DatasetError, parse_rows, proper_rotation, quaternion_pose, read_text


def read_poses(path: Path, numbers: list[int], stamps: np.ndarray) -> list[Pose]:
    """One Pose per scan: KITTI rows by file number, or TUM rows by nearest stamp."""
    text = read_text(path)
    first = next((ln.split() for ln in text.splitlines() if ln.split("#", 1)[0].strip()), None)
    if first is None:
        raise DatasetError(f"{path.name}: no data rows")
    if len(first) == 12:
        rows = parse_rows(text, path.name, 12)
        lines = [k + 1 for k, ln in enumerate(text.splitlines()) if ln.split("#", 1)[0].strip()]
        out = []
        for n in numbers:
            if n >= len(rows):
                raise DatasetError(f"{path.name}: {len(rows)} poses, no line for scan {n}")
            M = rows[n].reshape(3, 4)
            out.append(Pose(proper_rotation(M[:, :3], f"{path.name}:{lines[n]}"), M[:, 3].copy()))
        return out
    if len(first) == 8:
        rows = parse_rows(text, path.name, 8)
        order = np.argsort(rows[:, 0])
        rows = rows[order]
        out = []
        for s in stamps:
            j = int(np.clip(np.searchsorted(rows[:, 0], s), 1, len(rows) - 1)) if len(rows) > 1 else 0
            if len(rows) > 1 and abs(rows[j - 1, 0] - s) <= abs(rows[j, 0] - s):
                j -= 1
            t, q = rows[j, 1:4], rows[j, 4:8]
            out.append(quaternion_pose(t, np.array([q[3], q[0], q[1], q[2]]), f"{path.name}:{int(order[j]) + 1}"))
        return out
    raise DatasetError(f"{path.name}:1: expected 12 numbers (KITTI) or 8 (TUM), found {len(first)} fields")
