"""Under load a tile is served older rather than traced more (ingest first): which state of a cached
tile a request is served, and which requests are shed (docs/ARCHITECTURE.md, "Ingest first, tiles
degrade"). A part of TileCache (tiles.py).
"""

from __future__ import annotations

from .tile_state import Tile, TileAnswer, age_of
from .tracers import TracersSaturated, TracingStopped

COALESCE_S = 0.5  # under load, a state this young ...
COALESCE_CHANGES = 16  # ... with at most this many changes since is served instead of updated

WAIT = object()  # TileCache._cached: wait for the update under way


class ServingPolicy:
    """TileCache's choice between a tile's previous state, an update and a refusal; on the cache's
    lock, tracers, background updates (`_refresh`) and counters."""

    def _cached(self, tile: Tile, max_age: float, patient: bool, waited: bool = False) -> TileAnswer | None | object:
        """The answer from the cache; None when this request must update the tile (or wait for the
        request that does); WAIT when it should wait for the update under way (`patient`: its
        patience lasts; `waited`: it did, so an up-to-date state is the update it waited for).
        Under the map's lock.

        Up to date: fresh. Otherwise the previous state, while it has been out of date for at most
        `max_age`: stale while an update of the tile is under way; with every tracer busy (or
        saturated), coalesced while the state is at most COALESCE_S old with at most
        COALESCE_CHANGES changes since (a busy tile is updated once for many changes), else stale
        while an update starts in the background. So under load a request never waits for an
        update that a previous state can stand in for; with idle tracers it updates the tile itself,
        or, patient, starts the update in the background and waits for it while its patience lasts.
        Once the cache is closed, a request that would start a background update raises TracingStopped.
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
            refinable = tile.unrefined and not (tile.refreshing or tile.lock.locked() or self._closed)
            if refinable and self._tracers.load().idle:
                self._refresh_later(tile)  # refined in the background while the tracers are idle
            return self._answer(tile, 0.0, "fresh")
        age = age_of(tile)
        if age > max_age or max_age <= 0:
            return None
        if tile.lock.locked() or tile.refreshing:
            if patient:
                return WAIT
            self._stale += 1
            return self._answer(tile, age, "stale")
        load = self._tracers.load()
        if not (load.busy or load.saturated):
            if not patient:
                return None
            self._refresh_later(tile)
            return WAIT
        if not load.saturated and age <= COALESCE_S and tile.changes - tile.prob_at <= COALESCE_CHANGES:
            self._coalesced += 1
            return self._answer(tile, age, "coalesced")
        self._refresh_later(tile)
        self._stale += 1
        return self._answer(tile, age, "stale")

    def _refresh_later(self, tile: Tile) -> None:
        """Update `tile` in the background (`_refresh`). Under the map's lock, as `close` sets `_closed`:
        once the cache is closed, TracingStopped (a stopping server answers 503 with Retry-After), where
        the closed pool's RuntimeError "cannot schedule new futures after shutdown" was a 500."""
        if self._closed:
            raise TracingStopped()
        tile.refreshing = True
        self._refresher.submit(self._refresh, tile)

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
