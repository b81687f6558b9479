"""A cached tile of a fleet map (its counts, the nodes they hold, its state and how old that state is),
and an answer as served (tiles.py)."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np

from gmm_core import Grid

from .nodes import NodeKey, Posed


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


def age_of(tile: Tile) -> float:
    """Seconds since the tile's state stopped being current; 0 while it is."""
    return 0.0 if tile.outdated_since is None else time.monotonic() - tile.outdated_since
