"""`gmmap replay`: a log through fit and reconstruction, offline, as a server would build it."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from gmm_core import FitConfig, Grid, ScanModel, fit_scan
from gmm_core.analytic.evidence_2d import analytic_map_2d
from gmm_core.occupancy import map_estimate, monte_carlo_estimate
from gmm_core.pose import Pose
from gmm_core.raytrace import MAX_CELLS as MAX_TRACED_CELLS
from gmm_core.reconstruct import ReconstructionConfig, count_beams, reconstruct
from gmm_core.sampling import scan_seed
from gmm_core.voxel_em import fit_mixture_voxels
from protocol import ScanMessage, decode, encode
from services.datasets import RangeScan

METHODS = ("mc", "analytic", "raw")
KERNEL_POINTS = 1000  # points (and no-return beams) of the scan load_fit_kernels fits
DEFAULT_RESOLUTION = 0.05  # m: a laser map's cell; doubled where the data's extent needs it (replay_grid)
# Cells of a grid replay_grid chooses at the most: float64 hit and miss counts while tracing, then
# the float32 counts and map, 28 bytes a cell at the peak (1.8 GB). An outdoor lidar's extent at 5 cm
# is billions (BALM's, with its points to 140 m: 8 G).
MAX_REPLAY_CELLS = 64_000_000


@dataclass(frozen=True)
class ReplayMap:
    grid: Grid
    hits: np.ndarray
    misses: np.ndarray
    prob: np.ndarray
    scans: int
    components: int


def data_extent(scans: Sequence[RangeScan], max_range: float, margin: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Box around every sensor origin and beam end (no-returns cut at max_range), plus a margin."""
    lo, hi = np.inf, -np.inf
    for s in scans:  # scan by scan: a long lidar sequence's points at once would be gigabytes
        ends = np.concatenate([s.pose.apply(s.hits), s.pose.apply(s.no_return * max_range), s.pose.t[None]])
        lo, hi = np.minimum(lo, ends.min(axis=0)), np.maximum(hi, ends.max(axis=0))
    return lo - margin, hi + margin


def replay_grid(
    scans: Sequence[RangeScan], max_range: float, resolution: float | None = None, bbox: Sequence[float] | None = None
) -> Grid:
    """The grid a replay maps: `bbox` (min corner exact; xmin, ymin[, zmin], xmax, ymax[, zmax]) or
    the data's extent, at `resolution` m. None: DEFAULT_RESOLUTION, doubled until the grid holds at
    most MAX_REPLAY_CELLS; a resolution given is kept up to the tracer's limit (a machine with the
    memory may map more), past it a ValueError names the option and what fits."""
    dim = scans[0].pose.dim
    if bbox is None:
        lo, hi = data_extent(scans, max_range)
    else:
        if len(bbox) != 2 * dim:
            raise ValueError(f"bbox: a {dim}D log needs {2 * dim} numbers, got {len(bbox)}")
        lo, hi = np.asarray(bbox[:dim], float), np.asarray(bbox[dim:], float)
    grid = Grid.from_bbox(lo, hi, _finest_fitting(lo, hi) if resolution is None else resolution)
    if grid.n_cells > MAX_TRACED_CELLS:
        extent = " x ".join(f"{v:.0f}" for v in hi - lo)
        raise ValueError(
            f"resolution: {grid.resolution:g} m over {'the bbox' if bbox else 'the data'} ({extent} m) is "
            f"{grid.n_cells:,} cells, more than the {MAX_TRACED_CELLS:,} a trace can number; "
            f"{_finest_fitting(lo, hi):g} m makes at most {MAX_REPLAY_CELLS:,}, or give a smaller --bbox"
        )
    return grid


def _finest_fitting(lo: np.ndarray, hi: np.ndarray) -> float:
    """DEFAULT_RESOLUTION doubled until the box lo..hi holds at most MAX_REPLAY_CELLS cells."""
    resolution = DEFAULT_RESOLUTION
    while Grid.from_bbox(lo, hi, resolution).n_cells > MAX_REPLAY_CELLS:
        resolution *= 2.0
    return resolution


def scan_message(model: ScanModel, scan: RangeScan, fleet: str = "replay", robot: str = "replay") -> ScanMessage:
    """The message a robot agent would publish for this scan (node = scan index)."""
    return ScanMessage(fleet, robot, scan.index, scan.stamp, model, scan.pose)


