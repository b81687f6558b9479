"""What every reader shares: the scan record, the error type, and text-file parsing."""

from __future__ import annotations

import bz2
import gzip
import io
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gmm_core.pose import Pose


class DatasetError(ValueError):
    """A data file that cannot be read as its format; the message names file and line."""


@dataclass(frozen=True)
class RangeScan:
    """One range scan: returned end points and no-return directions, both in the sensor frame.

    The sensor sits at the origin of its own frame; `pose` places that frame in the log's map.
    """

    index: int  # 0-based position in the log's scan sequence
    stamp: float  # logger timestamp, seconds
    pose: Pose  # sensor pose in the log's map frame
    odom_pose: Pose | None  # the uncorrected (odometry) pose, where the log has one
    hits: np.ndarray  # (n, d) end points of returned beams
    no_return: np.ndarray  # (m, d) unit directions of beams that returned nothing

    def __post_init__(self):
        d = self.pose.dim
        for name in ("hits", "no_return"):
            a = getattr(self, name)
            if a.ndim != 2 or a.shape[1] != d or a.dtype != np.float64:
                raise ValueError(f"RangeScan.{name}: expected float64 (n, {d}), got {a.dtype} {a.shape}")


_OPENERS = {".gz": gzip.open, ".bz2": bz2.open}  # decompression by suffix


def read_text(path: Path) -> str:
    """The whole file as text, decompressed by suffix (.gz, .bz2).

    A missing file raises FileNotFoundError; a corrupt archive raises DatasetError.
    """
    # latin-1 decodes any byte, so stray bytes surface as a line-numbered parse error instead
    with _OPENERS.get(path.suffix, open)(path, "rt", encoding="latin-1") as f:
        try:
            return f.read()
        except (OSError, EOFError) as e:
            raise DatasetError(f"{path.name}: cannot read: {e}") from e


def read_bytes(path: Path) -> bytes:
    """The whole file as bytes, decompressed by suffix, with read_text's errors."""
    with _OPENERS.get(path.suffix, open)(path, "rb") as f:
        try:
            return f.read()
        except (OSError, EOFError) as e:
            raise DatasetError(f"{path.name}: cannot read: {e}") from e


def numbered_files(path: Path, pattern: re.Pattern[str], fmt: str, kind: str) -> dict[int, Path]:
    """{number: file} of a directory (or the one file given) whose names `pattern` matches, the
    number being its first group; `kind` describes the files in the error when there are none."""
    if not path.exists():
        raise FileNotFoundError(f"{fmt}: no such file or directory: {path}")
    found: dict[int, Path] = {}
    for f in sorted(path.iterdir()) if path.is_dir() else [path]:
        m = pattern.fullmatch(f.name)
        if m:
            if int(m[1]) in found:
                raise DatasetError(f"{f.name}: scan {int(m[1])} exists twice ({found[int(m[1])].name})")
            found[int(m[1])] = f
    if not found:
        raise DatasetError(f"{path}: no {kind} files")
    return found


def proper_rotation(R: np.ndarray, where: str) -> np.ndarray:
    """R snapped to the nearest rotation (files print few digits); DatasetError if it is none."""
    if abs(np.linalg.det(R) - 1) > 1e-3 or not np.allclose(R @ R.T, np.eye(3), atol=1e-3):
        raise DatasetError(f"{where}: not a proper rotation: {R.tolist()}")
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt


def quaternion_pose(t: np.ndarray, q_wxyz: np.ndarray, where: str) -> Pose:
    """The pose (t, q) with q normalised: files and messages print few digits, but a norm far
    from 1 (an all-zero quaternion, a field mix-up) is a DatasetError naming `where`."""
    norm = np.linalg.norm(q_wxyz)
    if not 0.9 < norm < 1.1:
        raise DatasetError(f"{where}: quaternion norm {norm:.3f}, expected 1")
    return Pose.from_quaternion(t, np.asarray(q_wxyz, dtype=np.float64) / norm)


def parse_rows(text: str, name: str, ncols: int, first_line: int = 1) -> np.ndarray:
    """Whitespace-separated rows of `ncols` numbers -> (k, ncols) float64; `#` starts a comment.

    first_line: the file's line number of the text's first line (text after a header), for errors.
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "input contained no data": reported below instead
            rows = np.loadtxt(io.StringIO(text), dtype=np.float64, ndmin=2)
    except ValueError:
        rows = None  # loadtxt's message has no file name; find the line ourselves below
    if rows is not None and rows.size == 0:
        raise DatasetError(f"{name}: no data rows")
    if rows is not None and rows.shape[1] == ncols:
        return rows
    for lineno, line in enumerate(text.splitlines(), first_line):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        if len(fields) != ncols:
            raise DatasetError(f"{name}:{lineno}: expected {ncols} numbers, found {len(fields)} fields")
        try:
            [float(x) for x in fields]
        except ValueError:
            raise DatasetError(f"{name}:{lineno}: non-numeric field in {line.strip()!r}") from None
    # float() accepts a few spellings loadtxt refuses (e.g. "1_000")
    raise DatasetError(f"{name}: numbers in a form numpy cannot read")


def classify_beams(
    ranges: np.ndarray, min_range: float, no_return_range: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """Boolean masks (hit, no_return) over beams.

    Ranges in [min_range, no_return_range) are hits; ranges at or beyond no_return_range are
    no-return beams; zero, negative and non-finite ranges are neither.
    """
    limit = np.inf if no_return_range is None else no_return_range
    ok = np.isfinite(ranges) & (ranges > 0)
    return ok & (ranges >= min_range) & (ranges < limit), ok & (ranges >= limit)


def split_points(points: np.ndarray, min_range: float, no_return_range: float | None) -> tuple[np.ndarray, np.ndarray]:
    """(hits, no_return) from end points given directly (3D scans): ranges are their norms."""
    ranges = np.linalg.norm(points, axis=1)
    hit, miss = classify_beams(ranges, min_range, no_return_range)
    return np.ascontiguousarray(points[hit]), points[miss] / ranges[miss, None]
