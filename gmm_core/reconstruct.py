"""Occupancy evidence on a grid from many scans with world poses (Sec. III-C3, Algorithm 1).

`reconstruct` samples each scan's mixtures in the scan frame, moves the samples and the sensor
origin by the scan's pose (the points-level form of Eq. 2) and ray-traces them
(gmm_core.scan_trace); `count_beams`
is the plain counting occupancy grid from the raw beams, through the same ray tracer.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from gmm_core.grid import Grid
from gmm_core.occupancy import DEFAULT_PRIOR, DEFAULT_VARIANCE, check_variance
from gmm_core.pose import Pose
from gmm_core.raytrace import trace_rays
from gmm_core.sampling import scan_samples
from gmm_core.scan import ScanModel
from gmm_core.scan_trace import GridCounts
from gmm_core.validation import require_number

RAYS_PER_BATCH = 2_000_000  # bounds memory: rays are traced in batches and their counts added


@dataclass(frozen=True)
class ReconstructionConfig:
    """How occupancy is rebuilt from mixtures (the `reconstruction` section of the configuration)."""

    samples_per_cell: float = 4.0  # Monte-Carlo samples per cell of the queried resolution (Sec. III-C3), > 0
    prior: float = DEFAULT_PRIOR  # N_p of Eq. 11, pseudo-counts, > 0
    variance: float = DEFAULT_VARIANCE  # sigma^2 of Eq. 12's dead band, in [0, 0.25], where maps are classified

    def __post_init__(self):
        require_number("reconstruction.samples_per_cell", self.samples_per_cell, positive=True)
        require_number("reconstruction.prior", self.prior, positive=True)
        check_variance(
            require_number("reconstruction.variance", self.variance, positive=False), "reconstruction.variance"
        )


def trace_groups(
    grid: Grid,
    rays: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    progress: Callable[[int], None] | None,
    dtype=np.float32,
    threads: int | None = None,
):
    """Trace groups of rays (world origin, world ends, weights, is_hit) in batches.

    Counts add up across batches, so memory stays bounded however many scans there are. They are
    summed in float64 and returned as `dtype`, so the map does not depend on batching or threads
    (with sampling's quantised weights the float64 sums are exact). `threads`: as trace_rays.
    """
    hits = np.zeros(grid.array_shape)
    misses = np.zeros(grid.array_shape)
    batch: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    n_rays = 0

    def flush():
        nonlocal batch, n_rays
        if batch:
            origins = np.stack([b[0] for b in batch])
            ray_origin = np.repeat(np.arange(len(batch)), [len(b[1]) for b in batch])
            h, m = trace_rays(
                grid,
                origins,
                ray_origin,
                np.concatenate([b[1] for b in batch]),
                np.concatenate([b[2] for b in batch]),
                np.concatenate([b[3] for b in batch]),
                threads,
            )
            np.add(hits, h, out=hits)
            np.add(misses, m, out=misses)
            if progress is not None:
                progress(len(batch))
        batch, n_rays = [], 0

    for group in rays:
        batch.append(group)
        n_rays += len(group[1])
        if n_rays >= RAYS_PER_BATCH:
            flush()
    flush()
    return hits.astype(dtype, copy=False), misses.astype(dtype, copy=False)


def reconstruct(
    grid: Grid,
    scans: Iterable[tuple[ScanModel, Pose, int]],
    *,
    samples_per_cell: float = ReconstructionConfig.samples_per_cell,
    progress: Callable[[int], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Expected hit and miss counts (float32) on `grid` from (scan model, world pose, seed) triples.

    Samples are drawn in the scan frame from `seed`, so a pose correction moves the same
    samples and the same query always gives the same counts; they are traced as they are drawn,
    and only those of components that can reach the grid (gmm_core.scan_trace). `progress(1)`
    is told as each scan is traced.
    """
    counts = GridCounts(grid)
    for model, pose, seed in scans:
        counts.add(scan_samples(model, grid.resolution, seed, samples_per_cell), pose)
        if progress is not None:
            progress(1)
    hits, misses = counts.arrays()
    return hits.astype(np.float32), misses.astype(np.float32)


def count_beams(
    grid: Grid,
    beams: Iterable[tuple[np.ndarray, np.ndarray, Pose]],
    max_range: float,
    progress: Callable[[int], None] | None = None,
    threads: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The counting occupancy grid of raw beams: (hits, no-return directions, sensor pose) per scan.

    Hits are in the sensor frame; a no-return beam adds misses up to `max_range`. `threads`: as
    trace_rays (1 for a single scan: numba's threads cost more to start than its few rays).
    """

    def rays():
        for hits, no_return, pose in beams:
            ends = np.concatenate([hits, no_return * max_range])
            is_hit = np.concatenate([np.ones(len(hits), bool), np.zeros(len(no_return), bool)])
            yield pose.t, pose.apply(ends), np.ones(len(ends)), is_hit

    return trace_groups(grid, rays(), progress, threads=threads)
