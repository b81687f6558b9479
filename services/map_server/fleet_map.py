"""The in-memory map of a fleet: every robot's scan models in their node frames, posed by a
per-robot pose graph, and occupancy reconstructed on demand for any region and resolution.

A pose-graph update changes node poses only: components and their cached samples stay in the
node frame and are moved by the world pose when traced (Eq. 2), never refitted.

A cached tile keeps its hit and miss counts and the (node, pose) pairs they hold. A new or
moved node only marks the tiles it can reach stale; the next query of such a tile traces the
difference: new nodes added, moved nodes subtracted at their old pose and added at the new
one. Counts are sums of quantised weights (gmm_core.sampling), exact in float64, so an updated
tile has the bytes a fresh reconstruction would have.
"""
from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from gmm_core import Grid, Pose, ScanModel
from gmm_core.occupancy import DEFAULT_PRIOR, map_estimate
from gmm_core.reconstruct import trace_groups
from gmm_core.sampling import scan_rays, scan_seed
from protocol import PoseGraphUpdate, ScanMessage
from services.host import cpu_cores

SAMPLE_CACHE_RAYS = 8_000_000  # node-frame samples kept across queries (about 300 MB)
TILE_CACHE_BYTES = 256 << 20  # counts and probabilities of cached tiles
SPLIT_MIN_NODES = 64  # nodes per thread below which an update is not split
SPLIT_MAX_CELLS = 1 << 22  # nor one whose grid is this large (each thread holds its own counts)


def local_reach(model: ScanModel) -> tuple[np.ndarray, np.ndarray]:
    """Node-frame box every ray of the scan stays in: sensor origin plus 3-sigma of all components."""
    lo, hi = model.origin.copy(), model.origin.copy()
    for mixture in (model.occupied, model.free):
        m_lo, m_hi = mixture.bounds(3.0)
        lo, hi = np.minimum(lo, m_lo), np.maximum(hi, m_hi)
    return lo, hi


def world_boxes(poses: Sequence[Pose], lo: np.ndarray, hi: np.ndarray,
                anchor: Pose | None = None) -> tuple[np.ndarray, np.ndarray]:
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


@dataclass
class Node:
    model: ScanModel
    estimate: Pose  # from the scan message, in the robot's map frame
    seed: int
    local_lo: np.ndarray
    local_hi: np.ndarray
    corrected: Pose | None = None  # from the newest pose-graph update
    pose_rev: int = 0  # bumped whenever `corrected` changes


@dataclass
class Robot:
    nodes: dict[int, Node] = field(default_factory=dict)
    pending: dict[int, Pose] = field(default_factory=dict)  # corrections for nodes not received yet
    anchor: Pose | None = None  # robot map frame -> world
    anchor_rev: int = 0  # bumped whenever `anchor` changes
    revision: int = -1
    bytes_received: int = 0
    last_seen: float = 0.0
    components: int = 0

    def world_pose(self, node: Node) -> Pose:
        pose = node.corrected or node.estimate
        return self.anchor.compose(pose) if self.anchor is not None else pose

    def stamp(self, node: Node) -> tuple[int, int]:
        """Changes whenever the node's world pose may have."""
        return node.pose_rev, self.anchor_rev


@dataclass
class Tile:
    """A cached query: counts of the nodes in `held`, and p(occupied) while nothing changed."""

    grid: Grid
    hits: np.ndarray  # float64, exact sums
    misses: np.ndarray
    held: dict = field(default_factory=dict)  # (robot, node) -> (stamp, node, world pose) counted in
    seen: int = 0  # entries of the FleetMap's change log that `held` accounts for
    changes: int = 0  # bumped when a new or moved node may reach the tile
    prob: np.ndarray | None = None
    prob_at: int = -1  # `changes` when `prob` was computed
    lock: threading.Lock = field(default_factory=threading.Lock)  # one update at a time

    @property
    def nbytes(self) -> int:
        return self.hits.nbytes + self.misses.nbytes + self.grid.n_cells * 4


@contextmanager
def _held(lock: threading.Lock):
    """Release a lock that is already acquired when the block ends."""
    try:
        yield
    finally:
        lock.release()


