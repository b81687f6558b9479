"""Occupancy as a ROS map: an 8-bit PGM (P5) and the YAML that ROS map_server and Nav2's map
server load it with (the layout map_saver writes).

Conventions of map_server: row 0 of the image is the top of the map (its largest y); `origin` is
the pose [x, y, yaw] of the lower-left corner of the lower-left pixel, here the grid's min corner
with yaw 0. A loader reads a pixel v as occupied with probability occ = (255 - v) / 255
(negate 0) and, in trinary mode, calls it occupied when occ > occupied_thresh, free when occ <
free_thresh, unknown otherwise.

The pixels are the classes of Eq. 12 at sigma^2 = `variance` (gmm_core.occupancy.classify):
occupied 0, free 254, unknown 205, map_saver's trinary shades. The thresholds written are
map_saver's (ROS 1) 0.65 and 0.196, which read those three shades back as exactly those classes
(205 is occ = 0.19608: above 0.196, below 0.65). Eq. 12's own thresholds cannot go there: at the
default sigma^2 = 0.21 its free threshold is 0.3, and a loader would read every unknown pixel as
free; they are written in a comment instead. A 3D map becomes its top-down classes, as the PNGs
show it (services.render: a column is occupied if any voxel is, free if none is and one is free).
"""

from __future__ import annotations

import json

import numpy as np

from gmm_core import Grid
from gmm_core.occupancy import FREE, OCCUPIED, UNKNOWN, class_bounds

SHADE = {OCCUPIED: 0, FREE: 254, UNKNOWN: 205}  # map_saver's trinary pixels
OCCUPIED_THRESH = 0.65  # read back: occ = 1 > 0.65
FREE_THRESH = 0.196  # read back: occ = 1/255 < 0.196 <= 50/255 (unknown's)


def pgm_bytes(classes: np.ndarray) -> bytes:
    """A binary PGM of [iy, ix] classes, north up."""
    pixels = np.full(classes.shape, SHADE[UNKNOWN], dtype=np.uint8)
    pixels[classes == OCCUPIED] = SHADE[OCCUPIED]
    pixels[classes == FREE] = SHADE[FREE]
    height, width = classes.shape
    return f"P5\n{width} {height}\n255\n".encode("ascii") + pixels[::-1].tobytes()


def map_yaml(image: str, grid: Grid, variance: float) -> str:
    """The map_server YAML of the PGM file `image` (a path relative to the YAML's folder)."""
    free_max, occupied_min = class_bounds(variance)
    x, y = (float(v) for v in grid.origin[:2])
    return (
        f"# gmmap export: the classes of Eq. 12 at sigma^2 = {variance!r}: free for p <= {free_max:.6g}, "
        f"occupied for p >= {occupied_min:.6g}\n"
        + (
            f"# a 3D map seen from above, z {float(grid.origin[2])!r} .. {float(grid.upper[2])!r} m\n"
            if grid.dim == 3
            else ""
        )
        + f"image: {json.dumps(image)}\n"
        "mode: trinary\n"
        f"resolution: {grid.resolution!r}\n"
        f"origin: [{x!r}, {y!r}, 0.0]\n"
        "negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH}\n"
        f"free_thresh: {FREE_THRESH}\n"
    )
