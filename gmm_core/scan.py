"""One scan as two mixtures: occupied (hit points) and free (no-return beams), Sec. III-A/B."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TypeVar

import numpy as np

from gmm_core.em import fit_mixture
from gmm_core.mixture import Mixture
from gmm_core.rings import ring_spacing
from gmm_core.validation import require_count, require_number
from gmm_core.voxel_em import count_voxels, fit_mixture_voxels

T = TypeVar("T")


@dataclass(frozen=True)
class ScanModel:
    """The evidence a scan carries, in the scan's own (sensor/node) frame.

    `occupied` models the hit points; `free` models the end points of no-return beams, placed
    at `max_range` from `origin`. Rays from `origin` to samples of either mixture give free-space
    evidence (Sec. III-C3); only samples of `occupied` give hits.
    """

    occupied: Mixture
    free: Mixture
    origin: np.ndarray  # (d,) sensor origin in the node frame
    max_range: float  # truncation range of no-return beams, metres

    def __post_init__(self):
        origin = np.asarray(self.origin, dtype=np.float64)
        if origin.shape != (self.occupied.dim,) or self.free.dim != self.occupied.dim:
            raise ValueError("scan model: origin and both mixtures must share one dimension")
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "max_range", float(self.max_range))

    @property
    def dim(self) -> int:
        return self.occupied.dim

    @property
    def n_components(self) -> int:
        return self.occupied.n_components + self.free.n_components


POINTS_PER_COMPONENT = 3.0  # a 2D scan's points per component (Sec. IV-C)
# A 3D scan's points per component at least: at about 13 bytes a component in `q`, a message is
# then at most 3.7 % of its points' float32 xyz at any density. A sparse or long-range scan
# occupies a 1 m cell every few points, so the cells alone let it send 11-14 % (BALM scans
# stretched to 60 m); with 30, AUROC at 10 % of BALM's points rose (docs/BENCHMARKS.md, seventeenth session).
DENSE_3D_POINTS_PER_COMPONENT = 30.0
DENSE_3D_COMPONENT_SIZE = 1.0  # m: a dense 3D scan gets about one component per square metre of surface
DENSE_3D_VOXEL_SIZE = 0.25  # m: 3D EM runs on the statistics of voxels this size (docs/BENCHMARKS.md, issue 15)
# m: beyond this range from the sensor, voxels of twice the size (docs/BENCHMARKS.md, issue 15 part 3)
DENSE_3D_VOXEL_NEAR_RANGE = 12.0
# m: within this range of a cloud without rings, voxels of half the size, and within half of it a
# quarter, where the points are densest. Kurt3D's first scan (57 % of its points within 2 m) reaches
# scikit-learn's converged EM with the same K from 4.5 m (with the EM below); 2.5 m fell 0.058 nats a
# point short, 5 m fitted its sparser subsamples worse (docs/BENCHMARKS.md, thirty-eighth session).
DENSE_3D_VOXEL_FINE_RANGE = 4.5
# EM passes over the voxels of a cloud without rings after they are merged into groups (voxel_merge),
# each voxel's candidate components searched again every DENSE_3D_VOXEL_SEARCH_EVERY-th pass: the
# groups' hard boundaries cut through what EM shares between components where such a cloud is dense
# (with the fine voxels to 4.5 m, +0.059 nats a point on Kurt3D's first scan, to scikit-learn's, for
# 2.7x its fit; without the searches EM stalls 0.014 lower). On a lidar's rings the groups alone end
# above scikit-learn's EM (BALM, whose fit keeps up with the sensor: 8 passes gained 0.05 for 1.9x;
# docs/BENCHMARKS.md, twenty-second and thirty-eighth sessions).
DENSE_3D_VOXEL_MAX_ITER = 12
DENSE_3D_VOXEL_SEARCH_EVERY = 4


def _given(value: T | None, default: T) -> T:
    """A setting's value, its default where it is unset (None)."""
    return default if value is None else value


