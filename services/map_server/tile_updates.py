"""How a cached tile is brought up to date: afresh, or by tracing only what changed since it last
read the node store's change log (new nodes added, moved ones taken out at their old pose and
added at the new one), with fewer samples per cell when the tracers are busy and refined with
every sample once they are idle. A part of TileCache (tiles.py).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterable
from contextlib import contextmanager
from itertools import chain, compress, islice

import numpy as np

from gmm_core.occupancy import monte_carlo_estimate
from gmm_core.pose import displacements

from .nodes import NodeKey, Posed
from .tile_state import Tile, TileAnswer, age_of

log = logging.getLogger("gmmap.server")

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
# Bounded updates (those of HTTP requests and in the background: TileCache._begin_update) trace at most
# FULL_UPDATE_NODES nodes with every sample on idle tracers, and apply at most MAX_UPDATE_NODES changed
# nodes, those changed longest ago (the next update goes on from there). A layer's update after loop
# closures moves thousands of nodes: at 4 samples per cell it held the tracers for tens of seconds,
# and every request waited for it once the state it replaces was too old to serve
# (docs/RELIABILITY.md, "Seventh session").
FULL_UPDATE_NODES = 64
MAX_UPDATE_NODES = 400
SLOW_UPDATE_S = 1.0  # an update that took longer is logged (with what it traced)


@contextmanager
def _held(lock: threading.Lock):
    """Release a lock that is already acquired when the block ends."""
    try:
        yield
    finally:
        lock.release()


class TileUpdates:
    """TileCache's updates of a tile, on the cache's lock, node store and tracers."""

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
                return self._answer(tile, age_of(tile), "updated")

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


def _mark_loose(tile: Tile, loose: dict[NodeKey, bool], traced: Iterable[NodeKey]) -> None:
    """Bring tile.loose up to an update: `loose` says of each node it kept at the pose held whether
    that node is loose now; the nodes it `traced` (moved, refined or gone) are not."""
    tile.loose = {k for k in tile.loose | loose.keys() if loose.get(k, True)}.difference(traced)


def _thinned(counted: Iterable[Posed]) -> int:
    """How many of `counted` hold fewer samples per cell than the map's (a tile keeps the count as
    it goes: summing it over every node held took 2.6 % of a busy tile's update, docs/BENCHMARKS.md)."""
    return sum(posed.samples_per_cell is not None for posed in counted)
