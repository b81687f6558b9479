"""A scan's voxels (gmm_core.voxels) against numpy: the voxel sums, the voxels counted, the
cells counted from the voxels."""

import numpy as np
import pytest

from gmm_core import em
from gmm_core.voxels import _count_cells, _voxel_statistics, count_voxels, voxel_tiers

TIERS = {"one size": [], "twice beyond 2.5": [2.5], "four sizes": [1.0, 2.0, 2.5]}


def numpy_voxel_statistics(points, size, shift, tiers):
    """_voxel_statistics by np.unique and np.add.at: the sums of em._features(x - shift) of the voxels
    of x (2^l `size` beyond l of the ranges `tiers`), the voxels in the order of their first point."""
    level = (np.linalg.norm(points, axis=1)[:, None] > np.asarray(tiers)[None, :]).sum(axis=1)
    voxel = np.column_stack([np.floor(points / (size * 2.0**level)[:, None]), level])
    cells, first, inverse = np.unique(voxel, axis=0, return_index=True, return_inverse=True)
    expected = np.zeros((len(cells), 1 + points.shape[1] * (points.shape[1] + 3) // 2))
    np.add.at(expected, inverse.ravel(), em._features(points - shift))
    return expected[np.argsort(first)]


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("tiers", TIERS.values(), ids=TIERS.keys())
def test_voxel_statistics_match_numpy(dim, tiers):
    # Beyond each range of `tiers` from the origin, voxels of twice the size (a voxel of each size per key).
    # Thousands of points: several of the blocks the points are summed in, voxels first met in each.
    rng = np.random.default_rng(0)
    points = np.repeat(rng.uniform(-3, 3, (1500, dim)), rng.integers(1, 5, 1500), axis=0)  # runs
    points = np.concatenate([points, rng.uniform(-3, 3, (300, dim))])
    shift = rng.uniform(-1, 1, dim)
    ranges = np.array(tiers, dtype=float)
    sums, keys = _voxel_statistics(points, 0.7, shift, ranges)
    level = (np.linalg.norm(points, axis=1)[:, None] > ranges[None, :]).sum(axis=1)
    assert set(level.tolist()) == set(range(len(tiers) + 1))
    expected = numpy_voxel_statistics(points, 0.7, shift, tiers)
    assert np.allclose(sums, expected, rtol=1e-12, atol=1e-9)
    assert len(np.unique(keys)) == len(keys) == len(expected)
    if not tiers:
        assert count_voxels(points, 0.7) == len(expected)
    assert count_voxels(points[:0], 0.7) == 0
    assert _voxel_statistics(points[:0], 0.7, shift, ranges)[0].shape == (0, sums.shape[1])
    # Thousands of voxels: the hash table grows from 1024 slots several times on the way.
    spread = rng.uniform(-50, 50, (6000, dim))
    assert count_voxels(spread, 0.05) == len(np.unique(np.floor(spread / 0.05), axis=0))
    spread_sums = _voxel_statistics(spread, 0.05, np.zeros(dim), ranges)[0]
    assert np.allclose(spread_sums, numpy_voxel_statistics(spread, 0.05, np.zeros(dim), tiers), rtol=1e-12, atol=1e-9)


def test_voxel_tiers_halve_the_voxels_twice_within_the_fine_range():
    finest, ranges, base = voxel_tiers(0.25, 3.0, 12.0)
    assert finest == 0.0625 and ranges.tolist() == [1.5, 3.0, 12.0] and base == 2
    finest, ranges, base = voxel_tiers(0.25, 0.0, np.inf)
    assert finest == 0.25 and ranges.tolist() == [] and base == 0
    with pytest.raises(ValueError, match="fine_range 12.0 m must lie within near_range 12.0 m"):
        voxel_tiers(0.25, 12.0, 12.0)


@pytest.mark.parametrize("dim", [2, 3])
def test_cells_counted_from_the_voxels_are_count_voxels_of_the_points(dim):
    # Cells of 4 voxels of 0.25 m (and 2 of 0.5 m, ...): the occupied 1 m cells of the points, on both
    # sides of the origin (floor division of negative voxel numbers) and on cell boundaries.
    rng = np.random.default_rng(7)
    points = np.concatenate([rng.uniform(-30, 30, (5000, dim)), rng.integers(-20, 20, (200, dim)).astype(float)])
    for voxel_size, ratio, tiers in (
        (0.25, 4, []),
        (0.5, 2, []),
        (0.25, 1, []),
        (0.25, 4, [12.0]),
        (0.5, 2, [12.0]),
        (0.0625, 16, [1.5, 3.0, 12.0]),  # the 3D defaults' tiers: 1 m cells of 16, 8, 4 and 2 voxels
    ):
        _, keys = _voxel_statistics(points, voxel_size, np.zeros(dim), np.array(tiers, dtype=float))
        assert _count_cells(keys, dim, ratio) == count_voxels(points, voxel_size * ratio)
