"""Analytic evidence and occupancy at given cells (squares in 2D, cubes in 3D), without a grid:
one component (component_evidence), scan models with poses (scan_evidence, occupancy_at_cells).
Every component is tested against every cell, after the cone culling. An occupied component's
misses stop short of each sample (a cell, or three of its thinnest standard deviations), as the
Monte-Carlo tracer's do (gmm_core.scan_trace.hit_stop, evidence_2d, evidence_3d): the two methods of a
point query estimate the same counts."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from gmm_core.analytic.components import isotropic_maps, may_reach, world_components
from gmm_core.analytic.evidence_2d import cell_evidence_2d
from gmm_core.analytic.evidence_3d import cell_evidence_3d
from gmm_core.occupancy import DEFAULT_PRIOR, map_estimate


@njit(cache=True)
def _evidence_at_cell(
    c, centers, half, means, covs, isos, evals, evecs, sensors, max_range, counts, axes, dist_means, reaches,
    half_angles, hits, misses, fx, fy,
):  # fmt: skip
    """hits[c], misses[c]: expected hits and misses at cell c from every component that may reach it."""
    cell = centers[c]
    rho = half * math.sqrt(centers.shape[1])
    for k in range(means.shape[0]):
        if not may_reach(cell, rho, sensors[k], means[k], axes[k], dist_means[k], reaches[k], half_angles[k]):
            continue
        if centers.shape[1] == 2:
            h, m = cell_evidence_2d(
                means[k], covs[k], isos[k], sensors[k], max_range[k], cell[0], cell[1], half, fx, fy
            )
        else:
            h, m = cell_evidence_3d(
                means[k], evals[k], evecs[k], isos[k], sensors[k], max_range[k], cell[0], cell[1], cell[2], half
            )
        hits[c] += counts[k] * h
        misses[c] += counts[k] * m


@njit(cache=True, parallel=True)
def _evidence_at_cells(
    centers, half, means, covs, isos, evals, evecs, sensors, max_range, counts, axes, dist_means, reaches, half_angles
):
    """Expected hits and misses at each cell, the cells shared among numba's threads."""
    hits, misses = np.zeros(centers.shape[0]), np.zeros(centers.shape[0])
    for c in prange(centers.shape[0]):
        _evidence_at_cell(
            np.int64(c), centers, half, means, covs, isos, evals, evecs, sensors, max_range, counts, axes, dist_means,
            reaches, half_angles, hits, misses, np.empty(4), np.empty(4),
        )  # fmt: skip
    return hits, misses


@njit(cache=True, nogil=True)
def _evidence_at_cells_here(
    centers, half, means, covs, isos, evals, evecs, sensors, max_range, counts, axes, dist_means, reaches, half_angles
):
    """_evidence_at_cells on the calling thread alone, outside numba's threading layer (a map
    server's request threads may call it at the same time)."""
    hits, misses = np.zeros(centers.shape[0]), np.zeros(centers.shape[0])
    fx, fy = np.empty(4), np.empty(4)
    for c in range(centers.shape[0]):
        _evidence_at_cell(
            c, centers, half, means, covs, isos, evals, evecs, sensors, max_range, counts, axes, dist_means,
            reaches, half_angles, hits, misses, fx, fy,
        )  # fmt: skip
    return hits, misses


def as_cells(centers, cell_size: float, dim: int) -> tuple[np.ndarray, float]:
    centers = np.asarray(centers, dtype=np.float64)
    if centers.shape[-1] != dim:
        raise ValueError(f"centers are {centers.shape[-1]}D points, the component or scans are {dim}D")
    # writable and C-ordered, and c an int64 in _evidence_at_cells' prange: _evidence_at_cell is
    # compiled for one signature, not three (read-only centers cost 5.6 s more, the prange's index
    # 3.3 s, on a 2-core AMD EPYC: BENCHMARKS.md, twenty-ninth session)
    centers = np.require(centers.reshape(-1, dim), requirements=("C", "W"))
    if not (np.isfinite(cell_size) and cell_size > 0):
        raise ValueError(f"cell_size must be positive, got {cell_size}")
    return centers, 0.5 * float(cell_size)


def component_evidence(
    mean, cov, origin, centers, cell_size: float, *, max_range: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Hits and misses one Gaussian component gives each cell, as fractions of its mass.

    mean (d,), cov (d, d), origin (d,): the sensor; centers (M, d), cell_size: axis-aligned
    squares (d = 2) or cubes (d = 3). Hits are Eq. 10 (zero for a max-range component); misses
    the mass beyond the cell on rays from the origin (Eq. 3-9), plus the mass inside the cell
    for a max-range component. Multiply by N pi_k for expected counts.
    """
    mean = np.asarray(mean, dtype=np.float64).reshape(1, -1)
    cov = np.asarray(cov, dtype=np.float64).reshape(1, mean.shape[1], mean.shape[1])
    centers, half = as_cells(centers, cell_size, mean.shape[1])
    cov, evals, evecs, isos = isotropic_maps(cov)
    sensor = np.asarray(origin, dtype=np.float64).reshape(1, -1)
    everywhere = (np.ones_like(mean), np.zeros(1), np.full(1, np.inf), np.full(1, np.pi))  # no culling
    return _evidence_at_cells(
        centers, half, mean, cov, isos, evals, evecs, sensor, np.array([bool(max_range)]), np.ones(1), *everywhere
    )


def scan_evidence(
    models_with_poses, centers, cell_size: float, *, parallel: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Expected hit and miss counts (N_H, N_M of Eq. 11) at each cell from scan models with world
    poses, a list of (ScanModel, Pose) or (NodeComponents, Pose) (components.py: decomposed once).
    Only components whose 5-sigma cone reaches a cell count.
    `parallel`: on numba's threads; False: on the calling thread alone (safe from many threads)."""
    models_with_poses = list(models_with_poses)
    dim = models_with_poses[0][0].dim if models_with_poses else np.shape(centers)[-1]
    centers, half = as_cells(centers, cell_size, dim)
    comp = world_components(models_with_poses, dim)
    return (_evidence_at_cells if parallel else _evidence_at_cells_here)(
        centers,
        half,
        comp.means,
        comp.covs,
        comp.isos,
        comp.evals,
        comp.evecs,
        comp.sensors,
        comp.max_range,
        comp.counts,
        *comp.cone(),
    )


def occupancy_at_cells(
    models_with_poses, centers, cell_size: float, prior: float = DEFAULT_PRIOR, *, parallel: bool = True
) -> np.ndarray:
    """p(occupied) of each cell, Eq. 11, from the analytic evidence of scan models with world poses.

    models_with_poses: list of (ScanModel or NodeComponents, Pose); centers (M, d); cell_size: side of the square
    or cube; prior: N_p; parallel: as scan_evidence. Local occupancy evaluation for a few cells,
    without a grid.
    """
    hits, misses = scan_evidence(models_with_poses, centers, cell_size, parallel=parallel)
    return map_estimate(hits, misses, prior)
