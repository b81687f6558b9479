"""The tile cache of a fleet map: occupancy of the regions asked for, kept and brought up to date
incrementally.

A cached tile keeps its hit and miss counts and the posed nodes they hold. A new or moved node
only marks the tiles it can reach stale; the next query of such a tile traces the difference:
new nodes added, moved nodes subtracted at their old pose and added at the new one. Counts are
sums of quantised weights (gmm_core.sampling), exact in float64, so an updated tile has the
bytes a fresh reconstruction would have.

A tile reads the node store's change log from the position it last accounted for, at most
MAX_UPDATE_NODES changed nodes an update, oldest first; entries every cached tile has read are
dropped. A tile that the log no longer covers (it was not asked for while the log outgrew its
limit) is traced afresh on its next query. Grids on the lattice of their resolution, as the
viewer's tiles are, are windows of one tile per resolution, its layer (`TileCache._tile_for`).

Under load a tile is served older rather than traced more (ingest first): every answer carries the
age of its state, a previous state is served for at most MAX_STALE_S, and a request that would
trace while the tracers are saturated may be shed (docs/ARCHITECTURE.md, "Ingest first, tiles
degrade"). An update that begins while the tracers have other work counts the nodes it traces with
fewer samples per cell (`busy_samples_per_cell`): the same expected counts (Eq. 10: a sample's
weight is N pi_k / n_k), more Monte-Carlo noise, a fraction of the cost. Such nodes are traced again
at the map's samples per cell, REFINE_NODES at a time, while the tracers are idle, and all at once
when a request asks for every change (max_age 0); every answer says the fewest samples per cell it
holds.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from itertools import chain, compress, islice

import numpy as np

from gmm_core import Grid
from gmm_core.occupancy import monte_carlo_estimate
from gmm_core.pose import displacements

from .nodes import NodeKey, NodeStore, Posed
from .tracers import TracerPool, TracersSaturated, TracingStopped

log = logging.getLogger("gmmap.server")

TILE_CACHE_BYTES = 256 << 20  # counts and probabilities of cached tiles
MAX_STALE_S = 2.0  # a previous state is served only while out of date for at most this long
# A request whose tile has a previous state it may be served waits at most this long for the tile's
# update (run in the background) before it is served that state: an update after a loop closure
# can take seconds, and a viewer asks again soon (HTTP answers; in-process callers update the tile).
PATIENCE_S = 0.2
COALESCE_S = 0.5  # under load, a state this young ...
COALESCE_CHANGES = 16  # ... with at most this many changes since is served instead of updated
# A moved node is traced again into a tile only once some ray end of it moved by more than this many
# of the tile's cells since the pose the tile counts it at: an optimiser moves every node of a loop a
# little at every closure, and sub-cell moves do not change a tile beyond its Monte-Carlo noise.
REPOSE_CELLS = 0.25
# The busy samples per cell a server uses unless told (server.busy_samples_per_cell), by the map's
# dimension: a 3D ray costs tens of 2D ones, and with a 3D cell's prior from its neighbourhood
# (gmm_core.smoothing) 0.3 samples per cell serve a 3D map about as well as 1 did before
# (docs/BENCHMARKS.md, thirtieth session).
BUSY_SAMPLES_PER_CELL = {2: 1.0, 3: 0.3}
BUSY_REPOSE_CELLS = 1.0  # the same in an update with busy tracers, whose fewer samples are noisier than that
# Thinned nodes a tile traces again with every sample per update while the tracers are idle: a refinement
# is a background update like any other, and one of a whole tile would hold the tracers for seconds.
REFINE_NODES = 64
# Bounded updates (those of HTTP requests and in the background: TileCache._begin_update) trace at most
# FULL_UPDATE_NODES nodes with every sample on idle tracers, and apply at most MAX_UPDATE_NODES changed
# nodes, those changed longest ago (the next update goes on from there). A layer's update after loop
# closures moves thousands of nodes: at 4 samples per cell it held the tracers for tens of seconds,
# and every request waited for it once the state it replaces was too old to serve
# (docs/RELIABILITY.md, "Seventh session").
FULL_UPDATE_NODES = 64
MAX_UPDATE_NODES = 400
SLOW_UPDATE_S = 1.0  # an update that took longer is logged (with what it traced)
# A layer (TileCache._tile_for) holds at most this many cells: 2M, 40 MB with its counts and
# probabilities; a grid that would grow it further is a tile of its own.
LAYER_MAX_CELLS = 1 << 21
LATTICE_TOLERANCE = 1e-6  # cells an origin may be off the lattice and still be on it (decimal metres)


_WAIT = object()  # TileCache._cached: wait for the update under way


@dataclass(frozen=True)
class TileAnswer:
    """A tile's probabilities as served: `age` is how long ago (s) the state stopped being current,
    0 when up to date; `kind` is fresh (cached, up to date), updated (traced for this request),
    stale or coalesced (a previous state; see TileCache._cached)."""

    prob: np.ndarray
    age: float
    kind: str
    samples_per_cell: float  # the fewest any node of the state is counted with


@dataclass
class Tile:
    """A cached query: counts of the nodes in `held`, and p(occupied) while nothing changed."""

    grid: Grid
    hits: np.ndarray  # float64, exact sums
    misses: np.ndarray
    seen: int  # change-log position up to which `held` accounts for every change
    held: dict[NodeKey, Posed] = field(default_factory=dict)  # the nodes counted in, at the pose and samples counted
    thinned: int = 0  # nodes of `held` counted with the busy tracers' fewer samples per cell
    # Nodes of `held` counted at a pose that busy tracers' coarser tolerance (BUSY_REPOSE_CELLS) kept
    # though they had moved beyond REPOSE_CELLS: refined like thinned nodes, or a correction of many
    # nodes by less than a cell made while the tracers were busy would never reach the tile.
    loose: set[NodeKey] = field(default_factory=set)
    changes: int = 0  # bumped when a new or moved node may reach the tile
    prob: np.ndarray | None = None  # None until the first trace succeeded
    prob_at: int = -1  # `changes` when `prob` was computed
    # The fewest samples per cell a node of `prob` is counted with: the state's, published with it (an
    # update changes `thinned` while it traces, before its state is published).
    prob_samples_per_cell: float = 0.0
    robots: tuple[str, ...] | None = None  # the robots counted; None: all
    outdated_since: float | None = None  # monotonic time of the first change `prob` lacks; None: up to date
    dirty_since: float | None = None  # that of the first change since the running (or last) update began
    lock: threading.Lock = field(default_factory=threading.Lock)  # one update at a time
    refreshing: bool = False  # an update in the background is queued or running (TileCache._refresh)
    updated: threading.Condition | None = None  # on the map's lock: notified when an update ends
    # A layer's windows of one state, the same array each time it is asked for (so its encoded reply
    # is reused: services/api/encoded.py): (the state's prob, {window's (start, stop)s: view}).
    views: tuple[np.ndarray | None, dict] = field(default_factory=lambda: (None, {}))

    @property
    def unrefined(self) -> bool:
        """Whether idle tracers have nodes to trace again: thinned ones, or loose ones (at their pose now)."""
        return bool(self.thinned or self.loose)

    @property
    def nbytes(self) -> int:
        return self.hits.nbytes + self.misses.nbytes + self.grid.n_cells * 4


def _age(tile: Tile) -> float:
    """Seconds since the tile's state stopped being current; 0 while it is."""
    return 0.0 if tile.outdated_since is None else time.monotonic() - tile.outdated_since


