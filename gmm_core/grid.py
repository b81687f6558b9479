"""The grid convention (docs/ARCHITECTURE.md, "Conventions"): origin = min corner, index [iy, ix] or [iz, iy, ix]."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _check_resolution(resolution: float) -> None:
    if not (np.isfinite(resolution) and resolution > 0):
        raise ValueError(f"grid: resolution must be positive, got {resolution}")


@dataclass(frozen=True)
class Grid:
    """A regular grid over an axis-aligned box. Cell centre = origin + (index + 0.5) * resolution.

    `origin` and `shape` are given in (x, y[, z]) order; arrays over the grid are indexed in
    reverse order, `[iy, ix]` or `[iz, iy, ix]` (see `array_shape`).
    """

    origin: np.ndarray  # (d,) min corner, metres
    resolution: float
    shape: tuple[int, ...]  # cells along x, y[, z]

    def __post_init__(self):
        origin = np.asarray(self.origin, dtype=np.float64)
        shape = tuple(int(n) for n in self.shape)
        if origin.shape not in ((2,), (3,)) or len(shape) != origin.shape[0]:
            raise ValueError(f"grid: origin must have 2 or 3 values matching shape, got {origin.shape}, {shape}")
        if not np.isfinite(origin).all():
            raise ValueError("grid: origin is not finite")
        _check_resolution(self.resolution)
        if min(shape) < 1:
            raise ValueError(f"grid: shape must be at least 1 cell per axis, got {shape}")
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "resolution", float(self.resolution))

    @staticmethod
    def from_bbox(lo, hi, resolution: float) -> Grid:
        """The grid whose min corner is `lo` exactly, covering `hi` (rounded up to whole cells)."""
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        if lo.shape != hi.shape or not (hi > lo).all():
            raise ValueError(f"bbox: max corner must exceed min corner on every axis, got {lo} .. {hi}")
        _check_resolution(resolution)  # before dividing by it: numpy would warn, then Grid refuse
        # A tolerance keeps an exact multiple (e.g. 10 m at 0.1 m) from gaining a sliver cell.
        shape = np.ceil((hi - lo) / resolution - 1e-9).astype(np.int64)
        return Grid(lo, resolution, tuple(np.maximum(shape, 1)))

    @property
    def dim(self) -> int:
        return self.origin.shape[0]

    @property
    def array_shape(self) -> tuple[int, ...]:
        """Shape of arrays over this grid: (ny, nx) or (nz, ny, nx)."""
        return tuple(reversed(self.shape))

    @property
    def n_cells(self) -> int:
        return int(np.prod(self.shape))

    @property
    def upper(self) -> np.ndarray:
        return self.origin + np.asarray(self.shape) * self.resolution

    def cell_centers(self) -> np.ndarray:
        """(n_cells, d) centres in array order ([iy, ix] flattened, x fastest)."""
        axes = [self.origin[i] + (np.arange(self.shape[i]) + 0.5) * self.resolution for i in range(self.dim)]
        mesh = np.meshgrid(*reversed(axes), indexing="ij")
        return np.stack([m.ravel() for m in reversed(mesh)], axis=1)