class NodeIndex:
    """World boxes of every node: a row appended as each scan arrives, rewritten when it moves."""

    def __init__(self, dim: int):
        self.keys: list[tuple[str, int]] = []
        self._rows: dict[tuple[str, int], int] = {}
        self._lo = np.empty((1024, dim))
        self._hi = np.empty((1024, dim))

    def put(self, keys: Sequence[tuple[str, int]], lo: np.ndarray, hi: np.ndarray) -> None:
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

    def reaching(self, lo: np.ndarray, hi: np.ndarray) -> list[tuple[str, int]]:
        """Keys of the nodes whose box meets the box (lo, hi)."""
        n = len(self.keys)
        meets = np.all(self._lo[:n] <= hi, axis=1) & np.all(self._hi[:n] >= lo, axis=1)
        return [self.keys[i] for i in np.flatnonzero(meets)]

    def meets(self, keys: Sequence[tuple[str, int]], lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Whether the box of each of `keys` meets the box (lo, hi)."""
        rows = np.fromiter((self._rows[k] for k in keys), dtype=np.int64, count=len(keys))
        return np.all(self._lo[rows] <= hi, axis=1) & np.all(self._hi[rows] >= lo, axis=1)

    def extent(self) -> tuple[np.ndarray, np.ndarray] | None:
        n = len(self.keys)
        return (self._lo[:n].min(axis=0), self._hi[:n].max(axis=0)) if n else None


class FleetMap:
    """Thread-safe. A short lock guards the state; tracing runs outside it (and outside the GIL),
    so ingest never waits behind a tile, and different tiles trace in parallel.

    Tiles are traced by a pool of `trace_threads` tracer threads (default: one per core). Not
    numba's threading layer: a server shares its cores with ingest, HTTP and often robots, and
    numba's OpenMP threads spin at every barrier: two of them on a busy 2-core machine traced
    6x slower than one (0.5 vs 3.1-3.7 M rays/s). (Tracers at nice +10 were tried: under a
    flood of HTTP requests they starved, and a lone large query waited minutes.)
    """

    def __init__(self, fleet: str, *, samples_per_cell: float = 4.0, prior: float = DEFAULT_PRIOR,
                 trace_threads: int | None = None):
        self.fleet = fleet
        self.trace_threads = max(1, trace_threads or cpu_cores())
        # All sampling and tracing runs here: at most trace_threads at once, so memory stays bounded
        # and ingest and HTTP keep a share of the cores however many clients ask for tiles.
        self._tracers = ThreadPoolExecutor(self.trace_threads, "gmmap-trace")
        self.samples_per_cell = samples_per_cell
        self.prior = prior
        self.dim: int | None = None
        self._robots: dict[str, Robot] = {}
        self._lock = threading.RLock()
        self._samples_lock = threading.Lock()
        self._index: NodeIndex | None = None  # from the first scan on
        self._log: list[tuple[str, int]] = []  # (robot, node) of every node added or moved, in order
        self._samples: OrderedDict = OrderedDict()
        self._sample_rays = 0
        self._tiles: OrderedDict[tuple, Tile] = OrderedDict()
        self._tile_bytes = 0
        self._tile_boxes: tuple[list[Tile], np.ndarray, np.ndarray] | None = None  # while the tile set is unchanged
        self._cache_hits = 0
        self._cache_misses = 0
        self._cache_updates = 0
        self._cache_stale = 0  # answered with the previous tile while it was being updated

    # -- ingest ---------------------------------------------------------------------------
    def add_scan(self, msg: ScanMessage, size_bytes: int = 0) -> bool:
        """Hold a scan; False if (robot, node) is already held (a resend)."""
        with self._lock:
            if self.dim is None:
                self.dim = msg.dim
                self._index = NodeIndex(msg.dim)
            elif msg.dim != self.dim:
                raise ValueError(f"dimension: this map is {self.dim}D, the scan is {msg.dim}D")
            robot = self._robots.setdefault(msg.robot, Robot())
            robot.last_seen = time.time()
            robot.bytes_received += size_bytes
            if msg.node in robot.nodes:
                return False
            lo, hi = local_reach(msg.model)
            node = Node(msg.model, msg.pose, scan_seed(msg.robot, msg.node), lo, hi,
                        corrected=robot.pending.pop(msg.node, None))
            robot.nodes[msg.node] = node
            robot.components += msg.model.n_components
            world_lo, world_hi = world_boxes([node.corrected or node.estimate], lo[None], hi[None], robot.anchor)
            self._index.put([(msg.robot, msg.node)], world_lo, world_hi)
            self._log.append((msg.robot, msg.node))
            self._changed(world_lo, world_hi)
            return True

    def apply_poses(self, update: PoseGraphUpdate) -> bool:
        """Re-pose nodes (Eq. 2 at query time); False if the revision is older than the held one.

        An update with the held revision is applied too: a large revision may come in parts.
        """
        with self._lock:
            if self.dim is not None and any(p.dim != self.dim for _, p in update.poses):
                raise ValueError(f"poses: this map is {self.dim}D")
            robot = self._robots.setdefault(update.robot, Robot())
            robot.last_seen = time.time()
            if update.revision < robot.revision:
                return False
            if update.anchor is not None:
                moved = list(robot.nodes.values())  # a new anchor moves every node of the robot
                robot.anchor, old_anchor = update.anchor, robot.anchor
                robot.anchor_rev += 1
            else:
                moved, old_anchor = [], robot.anchor
            old_poses = {id(n): n.corrected or n.estimate for n in moved}
            for node_id, pose in update.poses:
                node = robot.nodes.get(node_id)
                if node is None:
                    robot.pending[node_id] = pose  # its scan is still on the way
                elif node.corrected is None or not (np.array_equal(node.corrected.R, pose.R)
                                                    and np.array_equal(node.corrected.t, pose.t)):
                    old_poses.setdefault(id(node), node.corrected or node.estimate)
                    node.corrected = pose
                    node.pose_rev += 1
                    moved.append(node)
            robot.revision = update.revision
            moved = list({id(n): n for n in moved}.values())
            if moved:
                lo = np.array([n.local_lo for n in moved])
                hi = np.array([n.local_hi for n in moved])
                old_lo, old_hi = world_boxes([old_poses[id(n)] for n in moved], lo, hi, old_anchor)
                new_lo, new_hi = world_boxes([n.corrected or n.estimate for n in moved], lo, hi, robot.anchor)
                ids = {id(node): node_id for node_id, node in robot.nodes.items()}
                keys = [(update.robot, ids[id(n)]) for n in moved]
                self._index.put(keys, new_lo, new_hi)
                self._log.extend(keys)
                self._changed(np.concatenate([old_lo, new_lo]), np.concatenate([old_hi, new_hi]))
            return True

    def _changed(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Mark stale every cached tile that one of the boxes (lo, hi) reaches."""
        if self._tile_boxes is None:
            tiles = list(self._tiles.values())
            d = self.dim or 2
            self._tile_boxes = (tiles, np.array([t.grid.origin for t in tiles]).reshape(-1, d),
                                np.array([t.grid.upper for t in tiles]).reshape(-1, d))
        tiles, tiles_lo, tiles_hi = self._tile_boxes
        reached = np.any(np.all(lo[:, None] <= tiles_hi[None], axis=2) & np.all(hi[:, None] >= tiles_lo[None], axis=2),
                         axis=0)
        for i in np.flatnonzero(reached):
            tiles[i].changes += 1

    # -- queries --------------------------------------------------------------------------
    def _node_rays(self, robot: str, node_id: int, node: Node, resolution: float):
        """Node-frame samples for this resolution, drawn once and kept (deterministic by seed)."""
        key = (robot, node_id, resolution)
        with self._samples_lock:
            rays = self._samples.get(key)
            if rays is not None:
                self._samples.move_to_end(key)
                return rays
        rays = scan_rays(node.model, resolution, node.seed, self.samples_per_cell)  # the same in every thread
        with self._samples_lock:
            if key not in self._samples:
                self._samples[key] = rays
                self._sample_rays += len(rays[0])
            while self._sample_rays > SAMPLE_CACHE_RAYS and len(self._samples) > 1:
                _, old = self._samples.popitem(last=False)
                self._sample_rays -= len(old[0])
        return rays

    def _reaching(self, grid: Grid, robots: Sequence[str] | None) -> dict:
        """(robot, node) -> (stamp, node, world pose) of every node that can reach `grid`. Under the lock."""
        self._check_dim(grid)
        if self._index is None:
            return {}
        wanted = None if robots is None else set(robots)
        return {key: self._posed(key) for key in self._index.reaching(grid.origin, grid.upper)
                if wanted is None or key[0] in wanted}

    def _changed_since(self, seen: int, grid: Grid, robots: Sequence[str] | None) -> dict:
        """Nodes added or moved since change-log entry `seen`: (robot, node) -> (stamp, node, world pose)
        where the node can reach `grid` now, else None. Under the lock.

        A tile update costs what changed since the last one, not what the map holds.
        """
        keys = list(dict.fromkeys(self._log[seen:]))
        if robots is not None:
            wanted = set(robots)
            keys = [k for k in keys if k[0] in wanted]
        if not keys:
            return {}
        return {key: self._posed(key) if reaches else None
                for key, reaches in zip(keys, self._index.meets(keys, grid.origin, grid.upper))}

    def _posed(self, key: tuple[str, int]) -> tuple[tuple[int, int], Node, Pose]:
        """(stamp, node, world pose) of node `key` now. Under the lock."""
        robot = self._robots[key[0]]
        node = robot.nodes[key[1]]
        return robot.stamp(node), node, robot.world_pose(node)

    def _check_dim(self, grid: Grid) -> None:
        if self.dim is not None and grid.dim != self.dim:
            raise ValueError(f"bbox: this map is {self.dim}D, the query is {grid.dim}D")

    def _trace(self, grid: Grid, plus: list, minus: list) -> tuple[np.ndarray, np.ndarray]:
        """Exact float64 counts of the nodes in `plus` less those in `minus`: ((robot, node), node, pose) each.

        Traced by the map's tracer threads: a large update split among them, each running the
        one-thread kernel on its share of the nodes (counts are sums of quantised weights, exact
        in any order, so the split changes no bit).
        """
        entries = [(1.0, entry) for entry in plus] + [(-1.0, entry) for entry in minus]
        parts = min(self.trace_threads, max(1, len(entries) // SPLIT_MIN_NODES))
        if grid.n_cells > SPLIT_MAX_CELLS:
            parts = 1
        shares = [self._tracers.submit(self._trace_part, grid, entries[i::parts]) for i in range(parts)]
        hits, misses = shares[0].result()
        for share in shares[1:]:
            h, m = share.result()
            hits += h
            misses += m
        return hits, misses

    def _trace_part(self, grid: Grid, entries: list) -> tuple[np.ndarray, np.ndarray]:
        def groups():
            for sign, ((name, node_id), node, pose) in entries:
                ends, weights, is_hit = self._node_rays(name, node_id, node, grid.resolution)
                if len(ends):
                    yield pose.apply(node.model.origin[None])[0], pose.apply(ends), sign * weights, is_hit

        return trace_groups(grid, groups(), None, dtype=np.float64, threads=1)

    def counts(self, grid: Grid, robots: Sequence[str] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Hit and miss evidence (float32) on `grid` from the nodes that can reach it (all robots or `robots`)."""
        with self._lock:  # a snapshot of the reaching nodes and their world poses
            posed = self._reaching(grid, robots)
        hits, misses = self._trace(grid, [(key, node, pose) for key, (_, node, pose) in posed.items()], [])
        return hits.astype(np.float32), misses.astype(np.float32)

    def occupancy(self, grid: Grid, robots: Sequence[str] | None = None) -> np.ndarray:
        """p(occupied) on `grid`, Eq. 11; cached, and brought up to date by tracing only what changed.

        While one request updates a tile, concurrent requests for it are answered with the tile as
        it was before that update (when there is one) rather than queue behind it: a viewer polling
        a busy map gets its tiles at once, one update late at most. A lone query always sees every
        change applied before it.
        """
        key = (tuple(grid.origin), grid.resolution, grid.shape, None if robots is None else tuple(sorted(robots)))
        with self._lock:
            self._check_dim(grid)
            tile = self._tiles.get(key)
            if tile is None:
                tile = Tile(grid, np.zeros(grid.array_shape), np.zeros(grid.array_shape))
                self._tiles[key] = tile
                self._tile_bytes += tile.nbytes
                self._tile_boxes = None
                self._evict()
            self._tiles.move_to_end(key)
        if not tile.lock.acquire(blocking=False):
            with self._lock:
                previous = tile.prob
                if previous is not None:
                    self._cache_stale += 1
                    return previous
            tile.lock.acquire()
        with _held(tile.lock):
            with self._lock:
                if tile.prob_at == tile.changes:
                    self._cache_hits += 1
                    return tile.prob
                changes, seen, first = tile.changes, len(self._log), tile.prob is None
                posed = self._changed_since(tile.seen, grid, robots)
            held = tile.held
            moved = {k for k in posed if k in held and (posed[k] is None or posed[k][0] != held[k][0])}
            new = [(k, *posed[k][1:]) for k in posed
                   if posed[k] is not None and (k not in held or held[k][0] != posed[k][0])]
            stale = [(k, *held[k][1:]) for k in moved]  # counted at their old pose: subtracted
            if new or stale:
                # Updating traces new + moved nodes, afresh traces new + unmoved ones: update unless
                # most of the tile moved (a big correction).
                if 2 * len(moved) <= len(held):
                    hits, misses = self._trace(grid, new, stale)
                    tile.hits += hits  # only after the trace succeeded: a failed one leaves the tile as it was
                    tile.misses += misses
                else:
                    kept = [(k, *v[1:]) for k, v in held.items() if k not in moved]
                    tile.hits, tile.misses = self._trace(grid, kept + new, [])
                for k in moved:
                    del held[k]
                held.update((k, posed[k]) for k, *_ in new)
            tile.seen = seen
            prob = map_estimate(tile.hits.astype(np.float32), tile.misses.astype(np.float32), self.prior)
            prob.setflags(write=False)
            with self._lock:
                # A change after the snapshot bumped `changes`: the next query updates again.
                tile.prob, tile.prob_at = prob, changes
                if first:
                    self._cache_misses += 1
                else:
                    self._cache_updates += 1
            return prob

    def _evict(self) -> None:
        """Drop least recently used tiles over TILE_CACHE_BYTES (always keeping the newest)."""
        while self._tile_bytes > TILE_CACHE_BYTES and len(self._tiles) > 1:
            _, old = self._tiles.popitem(last=False)
            self._tile_bytes -= old.nbytes
            self._tile_boxes = None

    def cache_stats(self) -> dict:
        with self._lock:
            return {"hits": self._cache_hits, "misses": self._cache_misses, "updates": self._cache_updates,
                    "stale": self._cache_stale,
                    "tiles": len(self._tiles), "tile_bytes": self._tile_bytes, "sample_rays": self._sample_rays}

    def robots(self) -> list[dict]:
        with self._lock:
            return [{"robot": name, "nodes": len(r.nodes), "components": r.components,
                     "bytes_received": r.bytes_received, "last_seen": r.last_seen, "pose_revision": r.revision}
                    for name, r in sorted(self._robots.items())]

    def trajectory(self, robot: str) -> np.ndarray:
        """World positions of the robot's sensor origins, in node order."""
        with self._lock:
            r = self._robots.get(robot)
            if r is None or not r.nodes:
                return np.zeros((0, self.dim or 2))
            return np.array([r.world_pose(n).apply(n.model.origin[None])[0]
                             for _, n in sorted(r.nodes.items())])

    def extent(self) -> tuple[np.ndarray, np.ndarray] | None:
        """World box of every node's reach, or None for an empty map."""
        with self._lock:
            return self._index.extent() if self._index is not None else None
