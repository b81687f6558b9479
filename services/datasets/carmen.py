"""CARMEN laser logs (plain, .gz or .bz2): the FLASER lines, one 2D scan each.

    FLASER n r_1 ... r_n x y theta odom_x odom_y odom_theta ipc_timestamp ipc_hostname logger_timestamp

`x y theta` is the laser pose (SLAM-corrected in the `*-corrected` logs), `odom_*` the odometry
pose. The n beams span 180 degrees starting at theta - 90 deg: 180 or 360 beams are spaced by
180/n degrees (the last one stops a step short of +90), 181 or 361 beams include both ends.
Every other line (`#`, PARAM, ODOM, NEFF, RLASER, ...) is ignored.

A range at or above the sensor's saturation value is a beam with no return. Logs do not record
that value, so unless it is given it is detected: the largest range of the log, provided it
occurs at least `SATURATION_MIN_COUNT` times (a real obstacle is never measured at exactly the
same longest distance that often).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from gmm_core.pose import poses_from_xytheta

from .common import DatasetError, RangeScan, classify_beams, read_text

TRAILING_FIELDS = 9  # x y theta odom_x odom_y odom_theta ipc_timestamp ipc_hostname logger_timestamp
SATURATION_MIN_COUNT = 10
BEAM_COUNTS = (180, 181, 360, 361)
FLASER_LINE = re.compile(r"^FLASER\s", re.MULTILINE)


@dataclass(frozen=True)
class FlaserLog:
    """The FLASER lines of one log, parsed and validated but not yet turned into scans."""

    ranges: list[np.ndarray]  # k arrays of n_i ranges, metres, as logged
    poses: np.ndarray  # (k, 3) laser x y theta
    odom: np.ndarray  # (k, 3) odom_x odom_y odom_theta
    stamps: np.ndarray  # (k,) logger timestamps, seconds


@cache
def beam_directions(n: int) -> np.ndarray:
    """(n, 2) unit directions of an n-beam scan (n in BEAM_COUNTS), sensor frame: x forward, y left."""
    step = np.pi / n if n % 2 == 0 else np.pi / (n - 1)  # odd counts include both ends
    angles = -np.pi / 2 + step * np.arange(n)
    directions = np.column_stack([np.cos(angles), np.sin(angles)])
    directions.flags.writeable = False  # shared by every scan through the cache
    return directions


def _parse_flaser(fields: list[str], where: str) -> np.ndarray:
    """n ranges, then x y theta odom_x odom_y odom_theta ipc_timestamp logger_timestamp."""
    try:
        n = int(fields[1])
    except (IndexError, ValueError):
        raise DatasetError(f"{where}: FLASER: missing or non-integer beam count") from None
    if n not in BEAM_COUNTS:
        raise DatasetError(f"{where}: FLASER: unsupported beam count {n} (expected one of {BEAM_COUNTS})")
    found = len(fields) - 2
    if found != n + TRAILING_FIELDS:
        raise DatasetError(
            f"{where}: FLASER: expected {n} ranges and {TRAILING_FIELDS} pose/timestamp "
            f"fields ({n + TRAILING_FIELDS} values after the count), found {found}"
        )
    try:
        # every field but the hostname, the second to last
        values = np.array(fields[2:-2] + fields[-1:], dtype=np.float64)
    except ValueError:
        raise DatasetError(f"{where}: FLASER: non-numeric field") from None
    if not np.isfinite(values[n:]).all():
        raise DatasetError(f"{where}: FLASER: non-finite pose or timestamp")
    return values


def load_flaser(path: str | Path) -> FlaserLog:
    """Parse every FLASER line of a log; DatasetError names the first bad line."""
    path = Path(path)
    text = read_text(path)
    records = []
    for lineno, line in enumerate(text.splitlines(), 1):
        if line.startswith("FLASER"):
            fields = line.split()
            if fields[0] == "FLASER":
                records.append(_parse_flaser(fields, f"{path.name}:{lineno}"))
    counts = [len(v) - 8 for v in records]
    tails = np.array([v[n:] for v, n in zip(records, counts)]).reshape(-1, 8)
    return FlaserLog(
        ranges=[v[:n] for v, n in zip(records, counts)], poses=tails[:, 0:3], odom=tails[:, 3:6], stamps=tails[:, 7]
    )


def count_carmen(path: str | Path) -> int:
    """Number of FLASER lines, without parsing them."""
    return sum(1 for _ in FLASER_LINE.finditer(read_text(Path(path))))


def saturation_range(ranges: np.ndarray, min_count: int = SATURATION_MIN_COUNT) -> float | None:
    """The sensor's no-return value: the largest finite range if it occurs min_count times."""
    finite = ranges[np.isfinite(ranges)]
    if finite.size == 0:
        return None
    top = finite.max()
    return float(top) if np.count_nonzero(finite == top) >= min_count else None


def read_carmen(path: str | Path, *, no_return_range: float | None = None) -> Iterator[RangeScan]:
    """The FLASER scans of a log, in order; `no_return_range=None` detects the saturation value."""
    log = load_flaser(path)
    if no_return_range is None and log.ranges:
        no_return_range = saturation_range(np.concatenate(log.ranges))
    return _scans(log, no_return_range)


def _scans(log: FlaserLog, no_return_range: float | None) -> Iterator[RangeScan]:
    poses, odom = poses_from_xytheta(log.poses), poses_from_xytheta(log.odom)
    for i, ranges in enumerate(log.ranges):
        directions = beam_directions(len(ranges))
        hit, miss = classify_beams(ranges, 0.0, no_return_range)
        yield RangeScan(
            index=i,
            stamp=float(log.stamps[i]),
            pose=poses[i],
            odom_pose=odom[i],
            hits=directions[hit] * ranges[hit, None],
            no_return=directions[miss],
        )


def match_by_timestamp(
    scans_a: Iterable[RangeScan], scans_b: Iterable[RangeScan], tol: float = 1e-2, same_beams: bool = True
) -> list[tuple[RangeScan, RangeScan]]:
    """Pairs (a, b) of the same scan in two logs: stamps within tol seconds, nearest first.

    Timestamps alone are ambiguous: the raw Intel log holds scans a few microseconds apart and
    out of order, and the corrected logs print stamps to 6 significant digits (+-5 ms after
    1000 s). So with `same_beams` a pair also needs identical hits and no-return beams; without
    it, each a takes the b nearest in time. Scans of a with no partner are left out.
    """
    a, b = list(scans_a), list(scans_b)
    stamps_b = np.array([s.stamp for s in b])
    order = np.argsort(stamps_b, kind="stable")
    sorted_b = stamps_b[order]
    pairs = []
    for scan in a:
        lo = np.searchsorted(sorted_b, scan.stamp - tol)
        hi = np.searchsorted(sorted_b, scan.stamp + tol, "right")
        nearest_first = order[lo:hi][np.argsort(np.abs(sorted_b[lo:hi] - scan.stamp), kind="stable")]
        partner = next((b[j] for j in nearest_first if not same_beams or _same_beams(scan, b[j])), None)
        if partner is not None:
            pairs.append((scan, partner))
    return pairs


def _same_beams(a: RangeScan, b: RangeScan) -> bool:
    return np.array_equal(a.hits, b.hits) and np.array_equal(a.no_return, b.no_return)
