"""The node store of a fleet map: every robot's scan models in their node frames, the pose graph
that places them (Eq. 2, applied at query time), a spatial index of their world boxes, and the
change log a cached tile reads to learn what moved since it was traced.

Held for a whole shift, so held compactly: a server's node holds neither its model nor the scan
message's bytes (about 1 KB in 2D, several in 3D) but reads them from the store when its samples
are drawn (samples.SampleCache, itself bounded); without a store a node keeps the wire bytes,
several times smaller than the decoded model. A node's world pose is made once per pose change and
shared by every tile that counts it; the change log keeps each node once, at its latest change.

Not thread-safe: the FleetMap calls it under its lock.
"""

from __future__ import annotations

import bisect
import itertools
import math
import time
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from gmm_core import Grid, Pose, ScanModel
from gmm_core.sampling import sample_bounds, scan_seed
from protocol import PoseGraphUpdate, ScanMessage

from .pose_graph import PoseGraph

CHANGE_LOG_LIMIT = 1 << 20  # entries (8 bytes each) kept for tiles that are not asked for again
BATCH_TIMES_LIMIT = 4096  # times of change-log batches kept (ChangeLog.time_of), however long the shift


class NodeKey(NamedTuple):
    """Which node: one scan of one robot."""

    robot: str
    node: int  # the scan's node id, as the robot numbers them


class Stamp(NamedTuple):
    """Changes whenever a node's world pose may have: equal stamps, equal poses."""

    pose_changes: int  # of the node's corrected pose so far
    anchor_changes: int  # of its robot's anchor so far


def local_reach(model: ScanModel) -> tuple[np.ndarray, np.ndarray]:
    """Node-frame box every ray of the scan stays in: sensor origin plus every sample's box
    (gmm_core.sampling.sample_bounds), so a node whose box misses a tile adds nothing to it."""
    lo, hi = model.origin.copy(), model.origin.copy()
    for mixture in (model.occupied, model.free):
        m_lo, m_hi = sample_bounds(mixture)
        lo, hi = np.minimum(lo, m_lo), np.maximum(hi, m_hi)
    return lo, hi


class ScanEntry(NamedTuple):
    """What the node store holds of a scan: made from a decoded message (`of`), or read back from a
    store's row without decoding the model (a restart: Store.load)."""

    robot: str
    node: int
    pose: Pose  # the scan's own estimate, robot map frame (the node's pose until a correction)
    origin: np.ndarray  # (d,) sensor origin in the node frame
    local_lo: np.ndarray  # node-frame box of its rays (local_reach), metres
    local_hi: np.ndarray
    components: int
    size: int  # bytes on the wire
    raw: bytes | None  # the ScanMessage as received; None: `model` holds it
    model: ScanModel | None = None

    @property
    def dim(self) -> int:
        return self.pose.dim

    @staticmethod
    def of(msg: ScanMessage, size: int = 0, raw: bytes | None = None) -> ScanEntry:
        lo, hi = local_reach(msg.model)
        held = None if raw is None else bytes(raw)
        model = msg.model if raw is None else None
        return ScanEntry(
            msg.robot, msg.node, msg.pose, msg.model.origin, lo, hi, msg.model.n_components, size, held, model
        )


