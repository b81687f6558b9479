"""The in-memory map of a fleet: every robot's scan models in their node frames, posed by a
per-robot pose graph, and occupancy reconstructed on demand for any region and resolution.

A pose-graph update changes node poses only: components and their cached samples stay in the
node frame and are moved by the world pose when traced (Eq. 2), never refitted.

FleetMap is the facade the API, ingest and server use; the work is done by its parts:
nodes.NodeStore (nodes, pose graphs, spatial index, change log), samples.SampleCache,
tiles.TileCache (the incremental tile update) and tracers.TracerPool.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Collection, Mapping, Sequence
from pathlib import Path

import numpy as np

from gmm_core import Grid, Pose, ScanModel
from gmm_core.analytic.components import NodeComponents
from gmm_core.occupancy import DEFAULT_PRIOR
from gmm_core.reconstruct import ReconstructionConfig
from gmm_core.sampling import scan_seed
from protocol import PoseGraphUpdate, ScanMessage
from services.host import cpu_cores

from .nodes import NodeKey, NodeStore, ScanEntry
from .samples import SampleCache
from .tile_state import TileAnswer
from .tiles import MAX_STALE_S, TileCache
from .tracers import TracerPool


class FleetMap:
    """Thread-safe. A short lock guards the state; tracing runs outside it (and outside the GIL),
    so ingest never waits behind a tile, and different tiles trace in parallel.

    Tiles are traced by a pool of `trace_threads` tracer threads (default: one per core; see
    tracers.py for why not numba's threading layer).
    """

    def __init__(
        self,
        fleet: str,
        *,
        samples_per_cell: float = ReconstructionConfig.samples_per_cell,
        prior: float = DEFAULT_PRIOR,
        trace_threads: int | None = None,
        busy_samples_per_cell: float | Mapping[int, float] | None = None,
        stored_bytes: Callable[[NodeKey], bytes] | None = None,
        trace_store: Path | None = None,
        report_slow_updates: bool = True,
    ):
        """stored_bytes: a scan's message as a store holds it (Store.reader); given, nodes hold neither
        their models nor their bytes (a server keeps a shift's scans: nodes.py).
        busy_samples_per_cell: what tile updates begun while any tracer has work trace new and moved
        nodes with, one for all grids or one by dimension (tile_updates.py); None: always `samples_per_cell`.
        trace_store: the file of the store `stored_bytes` reads, to trace in a process per tracer
        thread reading the nodes from it (tracers.py); None: in the tracer threads.
        report_slow_updates: log tile updates over tile_updates.SLOW_UPDATE_S (a throwaway map logs none)."""
        self.fleet = fleet
        self.trace_threads = max(1, trace_threads or cpu_cores())
        self.samples_per_cell = samples_per_cell
        self.prior = prior
        self._lock = threading.RLock()
        self._samples = SampleCache(samples_per_cell, stored_bytes)
        self._tracers = TracerPool(
            self.trace_threads, self._samples, None if trace_store is None else (Path(trace_store), fleet)
        )
        self._prime = trace_store is None  # tracer processes keep samplers of their own
        self._nodes = NodeStore(lambda lo, hi: self._tiles.mark_stale(lo, hi), hold_models=stored_bytes is None)
        self._tiles = TileCache(
            self._lock, self._nodes, self._tracers, prior, samples_per_cell, busy_samples_per_cell, report_slow_updates
        )

    @property
    def dim(self) -> int | None:
        """2 or 3 from the first scan on; None for an empty map."""
        return self._nodes.dim

    # -- ingest ---------------------------------------------------------------------------
    def close(self) -> None:
        """Stop tracing (a server that is stopping); queries after this fail."""
        self._tiles.close()
        self._tracers.close()

    def ingest_first(self):
        """A context in which the tracers wait at their next node: ingest runs a batch first."""
        return self._tracers.ingest_first()

    def add_scan(self, msg: ScanMessage, size_bytes: int = 0, raw: bytes | None = None) -> bool:
        """Hold a scan; False if (robot, node) is already held (a resend). `raw`: `msg` as received,
        held instead of its decoded model (a server holds every scan of a shift: nodes.py)."""
        with self._lock:
            return self._nodes.add(msg, size_bytes, raw)

    def add_scans(self, scans: Sequence[tuple[ScanMessage, int, bytes | None]]) -> list[bool]:
        """Hold each (message, wire size, raw bytes or None) of an ingest batch; whether each was new."""
        return self.add_entries([ScanEntry.of(*scan) for scan in scans])

    def add_entries(self, entries: Sequence[ScanEntry], models: Sequence[ScanModel] | None = None) -> list[bool]:
        """Hold each scan of a batch as the node store keeps it (a restart reads them so); whether each
        was new. `models`: the entries' models where the caller decoded them (ingest): the new nodes'
        samples are made ready from them, so no tile decodes them again from the store."""
        with self._lock:
            new = self._nodes.add_many(entries)
        if models is not None and self._prime:
            for entry, model, added in zip(entries, models, new):
                if added:
                    self._samples.prime(NodeKey(entry.robot, entry.node), scan_seed(entry.robot, entry.node), model)
        return new

    def apply_poses(self, update: PoseGraphUpdate) -> bool:
        """Re-pose nodes (Eq. 2 at query time), node by node: a listed node takes the update's pose
        unless a newer revision set it (an equal one may be another part), the anchor likewise.
        False if the update changed nothing."""
        with self._lock:
            return self._nodes.apply(update)

    def set_last_seen(self, robot: str, when: float) -> None:
        """When `robot` was last heard from (time.time()): a restart replays its scans now, but saw
        it when they were stored."""
        with self._lock:
            self._nodes.robots[robot].last_seen = when

    # -- queries --------------------------------------------------------------------------
    def counts(self, grid: Grid, robots: Sequence[str] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Hit and miss evidence (float32) on `grid` from the nodes that can reach it (all robots or `robots`)."""
        with self._lock:  # a snapshot of the reaching nodes and their world poses
            reaching = self._nodes.reaching(grid, robots)
        hits, misses = self._tracers.trace(grid, list(reaching.values()), [])
        return hits.astype(np.float32), misses.astype(np.float32)

    def posed_components(self, grid: Grid, robots: Sequence[str] | None = None) -> list[tuple[NodeComponents, Pose]]:
        """(components in the node frame, world pose) of every node that can reach `grid` (all robots or
        `robots`): what the analytic evidence (gmm_core.analytic) is computed from, each node's
        decomposed once and kept with its samples."""
        with self._lock:  # a snapshot of the reaching nodes and their world poses
            reaching = self._nodes.reaching(grid, robots)
        return [(self._samples.components(posed.node), posed.pose) for posed in reaching.values()]

    def occupancy(self, grid: Grid, robots: Sequence[str] | None = None) -> np.ndarray:
        """p(occupied) on `grid`, Eq. 11; cached, and brought up to date by tracing only what changed
        (tiles.TileCache.occupancy)."""
        return self._tiles.occupancy(grid, robots)

    def occupancy_answer(
        self,
        grid: Grid,
        robots: Sequence[str] | None = None,
        *,
        may_shed: bool = False,
        max_age: float = MAX_STALE_S,
        patience: float | None = None,
    ) -> TileAnswer:
        """occupancy with the age and kind of the state served; tiles.TileCache.answer (which may
        shed, serve a state up to `max_age` s out of date, and wait `patience` s for an update)."""
        return self._tiles.answer(grid, robots, may_shed=may_shed, max_age=max_age, patience=patience)

    def cache_stats(self) -> dict:
        with self._lock:
            return {
                **self._tiles.stats(),
                "sample_bytes": self._samples.bytes_held,
                "change_log": len(self._nodes.log),
            }

    def robots(self) -> list[dict]:
        with self._lock:
            return self._nodes.robot_rows()

    def unknown_robots(self, robots: Collection[str]) -> list[str]:
        """Those of `robots` the map has had nothing from (no scan, no pose graph), sorted."""
        with self._lock:
            return sorted(set(robots) - self._nodes.robots.keys())

    def trajectory(self, robot: str) -> np.ndarray:
        """World positions of the robot's sensor origins, in node order."""
        with self._lock:
            return self._nodes.trajectory(robot)

    def world_poses(self, robot: str) -> list[tuple[int, Pose]]:
        """(node, world pose of its sensor) of the robot's nodes, in node order."""
        with self._lock:
            return self._nodes.world_poses(robot)

    def extent(self, robots: Collection[str] | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """World box of every node's reach (of all robots or of `robots`), or None when there is none."""
        with self._lock:
            return self._nodes.extent(robots)
