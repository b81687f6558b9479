"""The real BALM scans (Ouster OS0, ../shared/data/3d/balm-os0), subsampled for quick sequences."""

from __future__ import annotations

import numpy as np
import pytest

from support.paths import DATA

BALM = DATA / "3d" / "balm-os0"
BALM_NUMBERS = (0, 12, 24)  # the first three scan files; poses.txt line k is file k


def balm_points(step: int = 40) -> dict[int, np.ndarray]:
    """{number: every step-th point of that BALM scan, as the pcd reader reads it}; skips without the data."""
    if not BALM.is_dir():
        pytest.skip(f"real BALM scans {BALM} are absent (../shared/data beside the repository)")
    from services.datasets.pcd import read_pcd_points

    return {k: read_pcd_points(BALM / f"{k:06d}.pcd.gz")[::step] for k in BALM_NUMBERS}
