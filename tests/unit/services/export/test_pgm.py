"""The PGM + YAML pair read back as ROS map_server and Nav2 read it (a YAML parser, PIL, and their
thresholding rule), against the grid it was written from."""

from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from gmm_core import Grid
from gmm_core.occupancy import classify
from services.export import output_paths, write_export
from services.export.pgm import map_yaml
from services.export.sources import ExportMap
from services.render import top_down_classes
from support.ros_maps import grid_values, map_server_load


@pytest.mark.parametrize("variance", [0.21, 0.06, 0.25])
def test_2d_map_round_trip(tmp_path, variance):
    rng = np.random.default_rng(3)
    grid = Grid([-3.25, 10.5], 0.05, (40, 30))
    prob = rng.random(grid.array_shape).astype(np.float32)
    prob[0, :5] = 0.5  # unseen, in the min-y row
    paths = write_export(ExportMap(grid, prob), "pgm", tmp_path / "office", variance)
    assert paths == [tmp_path / "office.pgm", tmp_path / "office.yaml"]
    assert paths[0].read_bytes().startswith(b"P5\n40 30\n255\n")
    data, meta = map_server_load(paths[1])
    assert meta["image"] == "office.pgm" and meta["mode"] == "trinary" and meta["negate"] == 0
    assert meta["resolution"] == 0.05 and meta["origin"] == [-3.25, 10.5, 0.0]
    np.testing.assert_array_equal(data, grid_values(classify(prob, variance)))
    assert (data[0, :5] == -1).all()
    shades = set(np.unique(np.asarray(Image.open(paths[0]))).tolist())
    assert shades == {0, 205, 254}  # map_saver's trinary shades


def test_row_zero_of_the_image_is_the_largest_y(tmp_path):
    grid = Grid([0.0, 0.0], 1.0, (3, 2))
    prob = np.array([[0.9, 0.1, 0.1], [0.1, 0.1, 0.5]], np.float32)  # [iy, ix]: an occupied cell at (0.5, 0.5)
    write_export(ExportMap(grid, prob), "pgm", tmp_path / "m.pgm", 0.21)
    pixels = np.asarray(Image.open(tmp_path / "m.pgm"))
    np.testing.assert_array_equal(pixels, [[254, 254, 205], [0, 254, 254]])


def test_3d_map_is_seen_from_above(tmp_path):
    rng = np.random.default_rng(4)
    grid = Grid([1.0, 2.0, -1.0], 0.5, (6, 5, 4))
    prob = rng.random(grid.array_shape).astype(np.float32)
    write_export(ExportMap(grid, prob), "pgm", tmp_path / "mine.yaml", 0.21)
    data, meta = map_server_load(tmp_path / "mine.yaml")
    assert meta["origin"] == [1.0, 2.0, 0.0] and data.shape == (5, 6)
    np.testing.assert_array_equal(data, grid_values(top_down_classes(prob, 0.21)))


def test_thresholds_separate_the_three_shades_whatever_the_variance():
    """205 is occ = 0.196: Eq. 12's free threshold at sigma^2 = 0.21 (0.3) would read it as free, so the
    YAML holds map_saver's thresholds and says Eq. 12's in a comment."""
    for variance in (0.0, 0.06, 0.21, 0.25):
        text = map_yaml("m.pgm", Grid([0.0, 0.0], 0.1, (1, 1)), variance)
        meta = yaml.safe_load(text)
        assert (255 - 254) / 255 < meta["free_thresh"] <= (255 - 205) / 255 <= meta["occupied_thresh"] < 1.0
        assert f"sigma^2 = {variance!r}" in text.splitlines()[0]


def test_output_paths():
    assert output_paths("pgm", "a/map") == [Path("a/map.pgm"), Path("a/map.yaml")]
    assert output_paths("pgm", "a/map.yaml") == [Path("a/map.pgm"), Path("a/map.yaml")]
    assert output_paths("bt", "a/map") == [Path("a/map.bt")]
    assert output_paths("ply", "a/map.ply") == [Path("a/map.ply")]
    assert output_paths("ply", "a/map.v2") == [Path("a/map.v2.ply")]