def through_wire(model: ScanModel, encoding: str) -> ScanModel:
    """The model as a server decodes it after `encoding` ("none": untouched)."""
    if encoding == "none":
        return model
    message = ScanMessage("replay", "replay", 0, 0.0, model, Pose.identity(model.dim))
    return decode(encode(message, encoding), expect=ScanMessage).model


def load_fit_kernels(scan: RangeScan, config: FitConfig) -> float:
    """Fit KERNEL_POINTS of `scan`'s points so that numba's fit kernels are compiled, or loaded from its
    cache (their first call does it: 0.3 s on BALM, twice what its 14 scans' fits take); returns the
    seconds it took. The points are spread over the scan's ranges, so that every tier of voxels the
    scan reaches is among them; and in 3D they are fitted again as a cloud without rings, whose voxel
    EM a lidar's scan does not run: a later scan whose rings go unseen (a sparse one) would otherwise
    load those kernels during its fit (49 ms instead of 15 on the 3x stand-in)."""
    start = time.perf_counter()
    by_range = np.linalg.norm(scan.hits, axis=1)
    spread = scan.hits[
        np.argsort(by_range)[np.linspace(0, len(by_range) - 1, min(KERNEL_POINTS, len(by_range))).astype(int)]
    ]
    fit_scan(spread, scan.no_return[:KERNEL_POINTS], config)
    three = config.for_dimension(3)
    if spread.shape[1] == 3 and len(spread) and three.voxel_size:
        fit_mixture_voxels(spread, len(spread), three.voxel_size, max_iter=2, search_every=1, rings=0.0)
    return time.perf_counter() - start


def fit_scans(
    scans: Sequence[RangeScan], config: FitConfig, progress: Callable[[int], None] | None = None
) -> list[ScanModel]:
    models = []
    for scan in scans:
        models.append(fit_scan(scan.hits, scan.no_return, config))
        if progress is not None:
            progress(1)
    return models


def replay(
    scans: Sequence[RangeScan],
    *,
    resolution: float | None = None,
    bbox: Sequence[float] | None = None,
    method: str = "mc",
    config: FitConfig = FitConfig(),
    seed: int = 0,
    reconstruction: ReconstructionConfig = ReconstructionConfig(),
    encoding: str = "q",
    progress: Callable[[str, int, int], Callable[[int], None]] | None = None,
) -> ReplayMap:
    """The occupancy map of `scans` on replay_grid's grid: `bbox` (min corner exact) or the data's
    extent, at `resolution` (None: the finest that replay_grid allows, from 5 cm).

    Every scan model passes through the wire `encoding` ("q", "f32" or "none") first, so the
    offline map equals what a server builds. `progress(stage, total)` returns a callback told of work done.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if not scans:
        raise ValueError("replay: the log holds no scans")
    dim = scans[0].pose.dim
    if method == "analytic" and dim != 2:
        raise ValueError("method: analytic maps are 2D only; use mc for 3D")
    grid = replay_grid(scans, config.max_range, resolution, bbox)
    tick = (lambda stage, total: progress(stage, total)) if progress else (lambda stage, total: None)
    if method == "raw":
        hits, misses = count_beams(
            grid, [(s.hits, s.no_return, s.pose) for s in scans], config.max_range, tick("trace", len(scans))
        )
        components = 0
    else:
        models = [through_wire(m, encoding) for m in fit_scans(scans, config, tick("fit", len(scans)))]
        components = sum(m.n_components for m in models)
    if method == "analytic":
        hits, misses = analytic_map_2d([(m, s.pose) for m, s in zip(models, scans)], grid)
        hits, misses = hits.astype(np.float32), misses.astype(np.float32)
    elif method == "mc":
        hits, misses = reconstruct(
            grid,
            [(m, s.pose, scan_seed(seed, s.index)) for m, s in zip(models, scans)],
            samples_per_cell=reconstruction.samples_per_cell,
            progress=tick("trace", len(scans)),
        )
    if method == "mc":
        prob = monte_carlo_estimate(hits, misses, reconstruction.samples_per_cell, reconstruction.prior)
    else:
        prob = map_estimate(hits, misses, reconstruction.prior)
    return ReplayMap(grid, hits, misses, prob, len(scans), components)