@contextmanager
def _held(lock: threading.Lock):
    """Release a lock that is already acquired when the block ends."""
    try:
        yield
    finally:
        lock.release()


class TileCache:
    """LRU of tiles up to TILE_CACHE_BYTES. `lock` is the map's: it guards the tiles' bookkeeping
    and the node store; tracing runs outside it (and outside the GIL), so ingest never waits behind
    a tile, and different tiles trace in parallel. `mark_stale` is called under it."""

    def __init__(
        self,
        lock: threading.RLock,
        nodes: NodeStore,
        tracers: TracerPool,
        prior: float,
        samples_per_cell: float,
        busy_samples_per_cell: float | Mapping[int, float] | None = None,
        report_slow: bool = True,
    ):
        """busy_samples_per_cell: what updates begun while any tracer has work count new and moved
        nodes with, one for every grid or one by dimension (as BUSY_SAMPLES_PER_CELL); None (or not
        below `samples_per_cell`, the map's): always the map's.
        report_slow: log each update over SLOW_UPDATE_S (a throwaway map's, as the warm-up's, are not)."""
        self._lock = lock
        self._nodes = nodes
        self._tracers = tracers
        # Background updates (`_refresh`): one per tracer thread at a time, each tracing on the pool.
        self._refresher = ThreadPoolExecutor(tracers.threads, "gmmap-refresh")
        self.prior = prior
        self.samples_per_cell = samples_per_cell
        self.report_slow = report_slow

        def thinning(spc: float | None) -> float | None:
            return spc if spc is not None and spc < samples_per_cell else None

        given = busy_samples_per_cell
        self._busy_samples_per_cell = {
            dim: thinning(given.get(dim) if isinstance(given, Mapping) else given) for dim in (2, 3)
        }
        self._tiles: OrderedDict[tuple, Tile] = OrderedDict()
        self._bytes = 0
        self._boxes: tuple[list[Tile], np.ndarray, np.ndarray] | None = None  # while the tile set is unchanged
        self._hits = 0
        self._misses = 0
        self._updates = 0
        self._stale = 0  # answered with the previous state while it was being updated or the tracers saturated
        self._coalesced = 0  # answered with a recent state while every tracer was busy
        self._shed = 0  # refused: the tracers were saturated
        self._thinned_updates = 0  # traced with busy_samples_per_cell

    def busy_samples_per_cell(self, grid: Grid) -> float | None:
        """The samples per cell of updates of `grid` begun with busy tracers; None: the map's."""
        return self._busy_samples_per_cell[grid.dim]

    def close(self) -> None:
        """No more background updates (the tracers are closed by their owner)."""
        self._refresher.shutdown(wait=False, cancel_futures=True)

    def values(self) -> list[Tile]:
        """The cached tiles, least recently used first."""
        with self._lock:
            return list(self._tiles.values())

    def mark_stale(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Mark stale every cached tile that one of the boxes (lo, hi) reaches."""
        if self._boxes is None:
            tiles = list(self._tiles.values())
            d = self._nodes.dim or 2
            self._boxes = (
                tiles,
                np.array([t.grid.origin for t in tiles]).reshape(-1, d),
                np.array([t.grid.upper for t in tiles]).reshape(-1, d),
            )
        tiles, tiles_lo, tiles_hi = self._boxes
        reached = np.any(
            np.all(lo[:, None] <= tiles_hi[None], axis=2) & np.all(hi[:, None] >= tiles_lo[None], axis=2), axis=0
        )
        now = time.monotonic()
        for i in np.flatnonzero(reached):
            tile = tiles[i]
            tile.changes += 1
            if tile.outdated_since is None:
                tile.outdated_since = now
            if tile.dirty_since is None:
                tile.dirty_since = now

    def occupancy(self, grid: Grid, robots: Sequence[str] | None = None) -> np.ndarray:
        """p(occupied) on `grid`, Eq. 11 (the array of `answer`)."""
        return self.answer(grid, robots).prob

    def answer(
        self,
        grid: Grid,
        robots: Sequence[str] | None = None,
        *,
        may_shed: bool = False,
        max_age: float = MAX_STALE_S,
        patience: float | None = None,
    ) -> TileAnswer:
        """p(occupied) on `grid`, Eq. 11; cached, and brought up to date by tracing only what changed.

        A request that would trace and finds the tracers saturated raises TracersSaturated when
        `may_shed` (before any work: no tile is made), else queues. See `_cached` for when a
        previous state (out of date for at most `max_age` s, at most MAX_STALE_S) is served instead
        of an update. `patience`: s a request waits for an update that such a state can stand in
        for (run in the background) before it is served that state; None: with idle tracers the
        request updates the tile itself, so a lone query, with no other request nor trace running,
        sees every change applied before it. `max_age` 0: every change, whatever the load.
        """
        max_age = min(max_age, MAX_STALE_S)
        deadline = None if patience is None else time.monotonic() + patience
        robots = None if robots is None else tuple(sorted(robots))
        with self._lock:
            self._nodes.check_dim(grid)
            # Before the first scan any dimension is asked for, and a tile is not cached: one of the
            # other dimension than that scan's would outlive it (mark_stale boxes every tile in one).
            found = None if self._nodes.dim is None else self._tile_for(grid, robots, may_shed, layered=max_age > 0)
        if found is None:
            return self._unknown(grid)
        tile, window = found
        answer = self._answer_from(tile, max_age, deadline, may_shed)
        if window is None:
            return answer
        with self._lock:
            return replace(answer, prob=_view(tile, answer.prob, window))

    def _unknown(self, grid: Grid) -> TileAnswer:
        """The answer of a map with no scan: Eq. 11 of no evidence, the state a trace of `grid` would have."""
        shape = grid.array_shape
        prob = monte_carlo_estimate(np.zeros(shape), np.zeros(shape), self.samples_per_cell, self.prior)
        prob.setflags(write=False)
        return TileAnswer(prob, 0.0, "fresh", self.samples_per_cell)

    def _tile_for(
        self, grid: Grid, robots: tuple[str, ...] | None, may_shed: bool, layered: bool
    ) -> tuple[Tile, tuple | None]:
        """The tile that answers `grid` and the window of `grid` in its arrays (None: all of it),
        made (empty) if need be. Under the map's lock.

        When `layered`, a grid on the lattice of its resolution (origin a whole number of cells from
        0) is a window of its layer: one tile per resolution and robots covering every such grid
        asked for, grown to take in a new one while it stays within LAYER_MAX_CELLS. A node then is
        drawn and traced once for all the viewer's tiles of a resolution, not once per tile it
        reaches (office, 20 robots: 5.8 of the twelve 0.05 m tiles a node on average;
        docs/BENCHMARKS.md). Other grids are tiles of their own; so are those asked for with every
        change (max_age 0, e.g. a graded snapshot), which would make the viewer's whole layer wait
        for every node to be traced again with every sample."""
        res, d = grid.resolution, grid.dim
        cells = grid.origin / res
        lo = np.rint(cells).astype(np.int64)
        if layered and LAYER_MAX_CELLS and np.all(np.abs(cells - lo) <= LATTICE_TOLERANCE):
            key: tuple = ("layer", res, d, robots)
            hi = lo + np.array(grid.shape)
            layer = self._tiles.get(key)
            if layer is not None:
                layer_lo = np.rint(layer.grid.origin / res).astype(np.int64)
                layer_hi = layer_lo + np.array(layer.grid.shape)
                if np.all(lo >= layer_lo) and np.all(hi <= layer_hi):
                    self._tiles.move_to_end(key)
                    return layer, _window(lo - layer_lo, grid.shape, layer.grid.shape)
                lo_union, hi_union = np.minimum(lo, layer_lo), np.maximum(hi, layer_hi)
            else:
                lo_union, hi_union = lo, hi
            lo_union, hi_union = self._with_extent(lo_union, hi_union, res, robots)
            if np.prod(hi_union - lo_union) <= LAYER_MAX_CELLS:
                if layer is not None:  # replaced by a larger layer, traced afresh at its first update
                    del self._tiles[key]
                    self._bytes -= layer.nbytes
                union = Grid(lo_union * res, res, tuple(int(n) for n in hi_union - lo_union))
                return self._new_tile(key, union, robots, may_shed), _window(lo - lo_union, grid.shape, union.shape)
        key = (tuple(grid.origin), res, grid.shape, robots)
        tile = self._tiles.get(key)
        if tile is None:
            return self._new_tile(key, grid, robots, may_shed), None
        self._tiles.move_to_end(key)
        return tile, None

    def _with_extent(
        self, lo: np.ndarray, hi: np.ndarray, res: float, robots: tuple[str, ...] | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Cells lo .. hi of a layer to be made, grown to take in the map's extent (the viewer's first
        screen: it fits the view to the map) while that stays within LAYER_MAX_CELLS: the viewer's
        tiles then arrive as windows of one trace, where a layer grown tile by tile was traced afresh
        at each growth (office, 20 robots: six times in its first half second, docs/RELIABILITY.md)."""
        extent = self._nodes.extent(robots)
        if extent is None:
            return lo, hi
        grown_lo = np.minimum(lo, np.floor(extent[0] / res).astype(np.int64))
        grown_hi = np.maximum(hi, np.ceil(extent[1] / res).astype(np.int64))
        return (grown_lo, grown_hi) if np.prod(grown_hi - grown_lo) <= LAYER_MAX_CELLS else (lo, hi)

    def _new_tile(self, key: tuple, grid: Grid, robots: tuple[str, ...] | None, may_shed: bool) -> Tile:
        """An empty tile cached under `key` (a request that would make one is shed first when it may be)."""
        self._admit(may_shed)
        # `seen` pins the change log until the first trace: it counts nothing yet (prob is None).
        tile = Tile(
            grid,
            np.zeros(grid.array_shape),
            np.zeros(grid.array_shape),
            self._nodes.log.end,
            robots=robots,
            updated=threading.Condition(self._lock),
        )
        self._tiles[key] = tile
        self._bytes += tile.nbytes
        self._boxes = None
        self._evict()
        return tile

    def _answer_from(self, tile: Tile, max_age: float, deadline: float | None, may_shed: bool) -> TileAnswer:
        """`answer` for the whole of `tile`."""
        waited, before = False, None
        while True:
            with self._lock:
                if before is not None and tile.prob is not before and max_age > 0:
                    # It waited for another request's update: that state, however much of a backlog
                    # it left (MAX_UPDATE_NODES), rather than a turn at the next update.
                    return self._answer(tile, _age(tile), "updated")
                patient = deadline is not None and time.monotonic() < deadline
                cached = self._cached(tile, max_age, patient, waited)
                if cached is _WAIT:
                    tile.updated.wait(deadline - time.monotonic())
                    waited = True
                    continue
                if cached is not None:
                    return cached
                self._admit(may_shed)  # it would trace, or wait for a trace: shed if they are saturated
                if tile.lock.acquire(blocking=False):  # never waits under the map's lock
                    full = max_age <= 0 or self._tracers.load().idle
                    refine = None if max_age <= 0 else REFINE_NODES
                    work = self._begin_update(tile, full, refine, bounded=refine is not None and deadline is not None)
                    break
                before = tile.prob
            with tile.lock:  # another request updates it, and its previous state is too old or absent
                pass
        return self._update(tile, work)

    def _begin_update(self, tile: Tile, full: bool, refine: int | None, bounded: bool) -> tuple:
        """What an update of `tile` traces, under the map's lock with `tile.lock` held: (afresh, the
        nodes reaching it or those changed since it last read the log (at most MAX_UPDATE_NODES when
        `bounded`), the changes and log position it will account for, whether that leaves later
        changes out, whether it is the first trace, the samples per cell of what it traces: None for
        the map's, which `full` asks for (for at most FULL_UPDATE_NODES nodes when `bounded`), and
        then the thinned and loose nodes, at most `refine` (None: all), it traces again with every sample,
        where they stand now; and whether its parts give way to other traces'). Bounded: the updates
        of HTTP requests (which may be served a previous state meanwhile) and in the background; an
        in-process caller (patience None) and a request for every change get every change, at every
        sample with idle tracers, in parts that give way (TracerPool.trace's `background`): such an
        update may trace thousands of nodes. A bounded one traces a bounded number and holds its
        tile meanwhile: giving way, a refinement begun on idle tracers kept the viewer's busiest
        layer waiting for every other tile's update once load came back (docs/RELIABILITY.md)."""
        changes, seen, first = tile.changes, self._nodes.log.end, tile.prob is None
        afresh = first or tile.seen < self._nodes.log.start
        if afresh:
            nodes = self._nodes.reaching(tile.grid, tile.robots)
        else:
            limit = MAX_UPDATE_NODES if bounded else None
            nodes, seen = self._nodes.changed_since(tile.seen, tile.grid, tile.robots, limit)
        repose_cells = REPOSE_CELLS if full else BUSY_REPOSE_CELLS  # the tolerance of busy tracers
        if bounded and len(nodes) > FULL_UPDATE_NODES:
            full = False  # a large update is thinned even on idle tracers, and refined behind it
        samples_per_cell = None if full else self.busy_samples_per_cell(tile.grid)
        refined = {}
        if full and tile.unrefined and not afresh:
            thinned = (k for k, posed in tile.held.items() if posed.samples_per_cell is not None)
            refined = {k: self._nodes.posed(k) for k in islice(chain(thinned, tile.loose), refine)}
        tile.dirty_since = None  # from here on, changes are left for the next update
        partial = seen < self._nodes.log.end  # MAX_UPDATE_NODES left changes for the next update
        return afresh, nodes, changes, seen, partial, first, samples_per_cell, repose_cells, refined, not bounded

    def _update(self, tile: Tile, work: tuple) -> TileAnswer:
        """Trace what `_begin_update` found and publish the tile's new state; releases `tile.lock`."""
        afresh, nodes, changes, seen, partial, first, samples_per_cell, repose_cells, refined, background = work
        start = time.monotonic()
        with _held(tile.lock):
            try:
                if afresh:
                    self._trace_afresh(tile, nodes, samples_per_cell, background)
                else:
                    self._trace_changes(tile, nodes, samples_per_cell, repose_cells, refined, background)
            except BaseException:
                with self._lock:
                    tile.dirty_since = tile.outdated_since  # nothing was applied
                    tile.updated.notify_all()
                raise
            # The state's samples per cell (a tile holds thinned nodes only where busy_samples_per_cell is set).
            state_samples_per_cell = self.busy_samples_per_cell(tile.grid) if tile.thinned else self.samples_per_cell
            prob = monte_carlo_estimate(tile.hits, tile.misses, state_samples_per_cell, self.prior)
            prob.setflags(write=False)
            seconds = time.monotonic() - start
            if self.report_slow and seconds > SLOW_UPDATE_S:
                log.warning(
                    "a tile update took %.1f s: %s, %d nodes (%d refined) at %s samples per cell on %s cells of %g m",
                    seconds, "afresh" if afresh else "changes", len(nodes), len(refined),
                    samples_per_cell or self.samples_per_cell, tile.grid.shape, tile.grid.resolution,
                )  # fmt: skip
            with self._lock:
                # A change after the snapshot bumped `changes` (and set `dirty_since`): the next
                # query updates again, and this state has been out of date since that change.
                tile.prob, tile.prob_at, tile.seen = prob, changes, seen
                tile.prob_samples_per_cell = state_samples_per_cell
                tile.outdated_since = tile.dirty_since
                if partial:
                    tile.prob_at = changes - 1  # so it is not up to date ...
                    tile.outdated_since = self._nodes.log.time_of(seen)  # ... since the first change it lacks
                tile.updated.notify_all()
                if first:
                    self._misses += 1
                else:
                    self._updates += 1
                self._thinned_updates += samples_per_cell is not None
                self._nodes.log.drop_before(min((t.seen for t in self._tiles.values()), default=seen))
                return self._answer(tile, _age(tile), "updated")

    def _refresh(self, tile: Tile) -> None:
        """Update `tile` in the background (a request served its previous state meanwhile)."""
        with self._lock:
            tile.refreshing = False
            full = self._tracers.load().idle
            refines = tile.unrefined and full
            if (tile.prob_at == tile.changes and not refines) or not tile.lock.acquire(blocking=False):
                return  # up to date (and refined, or the tracers are busy), or a request is updating it
            work = self._begin_update(tile, full, REFINE_NODES, bounded=True)
        try:
            self._update(tile, work)
        except TracingStopped:
            pass  # the server is stopping
        except Exception:  # the tile stays as it was; the next request updates it or says why
            log.exception("background update of a tile failed")

    def _cached(self, tile: Tile, max_age: float, patient: bool, waited: bool = False) -> TileAnswer | None | object:
        """The answer from the cache; None when this request must update the tile (or wait for the
        request that does); _WAIT when it should wait for the update under way (`patient`: its
        patience lasts; `waited`: it did, so an up-to-date state is the update it waited for).
        Under the map's lock.

        Up to date: fresh. Otherwise the previous state, while it has been out of date for at most
        `max_age`: stale while an update of the tile is under way; with every tracer busy (or
        saturated), coalesced while the state is at most COALESCE_S old with at most
        COALESCE_CHANGES changes since (a busy tile is updated once for many changes), else stale
        while an update starts in the background. So under load a request never waits for an
        update that a previous state can stand in for; with idle tracers it updates the tile itself,
        or, patient, starts the update in the background and waits for it while its patience lasts.
        """
        if tile.prob is None:
            return None
        if tile.prob_at == tile.changes:
            if max_age <= 0 and (tile.unrefined or tile.prob_samples_per_cell < self.samples_per_cell):
                # Every change, with every sample: refined by this request, or by the refinement that
                # has traced and not yet published (the tile's bookkeeping runs ahead of its state).
                return None
            if waited:
                return self._answer(tile, 0.0, "updated")
            self._hits += 1
            if tile.unrefined and not (tile.refreshing or tile.lock.locked()) and self._tracers.load().idle:
                tile.refreshing = True  # refined in the background while the tracers are idle
                self._refresher.submit(self._refresh, tile)
            return self._answer(tile, 0.0, "fresh")
        age = _age(tile)
        if age > max_age or max_age <= 0:
            return None
        if tile.lock.locked() or tile.refreshing:
            if patient:
                return _WAIT
            self._stale += 1
            return self._answer(tile, age, "stale")
        load = self._tracers.load()
        if not (load.busy or load.saturated):
            if not patient:
                return None
            tile.refreshing = True
            self._refresher.submit(self._refresh, tile)
            return _WAIT
        if not load.saturated and age <= COALESCE_S and tile.changes - tile.prob_at <= COALESCE_CHANGES:
            self._coalesced += 1
            return self._answer(tile, age, "coalesced")
        tile.refreshing = True
        self._refresher.submit(self._refresh, tile)
        self._stale += 1
        return self._answer(tile, age, "stale")

    def _answer(self, tile: Tile, age: float, kind: str) -> TileAnswer:
        """The tile's state as served. Under the map's lock."""
        return TileAnswer(tile.prob, age, kind, tile.prob_samples_per_cell)

    def _admit(self, may_shed: bool) -> None:
        """Raise TracersSaturated (counted) when `may_shed` and the tracers are saturated."""
        if may_shed:
            load = self._tracers.load()
            if load.saturated:
                self._shed += 1
                raise TracersSaturated(load)

    def _trace_afresh(
        self, tile: Tile, reaching: dict[NodeKey, Posed], samples_per_cell: float | None, background: bool
    ) -> None:
        """Counts of every node in `reaching`, replacing what the tile held."""
        counted = [posed.counted_with(samples_per_cell) for posed in reaching.values()]
        if counted:
            tile.hits, tile.misses = self._tracers.trace(tile.grid, counted, [], background)
        else:
            tile.hits, tile.misses = np.zeros(tile.grid.array_shape), np.zeros(tile.grid.array_shape)
        tile.held = {posed.key: posed for posed in counted}
        tile.thinned = len(counted) if samples_per_cell is not None else 0
        tile.loose = set()

    def _trace_changes(
        self,
        tile: Tile,
        changed: dict[NodeKey, Posed | None],
        samples_per_cell: float | None,
        repose_cells: float,
        refined: dict[NodeKey, Posed],
        background: bool,
    ) -> None:
        """Bring the counts up to the nodes in `changed` (None: it no longer reaches the tile), tracing
        them with `samples_per_cell` (None: the map's) where new or moved by over `repose_cells` cells,
        and trace the thinned and loose nodes in `refined` again with every sample, where they stand
        now; in parts that give way to other traces' when `background`.

        Only after the trace succeeded is the tile changed: a failed one leaves it as it was.
        """
        held, spc, loose = tile.held, samples_per_cell, {}
        moved = {k: held[k] for k, now in changed.items() if now is None and k in held}  # it left the tile
        new = [now.counted_with(spc) for k, now in changed.items() if now is not None and k not in held]
        reposed = [
            (held[k], now) for k, now in changed.items() if now is not None and k in held and now.stamp != held[k].stamp
        ]
        if reposed:  # traced again only when some ray end moved over `repose_cells` cells
            was, now = zip(*reposed)
            moved_by = (
                displacements(
                    np.array([p.pose.t for p in was]),
                    np.array([p.pose.R for p in was]),
                    np.array([p.pose.t for p in now]),
                    np.array([p.pose.R for p in now]),
                    np.array([p.node.reach for p in now]),
                )
                / tile.grid.resolution
            )
            far = moved_by > repose_cells
            for before, after in compress(reposed, far):
                moved[before.key] = before
                new.append(after.counted_with(spc))
            # The others stay counted at the pose held, within the tolerance of where they stand now:
            # loose (refined later) where only busy tracers' coarser tolerance keeps them there.
            loose = {b.key: cells > REPOSE_CELLS for (b, _), cells, f in zip(reposed, moved_by, far) if not f}
        for k, now in refined.items():  # taken out as counted, counted again with every sample
            if k not in moved and k in held:
                moved[k] = held[k]
                new.append(now)
        if not (new or moved):
            _mark_loose(tile, loose, moved)
            return
        # Updating traces new + moved nodes, afresh traces new + unmoved ones: update unless most of
        # the tile moved (a big correction).
        if 2 * len(moved) <= len(held):  # moved: taken out at their old pose
            hits, misses = self._tracers.trace(tile.grid, new, list(moved.values()), background)
            tile.hits += hits
            tile.misses += misses
            tile.thinned += _thinned(new) - _thinned(moved.values())
        else:
            kept = [posed.counted_with(spc) for k, posed in held.items() if k not in moved]
            tile.hits, tile.misses = self._tracers.trace(tile.grid, kept + new, [], background)
            held.update((posed.key, posed) for posed in kept)
            tile.thinned = _thinned(kept) + _thinned(new)
        for k in moved:
            del held[k]
        held.update((posed.key, posed) for posed in new)
        _mark_loose(tile, loose, moved)

    def _evict(self) -> None:
        """Drop least recently used tiles over TILE_CACHE_BYTES (always keeping the newest)."""
        while self._bytes > TILE_CACHE_BYTES and len(self._tiles) > 1:
            _, old = self._tiles.popitem(last=False)
            self._bytes -= old.nbytes
            self._boxes = None

    def stats(self) -> dict:
        load = self._tracers.load()
        with self._lock:
            return {
                "hits": self._hits,
                "misses": self._misses,
                "updates": self._updates,
                "stale": self._stale,
                "coalesced": self._coalesced,
                "shed": self._shed,
                "thinned_updates": self._thinned_updates,
                "trace_queued": load.queued,
                "tiles": len(self._tiles),
                "tile_bytes": self._bytes,
            }


def _window(offset: np.ndarray, shape: tuple[int, ...], whole: tuple[int, ...]) -> tuple[slice, ...] | None:
    """Array index of the cells offset .. offset + shape (x, y[, z] order) of a grid of `whole`
    cells; None when that is all of it."""
    if not offset.any() and shape == whole:
        return None
    return tuple(slice(int(o), int(o) + n) for o, n in reversed(list(zip(offset, shape))))


def _view(tile: Tile, prob: np.ndarray, window: tuple[slice, ...]) -> np.ndarray:
    """prob[window], the same view object for the same state and window (under the map's lock)."""
    held, views = tile.views
    if held is not prob:
        views = {}
        tile.views = (prob, views)
    key = tuple((s.start, s.stop) for s in window)
    view = views.get(key)
    if view is None:
        view = views[key] = prob[window]
    return view


def _mark_loose(tile: Tile, loose: dict[NodeKey, bool], traced: Iterable[NodeKey]) -> None:
    """Bring tile.loose up to an update: `loose` says of each node it kept at the pose held whether
    that node is loose now; the nodes it `traced` (moved, refined or gone) are not."""
    tile.loose = {k for k in tile.loose | loose.keys() if loose.get(k, True)}.difference(traced)


def _thinned(counted: Iterable[Posed]) -> int:
    """How many of `counted` hold fewer samples per cell than the map's (a tile keeps the count as
    it goes: summing it over every node held took 2.6 % of a busy tile's update, docs/BENCHMARKS.md)."""
    return sum(posed.samples_per_cell is not None for posed in counted)