@dataclass(frozen=True)
class FitConfig:
    """How a scan becomes mixtures (the `fit` section of the configuration).

    The number of components follows the data and a target resolution (Sec. IV-C): about
    `points_per_component` points each, so a sparse scan gets few and a dense one many, but no
    more than the cells of size `component_size` that the points occupy (a dense 3D scan needs
    one component per patch of surface, not one per three points), and no more than
    `max_components`, which bounds the message size. `for_dimension` resolves the defaults that
    depend on the scan: `points_per_component` None means `POINTS_PER_COMPONENT` in 2D and
    `DENSE_3D_POINTS_PER_COMPONENT` in 3D (which bounds a 3D message to a few per cent of its
    points' bytes); `component_size` None means none in 2D and `DENSE_3D_COMPONENT_SIZE` in 3D;
    `voxel_size` applies to 3D scans only (2D scans are fitted on their points) and None means
    `DENSE_3D_VOXEL_SIZE`; `voxel_near_range` None means `DENSE_3D_VOXEL_NEAR_RANGE`: beyond that
    range from the sensor the voxels are twice `voxel_size`, where a lidar's rings lie farther
    apart than a voxel; `voxel_fine_range` None means `DENSE_3D_VOXEL_FINE_RANGE`: within it they
    are half `voxel_size`, within half of it a quarter, where the points are densest.
    `voxel_max_iter` None means `DENSE_3D_VOXEL_MAX_ITER`.

    With `voxel_size` > 0, the voxels are merged bottom-up into the components
    (gmm_core.voxel_merge), then EM runs on the summed statistics of the voxels for at most
    `voxel_max_iter` passes (gmm_core.voxel_em): a 3D scan of 80k points in milliseconds. With 0,
    EM runs on the points themselves (gmm_core.em).

    The fine voxels and the EM apply to clouds without a spinning lidar's rings (gmm_core.rings
    finds none: a tilting scanner, a depth camera), which are dense in both directions near the
    sensor: Kurt3D's first scan gained 0.19 nats a point, to scikit-learn's. A lidar's near field is the ground
    under it, sampled along its rings: there they gained BALM 0.009 nats a point for 13 % of its
    fit, which has to keep up with the sensor (docs/BENCHMARKS.md, thirty-seventh session).
    """

    points_per_component: float | None = None  # > 0; None: POINTS_PER_COMPONENT in 2D, DENSE_3D_... in 3D
    component_size: float | None = None  # m, > 0; None: none in 2D, DENSE_3D_COMPONENT_SIZE in 3D
    max_components: int = 4096  # per mixture, >= 1
    max_range: float = 10.0  # m, where no-return beams end (long free rays bleed through walls)
    reg_covar: float = 1e-4  # m^2, variance floor: about the sensor's 1 cm range noise
    max_iter: int = 100  # EM iterations, >= 1
    tol: float = 1e-3  # EM stops when the mean log-likelihood gains less than this, nats per point
    voxel_size: float | None = None  # m, >= 0, 3D only, 0: no voxels; None: DENSE_3D_VOXEL_SIZE
    voxel_max_iter: int | None = None  # EM passes over the voxels, >= 0; None: DENSE_3D_VOXEL_MAX_ITER
    voxel_near_range: float | None = None  # m, > 0: voxels twice voxel_size beyond; None: DENSE_3D_VOXEL_NEAR_RANGE
    voxel_fine_range: float | None = None  # m, >= 0, < voxel_near_range: half voxel_size within (no rings), 0: none

    def __post_init__(self):
        for name in ("max_range", "reg_covar"):
            require_number(f"fit.{name}", getattr(self, name), positive=True)
        if self.points_per_component is not None:
            require_number("fit.points_per_component", self.points_per_component, positive=True)
        require_number("fit.tol", self.tol, positive=False)
        if self.component_size is not None:
            require_number("fit.component_size", self.component_size, positive=True)
        if self.voxel_size is not None:
            require_number("fit.voxel_size", self.voxel_size, positive=False)
        for name in ("max_components", "max_iter"):
            require_count(f"fit.{name}", getattr(self, name))
        if self.voxel_max_iter is not None:
            require_count("fit.voxel_max_iter", self.voxel_max_iter, minimum=0)
        if self.voxel_near_range is not None:
            require_number("fit.voxel_near_range", self.voxel_near_range, positive=True)
        if self.voxel_fine_range is not None:
            require_number("fit.voxel_fine_range", self.voxel_fine_range, positive=False)
        near = _given(self.voxel_near_range, DENSE_3D_VOXEL_NEAR_RANGE)
        fine = _given(self.voxel_fine_range, DENSE_3D_VOXEL_FINE_RANGE)
        if not fine < near:
            raise ValueError(f"fit.voxel_fine_range: must be less than fit.voxel_near_range ({near} m), got {fine} m")

    def for_dimension(self, dim: int) -> FitConfig:
        """This configuration as it applies to scans of dimension `dim` (2 or 3)."""
        voxel_size = self.voxel_size if self.voxel_size is not None else DENSE_3D_VOXEL_SIZE
        resolved = replace(
            self,
            points_per_component=self._points_per_component(dim),
            component_size=DENSE_3D_COMPONENT_SIZE if self.component_size is None and dim == 3 else self.component_size,
            voxel_size=voxel_size if dim == 3 else 0.0,
            voxel_max_iter=_given(self.voxel_max_iter, DENSE_3D_VOXEL_MAX_ITER),
            voxel_near_range=_given(self.voxel_near_range, DENSE_3D_VOXEL_NEAR_RANGE),
            voxel_fine_range=_given(self.voxel_fine_range, DENSE_3D_VOXEL_FINE_RANGE),
        )
        return self if resolved == self else resolved

    def n_components(self, points: np.ndarray) -> int:
        if len(points) == 0:
            return 0
        k = self.n_components_of_count(len(points), points.shape[1])
        if self.component_size is not None:
            k = min(k, count_voxels(points, float(self.component_size)))
        return max(1, k)

    def n_components_of_count(self, n_points: int, dim: int) -> int:
        """n_components without the cap of occupied cells (which the voxel fit counts itself)."""
        per_component = self._points_per_component(dim)
        return max(1, min(int(np.ceil(n_points / per_component)), self.max_components))

    def _points_per_component(self, dim: int) -> float:
        if self.points_per_component is not None:
            return self.points_per_component
        return DENSE_3D_POINTS_PER_COMPONENT if dim == 3 else POINTS_PER_COMPONENT


