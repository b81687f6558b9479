"""The OccupancyGrid's grid and cells, against plain loops."""

from __future__ import annotations

import numpy as np

from services.ros2.map_out import grid_cells, map_grid


def test_grid_covers_the_extent_on_whole_cells():
    grid = map_grid(np.array([-1.23, 4.01]), np.array([2.5, 6.0]), 0.1, 10**6)
    np.testing.assert_allclose(grid.origin, [-1.3, 4.0])
    assert np.all(grid.upper >= [2.5 - 1e-9, 6.0 - 1e-9]) and grid.shape == (38, 20)


def test_grid_is_cut_around_its_centre_to_the_cell_limit():
    grid = map_grid(np.array([0.0, 0.0]), np.array([100.0, 10.0]), 0.1, 10_000)
    assert np.prod(grid.shape) <= 10_000 and grid.shape[0] > grid.shape[1]
    centre = (grid.origin + grid.upper) / 2
    np.testing.assert_allclose(centre, [50.0, 5.0], atol=0.1)


def test_a_3d_grid_takes_the_z_band():
    grid = map_grid(np.array([0.0, 0.0, -3.0]), np.array([1.0, 1.0, 9.0]), 0.25, 10**6, (0.1, 1.9))
    np.testing.assert_allclose(grid.origin, [0.0, 0.0, 0.0])
    assert grid.shape == (4, 4, 8)


def test_cells_2d_and_3d_against_loops():
    rng = np.random.default_rng(3)
    prob = rng.choice([0.5, 0.0, 1.0, 0.234, 0.876, 0.5, 0.5], size=(4, 5, 6)).astype(np.float32)
    flat = grid_cells(prob[0])
    expect = [-1 if p == 0.5 else int(round(float(p) * 100)) for p in prob[0].ravel()]
    assert flat.dtype == np.int8 and flat.tolist() == expect
    projected = grid_cells(prob).reshape(5, 6)
    for iy in range(5):
        for ix in range(6):
            seen = [int(round(float(p) * 100)) for p in prob[:, iy, ix] if p != 0.5]
            assert projected[iy, ix] == (max(seen) if seen else -1)
