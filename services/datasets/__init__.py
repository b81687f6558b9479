"""Readers of real range data. Every reader yields `RangeScan`s: returned end points and no-return
directions in the sensor frame, plus the sensor pose in the log's map frame. `read_scans` picks
the reader; the formats (READERS):

- carmen: CARMEN laser logs (2D), .log/.clf, FLASER lines with odometry and corrected poses.
- kurt3d: 3DTK Kurt3D scans, scanNNN.3d(.gz) with .pose/.frames files.
- xyz: one plain text file of x y z end points.
- pcd: numbered NNNNNN.pcd(.gz) files (ascii, binary, binary_compressed), --poses KITTI or TUM.
- ply: numbered NNNNNN.ply(.gz) files (ascii, binary little/big endian), --poses KITTI or TUM.
- kitti: a KITTI odometry sequence: velodyne/NNNNNN.bin, calib.txt (Tr), poses.txt or --poses, times.txt.
- rosbag: ROS 1 .bag and ROS 2 .db3/.mcap bags: LaserScan (2D) or PointCloud2 (3D), poses from a pose topic or /tf.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .carmen import FLASER_LINE, count_carmen, match_by_timestamp, read_carmen
from .common import DatasetError, RangeScan, read_text
from .kitti import VELODYNE_FILE, count_kitti, read_kitti
from .kurt3d import SCAN_FILE, count_kurt3d, read_kurt3d
from .pcd import PCD_FILE, count_pcd, read_pcd
from .ply import PLY_FILE, count_ply, read_ply
from .rosbag import count_rosbag, is_rosbag, read_rosbag
from .xyz import read_xyz

__all__ = [
    "DatasetError",
    "FORMATS",
    "READERS",
    "Reader",
    "RangeScan",
    "count_scans",
    "guess_format",
    "keep_beams",
    "match_by_timestamp",
    "read_scans",
]


@dataclass(frozen=True)
class Reader:
    """One format: `read(path, **options)` yields RangeScans; `count(path, **options)` says how
    many without parsing them (for a progress bar)."""

    read: Callable[..., Iterator[RangeScan]]
    count: Callable[..., int]

    @property
    def options(self) -> list[str]:
        """The keywords `read` takes."""
        params = inspect.signature(self.read).parameters.values()
        return sorted(p.name for p in params if p.kind is p.KEYWORD_ONLY)


READERS = {
    "carmen": Reader(read_carmen, lambda path, **_: count_carmen(path)),
    "kurt3d": Reader(read_kurt3d, lambda path, scans=None, **_: count_kurt3d(path, scans=scans)),
    "xyz": Reader(read_xyz, lambda path, **_: 1),
    "pcd": Reader(read_pcd, lambda path, **_: count_pcd(path)),
    "ply": Reader(read_ply, lambda path, **_: count_ply(path)),
    "kitti": Reader(read_kitti, lambda path, **_: count_kitti(path)),
    "rosbag": Reader(read_rosbag, count_rosbag),
}
FORMATS = tuple(READERS)
_CARMEN_SUFFIXES = {".log", ".clf"}


def guess_format(path: str | Path) -> str:
    """The format of a path.

    rosbag for .bag/.db3/.mcap or a ROS 2 bag directory (metadata.yaml); pcd for NNN.pcd(.gz) or a
    directory of them; ply for NNN.ply(.gz) or a directory of them;
    kitti for a directory with a velodyne/ subdirectory or NNN.bin files; kurt3d for another
    directory or scanNNN.3d(.gz); carmen for .log/.clf, or .gz/.bz2 with FLASER lines; xyz otherwise.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no such file or directory: {path}")
    if is_rosbag(path):
        return "rosbag"
    names = [f.name for f in path.iterdir()] if path.is_dir() else [path.name]
    for fmt, pattern in (("pcd", PCD_FILE), ("ply", PLY_FILE)):
        if any(pattern.fullmatch(n) for n in names):
            return fmt
    if path.is_dir() and ((path / "velodyne").is_dir() or any(VELODYNE_FILE.fullmatch(n) for n in names)):
        return "kitti"
    if path.is_dir() or SCAN_FILE.fullmatch(path.name):
        return "kurt3d"
    suffixes = path.suffixes[-2:]
    if _CARMEN_SUFFIXES & set(suffixes):
        return "carmen"
    if suffixes and suffixes[-1] in (".gz", ".bz2") and FLASER_LINE.search(read_text(path)):
        return "carmen"
    return "xyz"


def read_scans(
    path: str | Path, fmt: str | None = None, *, keep_fraction: float = 1.0, seed: int = 0, **options
) -> Iterator[RangeScan]:
    """The scans of a data file or directory, in order.

    fmt: one of FORMATS, guessed from the path when None. keep_fraction < 1 keeps that
    fraction of each scan's beams, chosen at random from (seed, scan index), the same on every
    run. Other options go to the format's reader (see read_carmen, read_kurt3d, read_xyz, read_pcd,
    read_ply, read_kitti, read_rosbag).
    Bad files raise DatasetError naming file and line; a missing one FileNotFoundError.
    """
    if not 0 < keep_fraction <= 1:
        raise ValueError(f"keep_fraction must be in (0, 1], got {keep_fraction}")
    if not (isinstance(seed, (int, np.integer)) and seed >= 0):
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    fmt = fmt or guess_format(path)
    scans = _reader(fmt, options).read(path, **options)
    if keep_fraction == 1:
        return scans
    return (keep_beams(scan, keep_fraction, seed) for scan in scans)


def count_scans(path: str | Path, fmt: str | None = None, **options) -> int:
    """How many scans read_scans will yield (for a progress bar), without parsing the ranges."""
    fmt = fmt or guess_format(path)
    return _reader(fmt, options).count(path, **options)


def _reader(fmt: str, options: dict) -> Reader:
    """The reader of `fmt`; a ValueError names an unknown format or an option it does not take."""
    if fmt not in READERS:
        raise ValueError(f"unknown format {fmt!r}; expected one of {', '.join(FORMATS)}")
    reader = READERS[fmt]
    unknown = sorted(set(options) - set(reader.options))
    if unknown:
        flags = ", ".join("--" + name.replace("_", "-") for name in unknown)
        raise ValueError(f"{flags}: not an option of the {fmt} format (it takes {', '.join(reader.options) or 'none'})")
    return reader


def keep_beams(scan: RangeScan, keep_fraction: float, seed: int) -> RangeScan:
    """The scan with round(keep_fraction * beams) of its beams, hits and no-returns alike.

    The choice depends only on (seed, scan.index), so a sparsity study is repeatable.
    """
    n_hits, n_beams = len(scan.hits), len(scan.hits) + len(scan.no_return)
    rng = np.random.default_rng((seed, scan.index))
    keep = np.zeros(n_beams, dtype=bool)
    keep[rng.choice(n_beams, size=round(keep_fraction * n_beams), replace=False)] = True
    return replace(scan, hits=scan.hits[keep[:n_hits]], no_return=scan.no_return[keep[n_hits:]])
