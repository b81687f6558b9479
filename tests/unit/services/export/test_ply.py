"""The PLY writer read back by plyfile."""

import numpy as np
import pytest
from plyfile import PlyData

from gmm_core import Grid
from gmm_core.occupancy import OCCUPIED, classify
from services.export import write_export
from services.export.sources import ExportMap


@pytest.mark.parametrize(
    "grid", [Grid([-2.0, 3.5], 0.1, (30, 20)), Grid([-2.0, 3.5, -1.25], 0.25, (12, 10, 8))], ids=["2d", "3d"]
)
def test_occupied_cell_centres_with_their_probability(tmp_path, grid):
    rng = np.random.default_rng(5)
    prob = rng.random(grid.array_shape).astype(np.float32)
    (path,) = write_export(ExportMap(grid, prob), "ply", tmp_path / "cloud", 0.21)
    assert path == tmp_path / "cloud.ply"
    vertex = PlyData.read(path)["vertex"]
    occupied = classify(prob, 0.21).ravel() == OCCUPIED
    centres = grid.cell_centers()[occupied]
    assert vertex.count == occupied.sum() > 50
    points = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1)
    expected = np.pad(centres, ((0, 0), (0, 3 - grid.dim)))  # z = 0 on a 2D map
    np.testing.assert_allclose(points, expected, atol=1e-5)
    np.testing.assert_array_equal(vertex["probability"], prob.ravel()[occupied])
    assert (vertex["probability"] >= 0.7).all()


def test_a_larger_variance_calls_more_cells_occupied(tmp_path):
    grid = Grid([0.0, 0.0], 0.1, (50, 50))
    prob = np.random.default_rng(6).random(grid.array_shape).astype(np.float32)
    counts = []
    for variance in (0.06, 0.21):
        (path,) = write_export(ExportMap(grid, prob), "ply", tmp_path / f"v{variance}", variance)
        counts.append(PlyData.read(path)["vertex"].count)
    assert 0 < counts[0] < counts[1]