def fit_scan(hits: np.ndarray, no_return: np.ndarray, config: FitConfig = FitConfig()) -> ScanModel:
    """Fit the occupied mixture to `hits` (n, d) and the free mixture to the no-return beams.

    Both inputs are in the sensor frame, whose origin is the sensor. `no_return` holds unit
    directions of beams without a return; their end points are placed at `config.max_range`.
    """
    hits = np.asarray(hits, dtype=np.float64)
    no_return = np.asarray(no_return, dtype=np.float64)
    dim = hits.shape[1]
    config = config.for_dimension(dim)
    ends = no_return.reshape(-1, dim) * config.max_range

    def fit(points: np.ndarray) -> Mixture:
        if config.voxel_size:
            points = np.ascontiguousarray(points)
            rings = ring_spacing(points)
            ringless = rings == 0.0  # the fine voxels and the EM: see FitConfig
            passes = min(config.max_iter, _given(config.voxel_max_iter, DENSE_3D_VOXEL_MAX_ITER))
            return fit_mixture_voxels(
                points,
                config.n_components_of_count(len(points), dim),
                config.voxel_size,
                cell_size=config.component_size,
                near_range=_given(config.voxel_near_range, DENSE_3D_VOXEL_NEAR_RANGE),
                fine_range=_given(config.voxel_fine_range, DENSE_3D_VOXEL_FINE_RANGE) if ringless else 0.0,
                reg_covar=config.reg_covar,
                max_iter=passes if ringless else 0,
                tol=config.tol,
                search_every=DENSE_3D_VOXEL_SEARCH_EVERY,
                rings=rings,
            )
        k = config.n_components(points)
        return fit_mixture(points, k, reg_covar=config.reg_covar, max_iter=config.max_iter, tol=config.tol)

    return ScanModel(fit(hits), fit(ends), np.zeros(dim), config.max_range)
