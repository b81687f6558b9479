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

The cache is TileCache, in parts: tile_state.py (a tile and an answer), tile_set.py (which cached tile
answers a grid, which a change reaches, which are dropped), tile_updates.py (bringing a tile up to
date) and tile_serving.py (under load: which state is served, which request is shed).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np

from gmm_core import Grid
from gmm_core.occupancy import monte_carlo_estimate

from .nodes import NodeStore
from .tile_serving import WAIT, ServingPolicy
from .tile_set import TileSet, layer_view
from .tile_state import Tile, TileAnswer, age_of
from .tile_updates import TileUpdates
from .tracers import TracerPool, TracingStopped

log = logging.getLogger("gmmap.server")

MAX_STALE_S = 2.0  # a previous state is served only while out of date for at most this long
# A request whose tile has a previous state it may be served waits at most this long for the tile's
# update (run in the background) before it is served that state: an update after a loop closure
# can take seconds, and a viewer asks again soon (HTTP answers; in-process callers update the tile).
PATIENCE_S = 0.2
# Thinned nodes a tile traces again with every sample per update while the tracers are idle: a refinement
# is a background update like any other, and one of a whole tile would hold the tracers for seconds.
REFINE_NODES = 64


class TileCache(TileSet, TileUpdates, ServingPolicy):
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
        self._closed = False  # by `close`, under the lock: no more background updates
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
        """No more background updates (the tracers are closed by their owner): a request that would start
        one raises TracingStopped."""
        with self._lock:
            self._closed = True
        self._refresher.shutdown(wait=False, cancel_futures=True)

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
            return replace(answer, prob=layer_view(tile, answer.prob, window))

    def _unknown(self, grid: Grid) -> TileAnswer:
        """The answer of a map with no scan: Eq. 11 of no evidence, the state a trace of `grid` would have."""
        shape = grid.array_shape
        prob = monte_carlo_estimate(np.zeros(shape), np.zeros(shape), self.samples_per_cell, self.prior)
        prob.setflags(write=False)
        return TileAnswer(prob, 0.0, "fresh", self.samples_per_cell)

    def _answer_from(self, tile: Tile, max_age: float, deadline: float | None, may_shed: bool) -> TileAnswer:
        """`answer` for the whole of `tile`."""
        waited, before = False, None
        while True:
            with self._lock:
                if before is not None and tile.prob is not before and max_age > 0:
                    # It waited for another request's update: that state, however much of a backlog
                    # it left (MAX_UPDATE_NODES), rather than a turn at the next update.
                    return self._answer(tile, age_of(tile), "updated")
                patient = deadline is not None and time.monotonic() < deadline
                cached = self._cached(tile, max_age, patient, waited)
                if cached is WAIT:
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
