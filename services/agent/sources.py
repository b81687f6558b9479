"""What an agent publishes: the scans of a data source as pose-graph nodes.

`--source carmen:PATH --corrections PATH` pairs each raw scan with the same scan in a corrected
log (identical beams, services.datasets.match_by_timestamp): the node id is the position in
that matched sequence, the published pose is the raw log's odometry, and the corrected pose is
what the agent's SLAM back end later sends in pose-graph updates. Without corrections the node
id is the scan's index in the log and the log's pose is final.
"""
from __future__ import annotations

from dataclasses import dataclass

from gmm_core import FitConfig, Pose
from services.datasets import RangeScan, match_by_timestamp, read_scans

SOURCE_FORMATS = ("carmen", "kurt3d", "xyz")


@dataclass(frozen=True)
class Node:
    node: int
    scan: RangeScan  # beams in the sensor frame, stamp
    estimate: Pose  # published with the scan (odometry where corrections follow)
    corrected: Pose | None  # sent in pose-graph updates; None: no back end for this source


def parse_source(text: str) -> tuple[str | None, str]:
    """"carmen:PATH" -> ("carmen", PATH); a bare path leaves the format to be guessed (None)."""
    fmt, sep, path = text.partition(":")
    if sep and fmt in SOURCE_FORMATS:
        return fmt, path
    return None, text


def parse_slice(text: str | None) -> slice:
    """"A:B" (either side may be empty) -> slice(A, B)."""
    if not text:
        return slice(None)
    start, sep, stop = text.partition(":")
    try:
        if not sep:
            raise ValueError
        return slice(int(start) if start else None, int(stop) if stop else None)
    except ValueError:
        raise ValueError(f"--scans must be A:B with integers, got {text!r}") from None


def fit_config(dim: int, max_range: float) -> FitConfig:
    # Dense 3D scans: at most one component per cubic metre cell of surface (as `gmmap replay`).
    return FitConfig(max_range=max_range, component_size=1.0 if dim == 3 else None)


def load_nodes(source: str, corrections: str | None = None, scans: str | None = None) -> list[Node]:
    fmt, path = parse_source(source)
    if corrections is None:
        nodes = [Node(s.index, s, s.pose, None) for s in read_scans(path, fmt)]
    else:
        pairs = match_by_timestamp(read_scans(path, fmt), read_scans(corrections))
        if not pairs:
            raise ValueError(f"--corrections: no scan of {path} is in {corrections}")
        nodes = [Node(i, raw, raw.odom_pose or raw.pose, fixed.pose) for i, (raw, fixed) in enumerate(pairs)]
    return nodes[parse_slice(scans)]
