"""What crosses the wire, as frozen dataclasses; see docs/PROTOCOL.md for the bytes.

Construction checks what is cheap and structural (ids, counts, dimensions); the numeric
checks on mixtures (finite, positive definite, normalised) run in the codec, on both sides.
Classes that hold arrays compare by identity (eq=False): numpy arrays have no single truth value.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from gmm_core.pose import Pose
from gmm_core.scan import ScanModel
from protocol.errors import ProtocolError
from protocol.keys import MAX_NODE, check_count, check_id


def _check_finite(value, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ProtocolError(field, f"must be a finite number, got {value!r:.80}")
    return float(value)


def _check_positive(value, field: str) -> float:
    value = _check_finite(value, field)
    if value <= 0:
        raise ProtocolError(field, f"must be > 0, got {value}")
    return value


@dataclass(frozen=True, eq=False)
class ScanMessage:
    """One scan of one robot: its two mixtures in the node frame and the node's pose estimate.

    `pose` maps the node frame into the robot's map frame; later PoseGraphUpdates supersede it.
    """

    fleet: str
    robot: str
    node: int  # unique per robot, increasing with time
    stamp: float  # seconds
    model: ScanModel  # occupied + free mixtures, sensor origin, max range; fixes the dimension
    pose: Pose

    def __post_init__(self):
        check_id(self.fleet, "fleet")
        check_id(self.robot, "robot")
        check_count(self.node, "node")
        object.__setattr__(self, "stamp", _check_finite(self.stamp, "stamp"))
        if not isinstance(self.model, ScanModel):
            raise ProtocolError("model", "must be a gmm_core.scan.ScanModel")
        if not isinstance(self.pose, Pose) or self.pose.dim != self.model.dim:
            raise ProtocolError("pose", f"must be a Pose of dimension {self.model.dim}")

    @property
    def dim(self) -> int:
        return self.model.dim


@dataclass(frozen=True, eq=False)
class PoseGraphUpdate:
    """Corrected node poses in the robot's map frame, and optionally where that frame sits.

    `revision` increases with each update a robot sends. An update lists only the nodes whose
    poses it sets (a robot sends those that moved); the others keep their last pose. A receiver
    applies it node by node: a node takes the pose of the newest revision that listed it, so
    updates may arrive in any order and none is lost (protocol version 2). One revision may come
    in several parts (same revision number) when it does not fit one message. `anchor` maps the
    robot's map frame into the fleet's world frame; the newest revision that carried one wins.
    `poses` are kept in ascending node order, the order version 3 sends them in (as ranges of ids).
    """

    fleet: str
    robot: str
    revision: int
    poses: tuple[tuple[int, Pose], ...]
    anchor: Pose | None = None

    def __post_init__(self):
        check_id(self.fleet, "fleet")
        check_id(self.robot, "robot")
        check_count(self.revision, "revision")
        poses = tuple((node, pose) for node, pose in self.poses)
        if not poses and self.anchor is None:
            raise ProtocolError("poses", "an update needs at least one pose or an anchor")
        for node, pose in poses:
            check_count(node, "poses.nodes")
            if not isinstance(pose, Pose):
                raise ProtocolError("poses.poses", "must be gmm_core.pose.Pose")
        if len({node for node, _ in poses}) != len(poses):
            raise ProtocolError("poses.nodes", "duplicate node id")
        if self.anchor is not None and not isinstance(self.anchor, Pose):
            raise ProtocolError("anchor", "must be a gmm_core.pose.Pose or None")
        dims = {pose.dim for _, pose in poses} | ({self.anchor.dim} if self.anchor is not None else set())
        if len(dims) != 1:
            raise ProtocolError("poses", "all poses and the anchor must share one dimension")
        object.__setattr__(self, "poses", tuple(sorted(poses, key=_node_of)))

    @property
    def dim(self) -> int:
        return self.anchor.dim if self.anchor is not None else self.poses[0][1].dim


def _node_of(entry: tuple[int, Pose]) -> int:
    return entry[0]


@dataclass(frozen=True)
class Ack:
    """Store `store` (a server's data directory, by its identity) holds these scans (kind "scan",
    ids = node ids) or has applied these pose-graph revisions (kind "poses", ids = revisions);
    `queued` were received and wait in the server's queue, not yet stored: not to be resent, not
    yet to be forgotten. A robot forgets only what a store it reports to acknowledged."""

    fleet: str
    robot: str
    store: str
    kind: Literal["scan", "poses"]
    ids: tuple[int, ...]
    queued: tuple[int, ...] = ()

    def __post_init__(self):
        check_id(self.fleet, "fleet")
        check_id(self.robot, "robot")
        check_id(self.store, "store")
        if self.kind not in ("scan", "poses"):
            raise ProtocolError("kind", f'must be "scan" or "poses", got {self.kind!r:.80}')
        for name in ("ids", "queued"):
            values = tuple(getattr(self, name))
            for value in values:
                check_count(value, name)
            object.__setattr__(self, name, values)


@dataclass(frozen=True)
class Rejection:
    """Store `store` refuses these scans (kind "scan", ids = node ids) or pose-graph revisions
    (kind "poses", ids = revisions) for good: resending them gets the same answer. `reason` is a
    code ("quota": the robot's storage quota on the server is used up; "dimension": the message
    is 2D and the map 3D, or the reverse), `detail` says it in words for the robot's log. Robots
    stop resending them and report the reason.

    A message of its own (not a flag on Ack), so a decoder that predates it ignores it as an
    unknown type and keeps resending: it can never take a refusal for an acknowledgement.
    """

    fleet: str
    robot: str
    store: str
    kind: Literal["scan", "poses"]
    ids: tuple[int, ...]
    reason: str
    detail: str = ""

    def __post_init__(self):
        Ack(self.fleet, self.robot, self.store, self.kind, self.ids)  # the same rules as an Ack
        object.__setattr__(self, "ids", tuple(self.ids))
        check_id(self.reason, "reason")
        if not isinstance(self.detail, str) or len(self.detail.encode()) > 1000:
            raise ProtocolError("detail", "must be a string of at most 1000 bytes (UTF-8)")


@dataclass(frozen=True)
class StoreInventory:
    """What store `store` holds of one robot: its scans' node ids as sorted, disjoint, non-touching
    half-open ranges [start, stop), and the newest pose-graph revision it applied (None: none).
    The reply to a get on the robot's inventory key: a robot that finds a node missing (a new data
    directory, a restored backup) sends it again."""

    fleet: str
    robot: str
    store: str
    ranges: tuple[tuple[int, int], ...]
    revision: int | None = None

    def __post_init__(self):
        Ack(self.fleet, self.robot, self.store, "scan", ())
        ranges = check_ranges(self.ranges, "ranges")
        if self.revision is not None:
            check_count(self.revision, "revision")
        object.__setattr__(self, "ranges", ranges)

    @classmethod
    def of(cls, fleet: str, robot: str, store: str, nodes, revision: int | None = None) -> StoreInventory:
        """The inventory of a set of node ids."""
        return cls(fleet, robot, store, node_ranges(sorted(set(nodes))), revision)

    def __contains__(self, node: int) -> bool:
        k = bisect.bisect_right(self.ranges, (node, MAX_NODE + 1)) - 1
        return k >= 0 and self.ranges[k][0] <= node < self.ranges[k][1]

    def __len__(self) -> int:
        return sum(stop - start for start, stop in self.ranges)


MAX_STOP = MAX_NODE + 1  # a range's stop is one past its last node id, so node 2^63 - 1 can be listed


def node_ranges(nodes) -> tuple[tuple[int, int], ...]:
    """Sorted, distinct node ids as sorted, disjoint, non-touching half-open ranges [start, stop)."""
    ids = np.asarray(nodes, dtype=np.uint64)
    if not len(ids):
        return ()
    breaks = np.flatnonzero(np.diff(ids) != 1)
    starts, lasts = ids[np.r_[0, breaks + 1]].tolist(), ids[np.r_[breaks, len(ids) - 1]].tolist()
    return tuple((start, last + 1) for start, last in zip(starts, lasts))


def check_ranges(ranges, field: str) -> tuple[tuple[int, int], ...]:
    """`ranges` as a tuple if they are sorted, disjoint, non-touching [start, stop) with integer
    0 <= start < stop <= 2^63, else ProtocolError(field)."""
    ranges = tuple((start, stop) for start, stop in ranges)
    previous = -1
    for start, stop in ranges:
        check_count(start, field)
        if type(stop) is not int or not previous < start < stop <= MAX_STOP:
            raise ProtocolError(field, "must be sorted, disjoint, non-touching [start, stop) with start < stop <= 2^63")
        previous = stop
    return ranges


@dataclass(frozen=True, eq=False)
class MapQuery:
    """Occupancy of the axis-aligned box [lo, hi] in the fleet's world frame, on a grid of
    `resolution`; only from `robots` when given, else from every robot of the fleet."""

    fleet: str
    lo: np.ndarray  # (d,) min corner, metres
    hi: np.ndarray  # (d,) max corner, metres
    resolution: float
    robots: tuple[str, ...] | None = None

    def __post_init__(self):
        check_id(self.fleet, "fleet")
        lo = np.asarray(self.lo, dtype=np.float64)
        hi = np.asarray(self.hi, dtype=np.float64)
        if lo.shape not in ((2,), (3,)) or hi.shape != lo.shape:
            raise ProtocolError("bbox", f"lo and hi must both have 2 or 3 entries, got {lo.shape}, {hi.shape}")
        if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (lo < hi).all()):
            raise ProtocolError("bbox", "must be finite with lo < hi on every axis")
        resolution = _check_positive(self.resolution, "resolution")
        if self.robots is not None:
            robots = tuple(check_id(robot, "robots") for robot in self.robots)
            object.__setattr__(self, "robots", robots)
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)
        object.__setattr__(self, "resolution", resolution)

    @property
    def dim(self) -> int:
        return self.lo.shape[0]


@dataclass(frozen=True, eq=False)
class MapReply:
    """A probability grid: index [iy, ix] (2D) or [iz, iy, ix] (3D), cell centre
    origin + (index + 0.5) * resolution; 0.5 where nothing was observed."""

    fleet: str
    origin: np.ndarray  # (d,) min corner of the grid, metres, (x, y[, z])
    resolution: float
    probabilities: np.ndarray  # float32, shape (ny, nx) or (nz, ny, nx), values in [0, 1]

    def __post_init__(self):
        check_id(self.fleet, "fleet")
        origin = np.asarray(self.origin, dtype=np.float64)
        probabilities = np.asarray(self.probabilities, dtype=np.float32)
        if origin.shape not in ((2,), (3,)) or probabilities.ndim != origin.shape[0]:
            raise ProtocolError(
                "shape", f"origin {origin.shape} and grid {probabilities.shape} must share dimension 2 or 3"
            )
        if probabilities.size == 0:
            raise ProtocolError("shape", f"every extent must be >= 1, got {probabilities.shape}")
        if not np.isfinite(origin).all():
            raise ProtocolError("origin", "must be finite")
        resolution = _check_positive(self.resolution, "resolution")
        if not ((probabilities >= 0) & (probabilities <= 1)).all():  # also rejects NaN
            raise ProtocolError("probabilities", "must lie in [0, 1]")
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "resolution", resolution)
        object.__setattr__(self, "probabilities", probabilities)

    @property
    def dim(self) -> int:
        return self.origin.shape[0]


# How the map server evaluates a point query: analytic, the expected evidence of every component at
# the point's cell (the paper's Eq. 3-10); mc, Monte-Carlo grids of Eq. 11; auto, whichever the
# server measured cheaper for these points (services/api/points.py).
POINT_METHODS = ("auto", "analytic", "mc")
MAX_QUERY_POINTS = 10_000  # points in one point query (the HTTP API's limit too)


@dataclass(frozen=True, eq=False)
class PointQuery:
    """p(occupied) of the cell of size `resolution` centred on each of `points` (n, d) in the
    fleet's world frame, evaluated by `method` (one of POINT_METHODS); only from `robots` when
    given, else from every robot of the fleet."""

    fleet: str
    points: np.ndarray  # (n, d) metres, 1 <= n <= MAX_QUERY_POINTS, d 2 or 3
    resolution: float
    robots: tuple[str, ...] | None = None
    method: str = "auto"

    def __post_init__(self):
        check_id(self.fleet, "fleet")
        points = np.asarray(self.points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] not in (2, 3) or not 1 <= points.shape[0] <= MAX_QUERY_POINTS:
            raise ProtocolError(
                "points", f"must be 1 to {MAX_QUERY_POINTS:,} points of 2 or 3 coordinates, got shape {points.shape}"
            )
        if not np.isfinite(points).all():
            raise ProtocolError("points", "must be finite")
        resolution = _check_positive(self.resolution, "resolution")
        if self.method not in POINT_METHODS:
            raise ProtocolError("method", f"must be one of {', '.join(POINT_METHODS)}, got {self.method!r:.80}")
        if self.robots is not None:
            object.__setattr__(self, "robots", tuple(check_id(robot, "robots") for robot in self.robots))
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "resolution", resolution)

    @property
    def dim(self) -> int:
        return self.points.shape[1]


@dataclass(frozen=True, eq=False)
class PointReply:
    """The answer to a PointQuery: p(occupied) of each point's cell, in the query's order (0.5 where
    nothing was observed), and the `method` that evaluated them ("analytic" or "mc")."""

    fleet: str
    resolution: float
    probabilities: np.ndarray  # float32 (n,), values in [0, 1]
    method: str

    def __post_init__(self):
        check_id(self.fleet, "fleet")
        probabilities = np.asarray(self.probabilities, dtype=np.float32)
        if probabilities.ndim != 1 or not 1 <= probabilities.shape[0] <= MAX_QUERY_POINTS:
            raise ProtocolError("probabilities", f"must be 1 to {MAX_QUERY_POINTS:,} values, got {probabilities.shape}")
        if not ((probabilities >= 0) & (probabilities <= 1)).all():  # also rejects NaN
            raise ProtocolError("probabilities", "must lie in [0, 1]")
        if self.method not in POINT_METHODS[1:]:
            raise ProtocolError("method", f"must be analytic or mc, got {self.method!r:.80}")
        object.__setattr__(self, "resolution", _check_positive(self.resolution, "resolution"))
        object.__setattr__(self, "probabilities", probabilities)


Message = (
    ScanMessage | PoseGraphUpdate | Ack | MapQuery | MapReply | Rejection | StoreInventory | PointQuery | PointReply
)
