"""Occupied cells as a point cloud: a binary PLY of cell centres with their probability."""

from __future__ import annotations

import numpy as np

from gmm_core import Grid
from gmm_core.occupancy import OCCUPIED, classify

VERTEX = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("probability", "<f4")])


def ply_bytes(prob: np.ndarray, grid: Grid, variance: float) -> bytes:
    """The centres of the cells occupied by Eq. 12 at sigma^2 = `variance` (z = 0 on a 2D map), each
    with its probability p, as `binary_little_endian` PLY."""
    index = np.nonzero(classify(prob, variance) == OCCUPIED)  # array order: ([iz,] iy, ix)
    vertices = np.zeros(len(index[0]), dtype=VERTEX)
    for axis, name in enumerate("xyz"[: grid.dim]):
        vertices[name] = grid.origin[axis] + (index[grid.dim - 1 - axis] + 0.5) * grid.resolution
    vertices["probability"] = prob[index]
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"comment gmmap export: centres of the cells occupied by Eq. 12 at sigma^2 = {variance!r}, "
        f"{grid.resolution!r} m cells\n"
        f"element vertex {len(vertices)}\n"
        + "".join(f"property float {name}\n" for name in VERTEX.names)
        + "end_header\n"
    )
    return header.encode("ascii") + vertices.tobytes()