def world_boxes(
    poses: Sequence[Pose], lo: np.ndarray, hi: np.ndarray, anchor: Pose | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned boxes (n, d) around n node-frame boxes, each moved by anchor ∘ its pose."""
    if not poses:
        return np.zeros((0, lo.shape[-1])), np.zeros((0, lo.shape[-1]))
    R = np.array([p.R for p in poses])
    t = np.array([p.t for p in poses])
    if anchor is not None:
        R, t = anchor.R @ R, t @ anchor.R.T + anchor.t
    # Moving a box: centre by the pose, half-extent by |R| (the tight bound on every corner).
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    moved = np.einsum("nij,nj->ni", R, centre) + t
    reach = np.einsum("nij,nj->ni", np.abs(R), half)
    return moved - reach, moved + reach


@dataclass(slots=True, eq=False)
class Node:
    """One scan as the map holds it: its model stays in the node frame, only its pose changes."""

    key: NodeKey
    raw: bytes | None  # the ScanMessage as received, holding the model; None: `held_model` or the store
    held_model: ScanModel | None  # None: `raw` holds it, or the store (samples.SampleCache.model)
    origin: np.ndarray  # (d,) sensor origin in the node frame (the model's)
    map_pose: Pose  # in the robot's map frame: the newest correction, else the scan's own estimate
    seed: int  # of its samples: scan_seed(robot, node)
    local_lo: np.ndarray  # node-frame box of its rays (local_reach), metres
    local_hi: np.ndarray
    reach: float  # how far from the node frame's origin its rays reach at most (the box's far corner), metres
    pose_changes: int = 0  # bumped whenever a correction sets `map_pose`
    posed: Posed | None = None  # where it stood when last asked (Robot.posed), shared by the tiles counting it


class Posed(NamedTuple):
    """A node where it stands at one moment: what a tile counts in, and what it takes out again."""

    key: NodeKey
    stamp: Stamp  # of `pose`
    node: Node
    pose: Pose  # node frame -> world
    samples_per_cell: float | None = None  # what a tile counts it at; None: the map's (tile_updates.py, under load)

    def counted_with(self, samples_per_cell: float | None) -> Posed:
        """The node as a tile counts it with `samples_per_cell` (None: the map's); itself if so already."""
        if samples_per_cell == self.samples_per_cell:
            return self
        return Posed(self.key, self.stamp, self.node, self.pose, samples_per_cell)


@dataclass
class Robot:
    """One robot's nodes, its pose graph's corrections and anchor, and what the API reports of it."""

    nodes: dict[int, Node] = field(default_factory=dict)
    # Corrections by revision, of held nodes and of those whose scan is still on the way, and the anchor.
    graph: PoseGraph = field(default_factory=PoseGraph)
    anchor_changes: int = 0  # bumped whenever the anchor changes
    bytes_received: int = 0  # wire bytes of its scans
    last_seen: float = 0.0  # time.time() of its newest message (after a restart: the newest stored)
    components: int = 0  # of all its scan models

    @property
    def anchor(self) -> Pose | None:
        """Robot map frame -> world."""
        return self.graph.anchor

    @property
    def revision(self) -> int | None:
        """The newest pose-graph revision applied; None before any (as a store inventory says it)."""
        return self.graph.revision if self.graph.revision >= 0 else None

    def world_pose(self, node: Node) -> Pose:
        return self.anchor.compose(node.map_pose) if self.anchor is not None else node.map_pose

    def posed(self, node: Node) -> Posed:
        """The node where it stands now: made once per change of its pose or of the anchor."""
        stamp = Stamp(node.pose_changes, self.anchor_changes)
        if node.posed is None or node.posed.stamp != stamp:
            node.posed = Posed(node.key, stamp, node, self.world_pose(node))
        return node.posed


class NodeIndex:
    """World boxes of every node: a row appended as each scan arrives, rewritten when it moves."""

    def __init__(self, dim: int):
        self.keys: list[NodeKey] = []
        self._rows: dict[NodeKey, int] = {}
        self._lo = np.empty((1024, dim))
        self._hi = np.empty((1024, dim))

    def put(self, keys: Sequence[NodeKey], lo: np.ndarray, hi: np.ndarray) -> None:
        rows = np.empty(len(keys), dtype=np.int64)
        for i, key in enumerate(keys):
            row = self._rows.get(key)
            if row is None:
                row = self._rows[key] = len(self.keys)
                self.keys.append(key)
            rows[i] = row
        if len(self.keys) > len(self._lo):
            grow = ((0, len(self._lo)), (0, 0))
            self._lo, self._hi = np.pad(self._lo, grow), np.pad(self._hi, grow)
        self._lo[rows], self._hi[rows] = lo, hi

    def reaching(self, lo: np.ndarray, hi: np.ndarray) -> list[NodeKey]:
        """Keys of the nodes whose box meets the box (lo, hi), in the order they arrived."""
        n = len(self.keys)
        meets = np.all(self._lo[:n] <= hi, axis=1) & np.all(self._hi[:n] >= lo, axis=1)
        return [self.keys[i] for i in np.flatnonzero(meets)]

    def meets(self, keys: Sequence[NodeKey], lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Whether the box of each of `keys` meets the box (lo, hi)."""
        rows = np.fromiter((self._rows[k] for k in keys), dtype=np.int64, count=len(keys))
        return np.all(self._lo[rows] <= hi, axis=1) & np.all(self._hi[rows] >= lo, axis=1)

    def extent(self, robots: Collection[str] | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """The box of every node's box (of all robots or of `robots`), or None when there is none."""
        n = len(self.keys)
        rows = np.arange(n) if robots is None else np.flatnonzero([k.robot in robots for k in self.keys])
        return (self._lo[rows].min(axis=0), self._hi[rows].max(axis=0)) if len(rows) else None


class ChangeLog:
    """The nodes added or moved, each once at the position of its latest change, oldest first.

    Compacted as it goes: a node logged again moves to the end, so the log never holds more
    entries than there are nodes, however often they move. A position counts every change ever
    logged, so it stays valid when entries are dropped; `start` is the oldest position for which
    `since` still answers (changes before it may have been dropped)."""

    def __init__(self):
        self._latest: dict[NodeKey, int] = {}  # key -> position of its latest change, in position order
        self.start = 0
        self.end = 0  # the position the next change will have
        self._batches: list[tuple[int, float]] = []  # (first position, monotonic time) of each `extend`

    def __len__(self) -> int:
        return len(self._latest)

    def extend(self, keys: Iterable[NodeKey]) -> None:
        latest = self._latest
        self._batches.append((self.end, time.monotonic()))
        if len(self._batches) > BATCH_TIMES_LIMIT:  # no tile drops them (none asked for): every other one
            self._batches = self._batches[::2]  # goes, so `time_of` answers an earlier time, never a later one
        for key in keys:
            latest.pop(key, None)
            latest[key] = self.end
            self.end += 1
        if len(latest) > CHANGE_LOG_LIMIT:  # down to half: one O(length) drop per LIMIT / 2 entries
            self.drop_before(next(itertools.islice(latest.values(), len(latest) - CHANGE_LOG_LIMIT // 2, None)))

    def since(self, position: int) -> list[NodeKey]:
        """Each key changed at `position` or later, once, newest change first."""
        if position < self.start:
            raise ValueError(f"change log position {position} was dropped (the log starts at {self.start})")
        keys = []
        for key in reversed(self._latest):
            if self._latest[key] < position:
                break
            keys.append(key)
        return keys

    def oldest_since(self, position: int, limit: int | None) -> tuple[list[NodeKey], int]:
        """`since`, but at most the `limit` keys changed longest ago (None: all), and the position up
        to which they account for every change: `end`, or that of the first change they leave out."""
        keys = self.since(position)
        if limit is None or len(keys) <= limit:
            return keys, self.end
        return keys[len(keys) - limit :], self._latest[keys[len(keys) - limit - 1]]

    def time_of(self, position: int) -> float:
        """Monotonic time at which the change at `position` (< end) was logged."""
        return self._batches[bisect.bisect_right(self._batches, (position, math.inf)) - 1][1]

    def drop_before(self, position: int) -> None:
        latest = self._latest
        while latest:
            key = next(iter(latest))
            if latest[key] >= position:
                break
            del latest[key]
        self.start = max(self.start, position)
        first = bisect.bisect_right(self._batches, (self.start, math.inf)) - 1  # the batch holding `start`
        if first > 0:
            del self._batches[:first]


class NodeStore:
    """The nodes of every robot of a fleet, their poses, their boxes and the log of their changes.

    `moved(lo, hi)` is called with the world boxes (n, d) that new or moved nodes entered or left.
    """

    def __init__(self, moved: Callable[[np.ndarray, np.ndarray], None], hold_models: bool = True):
        self._moved = moved
        self.hold_models = hold_models  # False: a store holds every scan's bytes, nodes keep neither
        self.dim: int | None = None  # of the first scan: a map is 2D or 3D for good
        self.robots: dict[str, Robot] = {}
        self.log = ChangeLog()
        self._index: NodeIndex | None = None  # from the first scan on

    def add(self, msg: ScanMessage, size_bytes: int = 0, raw: bytes | None = None) -> bool:
        """Hold a scan; False if (robot, node) is already held (a resend). `raw`: `msg` as received,
        held instead of the decoded model."""
        return self.add_many([ScanEntry.of(msg, size_bytes, raw)])[0]

    def add_many(self, entries: Sequence[ScanEntry]) -> list[bool]:
        """Hold each scan as `add`; whether each was new.

        One ingest batch at a time: the new nodes' world boxes are made per robot, and the index,
        the change log and the tiles are told once for the whole batch.
        """
        dim = self.dim if self.dim is not None or not entries else entries[0].dim
        for entry in entries:  # all of the batch or none of it: a scan held here is indexed below
            if entry.dim != dim:
                held = f"this map is {dim}D" if self.dim is not None else f"the batch's first scan is {dim}D"
                raise ValueError(f"dimension: {held}, the scan is {entry.dim}D")
        if self.dim is None and entries:
            self.dim = dim
            self._index = NodeIndex(dim)
        added: dict[str, list[Node]] = {}
        new = []
        for entry in entries:
            robot = self.robots.setdefault(entry.robot, Robot())
            robot.last_seen = time.time()
            robot.bytes_received += entry.size
            new.append(entry.node not in robot.nodes)
            if not new[-1]:
                continue
            lo, hi = entry.local_lo, entry.local_hi
            node = Node(
                NodeKey(entry.robot, entry.node),
                entry.raw if self.hold_models else None,
                entry.model if self.hold_models else None,
                entry.origin,
                robot.graph.pose(entry.node) or entry.pose,  # a correction that came before its scan, else its estimate
                scan_seed(entry.robot, entry.node),
                lo,
                hi,
                float(np.linalg.norm(np.maximum(np.abs(lo), np.abs(hi)))),
            )
            robot.nodes[entry.node] = node
            robot.components += entry.components
            added.setdefault(entry.robot, []).append(node)
        if added:
            boxes = [
                world_boxes(
                    [n.map_pose for n in nodes],
                    np.array([n.local_lo for n in nodes]),
                    np.array([n.local_hi for n in nodes]),
                    self.robots[name].anchor,
                )
                for name, nodes in added.items()
            ]
            keys = [n.key for nodes in added.values() for n in nodes]
            world_lo, world_hi = np.concatenate([b[0] for b in boxes]), np.concatenate([b[1] for b in boxes])
            self._index.put(keys, world_lo, world_hi)
            self.log.extend(keys)
            self._moved(world_lo, world_hi)
        return new

    def apply(self, update: PoseGraphUpdate) -> bool:
        """Re-pose nodes (Eq. 2 at query time), node by node: each listed node that no newer revision
        set takes its pose, the anchor likewise (pose_graph.PoseGraph.apply). True if anything changed.

        Only the nodes whose world pose changed are moved (logged, re-indexed, their tiles marked).
        """
        if self.dim is not None and update.dim != self.dim:
            raise ValueError(f"poses: this map is {self.dim}D")
        robot = self.robots.setdefault(update.robot, Robot())
        robot.last_seen = time.time()
        old_anchor = robot.anchor
        applied = robot.graph.apply(update)
        moved = list(robot.nodes.values()) if applied.anchor_moved else []  # an anchor moves the whole robot
        robot.anchor_changes += applied.anchor_moved
        old_poses = {n.key: n.map_pose for n in moved}
        for node_id in applied.moved:
            node = robot.nodes.get(node_id)
            if node is not None:  # else its scan is still on the way: `add` takes the correction
                old_poses.setdefault(node.key, node.map_pose)
                node.map_pose = robot.graph.pose(node_id)
                node.pose_changes += 1
                moved.append(node)
        moved = list({n.key: n for n in moved}.values())
        if not moved:
            return applied.changed
        lo = np.array([n.local_lo for n in moved])
        hi = np.array([n.local_hi for n in moved])
        old_lo, old_hi = world_boxes([old_poses[n.key] for n in moved], lo, hi, old_anchor)
        new_lo, new_hi = world_boxes([n.map_pose for n in moved], lo, hi, robot.anchor)
        keys = [n.key for n in moved]
        self._index.put(keys, new_lo, new_hi)
        self.log.extend(keys)
        self._moved(np.concatenate([old_lo, new_lo]), np.concatenate([old_hi, new_hi]))
        return applied.changed

    def check_dim(self, grid: Grid) -> None:
        if self.dim is not None and grid.dim != self.dim:
            raise ValueError(f"bbox: this map is {self.dim}D, the query is {grid.dim}D")

    def posed(self, key: NodeKey) -> Posed:
        """Node `key` where it stands now."""
        robot = self.robots[key.robot]
        return robot.posed(robot.nodes[key.node])

    def reaching(self, grid: Grid, robots: Sequence[str] | None) -> dict[NodeKey, Posed]:
        """Every node (of all robots or of `robots`) that can reach `grid` now."""
        self.check_dim(grid)
        if self._index is None:
            return {}
        wanted = None if robots is None else set(robots)
        return {
            key: self.posed(key)
            for key in self._index.reaching(grid.origin, grid.upper)
            if wanted is None or key.robot in wanted
        }

    def changed_since(
        self, position: int, grid: Grid, robots: Sequence[str] | None, limit: int | None = None
    ) -> tuple[dict[NodeKey, Posed | None], int]:
        """Nodes (of all robots or of `robots`) added or moved from change-log `position` on: where
        they stand now if they can reach `grid`, else None; and the log position up to which they
        account for every change (ChangeLog.oldest_since: at most `limit` nodes, the longest changed).

        A tile update costs what changed since the last one, not what the map holds.
        """
        keys, upto = self.log.oldest_since(position, limit)
        if robots is not None:
            wanted = set(robots)
            keys = [k for k in keys if k.robot in wanted]
        if not keys:
            return {}, upto
        meets = self._index.meets(keys, grid.origin, grid.upper)
        return {key: self.posed(key) if reaches else None for key, reaches in zip(keys, meets)}, upto

    def robot_rows(self) -> list[dict]:
        return [
            {
                "robot": name,
                "nodes": len(r.nodes),
                "components": r.components,
                "bytes_received": r.bytes_received,
                "last_seen": r.last_seen,
                "pose_revision": r.revision,
            }
            for name, r in sorted(self.robots.items())
        ]

    def trajectory(self, robot: str) -> np.ndarray:
        """World positions of the robot's sensor origins, in node order."""
        r = self.robots.get(robot)
        if r is None or not r.nodes:
            return np.zeros((0, self.dim or 2))
        return np.array([r.world_pose(n).apply(n.origin[None])[0] for _, n in sorted(r.nodes.items())])

    def world_poses(self, robot: str) -> list[tuple[int, Pose]]:
        """(node, world pose of its sensor) of the robot's nodes, in node order."""
        r = self.robots.get(robot)
        return [] if r is None else [(k, r.world_pose(n)) for k, n in sorted(r.nodes.items())]

    def extent(self, robots: Collection[str] | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """World box of every node's reach (of all robots or of `robots`), or None when there is none."""
        return self._index.extent(robots) if self._index is not None else None
