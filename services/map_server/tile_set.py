"""The cached tiles of a fleet map: which tile answers a grid (a tile of its own, or a window of its
resolution's layer), which tiles a new or moved node reaches, and which are dropped (least recently
used, over TILE_CACHE_BYTES). A part of TileCache (tiles.py).
"""

from __future__ import annotations

import threading
import time

import numpy as np

from gmm_core import Grid

from .tile_state import Tile

TILE_CACHE_BYTES = 256 << 20  # counts and probabilities of cached tiles
# A layer (TileCache._tile_for) holds at most this many cells: 2M, 40 MB with its counts and
# probabilities; a grid that would grow it further is a tile of its own.
LAYER_MAX_CELLS = 1 << 21
LATTICE_TOLERANCE = 1e-6  # cells an origin may be off the lattice and still be on it (decimal metres)


class TileSet:
    """TileCache's tiles (an LRU: `_tiles`, `_bytes`, and their boxes `_boxes`), under the map's lock."""

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

    def _evict(self) -> None:
        """Drop least recently used tiles over TILE_CACHE_BYTES (always keeping the newest)."""
        while self._bytes > TILE_CACHE_BYTES and len(self._tiles) > 1:
            _, old = self._tiles.popitem(last=False)
            self._bytes -= old.nbytes
            self._boxes = None


def _window(offset: np.ndarray, shape: tuple[int, ...], whole: tuple[int, ...]) -> tuple[slice, ...] | None:
    """Array index of the cells offset .. offset + shape (x, y[, z] order) of a grid of `whole`
    cells; None when that is all of it."""
    if not offset.any() and shape == whole:
        return None
    return tuple(slice(int(o), int(o) + n) for o, n in reversed(list(zip(offset, shape))))


def layer_view(tile: Tile, prob: np.ndarray, window: tuple[slice, ...]) -> np.ndarray:
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
