"""The kernels of offline maps compiled into numba's cache before the tests (numba_cache.WARM_UPS):
`services.replay.replay` by each method in 2D (the Monte-Carlo rays traced by numba's threads, the
analytic evidence, the counted beams) and in 3D, and the voxel fit with EM passes after its merge.
No server or robot warm-up calls them; left to the tests, three of them compiled them while they
ran, 20-23 s each on a fresh clone (docs/BENCHMARKS.md, thirty-first session).

    python -c "from support.offline_kernels import warm_offline_kernels; warm_offline_kernels()"
"""

from __future__ import annotations

import numpy as np

from gmm_core import FitConfig, Pose, fit_scan
from services.datasets import RangeScan
from services.replay import METHODS, replay


def _ring_scans(dim: int, n_scans: int = 3, beams: int = 360) -> list[RangeScan]:
    """Scans of a room about 3-4 m round, from poses 10 cm apart, with a few beams lost."""
    rng = np.random.default_rng(dim)
    scans = []
    for i in range(n_scans):
        angle = rng.uniform(-np.pi, np.pi, beams)
        up = rng.uniform(-0.3, 0.3, beams) if dim == 3 else np.zeros(beams)
        directions = np.column_stack([np.cos(angle), np.sin(angle), up][:dim])
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        ends = directions * rng.uniform(3.0, 4.0, (beams, 1))
        t = np.zeros(dim)
        t[0] = 0.1 * i
        scans.append(RangeScan(i, float(i), Pose(np.eye(dim), t), None, ends[10:], directions[:10]))
    return scans


def warm_offline_kernels() -> None:
    for dim in (2, 3):
        for method in METHODS:
            if method != "analytic" or dim == 2:
                replay(_ring_scans(dim), resolution=0.1, method=method)
    points = _ring_scans(3)[0].hits
    fit_scan(points, np.zeros((0, 3)), FitConfig(voxel_max_iter=2).for_dimension(3))
