"""Reading a PGM + YAML map pair as ROS map_server and Nav2's map server read it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from gmm_core.occupancy import FREE, OCCUPIED


def map_server_load(yaml_path: Path) -> tuple[np.ndarray, dict]:
    """nav_msgs/OccupancyGrid values (100, 0, -1; row 0 at the min y) and the YAML, as map_server's
    trinary loader makes them: occ = (255 - v) / 255 with negate 0, occupied above occupied_thresh,
    free below free_thresh."""
    meta = yaml.safe_load(yaml_path.read_text())
    image = Image.open(yaml_path.parent / meta["image"])
    assert image.format == "PPM" and image.mode == "L"  # PIL's name for the PGM family (P5 here)
    occ = (255 - np.asarray(image, dtype=np.float64)) / 255.0
    if meta["negate"]:
        occ = 1.0 - occ
    data = np.where(occ > meta["occupied_thresh"], 100, np.where(occ < meta["free_thresh"], 0, -1))
    return data[::-1], meta  # the loader puts image row 0 at the top: the largest y


def grid_values(classes: np.ndarray) -> np.ndarray:
    """The OccupancyGrid values of Eq. 12 classes: 100 occupied, 0 free, -1 unknown."""
    return np.select([classes == OCCUPIED, classes == FREE], [100, 0], -1)
