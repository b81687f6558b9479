"""Occupancy as 8-bit grey pictures, north up (row 0 of the image is the grid's largest y).

What a map shows people is the classification of Eq. 12 (`occupancy_png`): free white, occupied
black, unknown grey, where a cell is free for p <= (1 - sqrt(1 - 4 sigma^2)) / 2, occupied for
p >= (1 + sqrt(1 - 4 sigma^2)) / 2 and unknown in the dead band between (and at p = 0.5, nothing
seen). sigma^2 is the `variance` parameter, DEFAULT_VARIANCE unless given (0.21: thresholds 0.3 and
0.7; gmm_core.occupancy says why).
The continuous picture, grey = 1 - p (`probability_png`), stays for looking at the evidence itself;
both draw p = 0.5 in the same mid grey.

3D maps are seen from above. Classes: each voxel is classified, then a column is occupied if any
voxel is, free if none is and some is free, unknown if all are unknown. A dead-band voxel counts as
unobserved there, not as a veto on free: the dead band is Eq. 12's statement that its evidence
decides nothing, and as a veto it would leave almost no column free (Kurt3D at 0.25 m and sigma^2 =
0.06: 49 free columns instead of 1561, as nearly every column holds a voxel in the band).
Probabilities: a column is as occupied as its most occupied voxel or, if none is above 0.5, as free
as its freest one.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np
from numba import njit

from gmm_core.occupancy import DEFAULT_VARIANCE, FREE, OCCUPIED, UNKNOWN, class_bounds

CLASS_GREY = {FREE: 255, OCCUPIED: 0, UNKNOWN: 128}  # 128: the grey of p = 0.5 in the probability picture


def top_down_probability(prob: np.ndarray) -> np.ndarray:
    """A [iz, iy, ix] probability map seen from above, [iy, ix]."""
    top, bottom = prob.max(axis=0), prob.min(axis=0)
    return np.where(top > 0.5, top, bottom)


def top_down_classes(prob: np.ndarray, variance: float) -> np.ndarray:
    """The Eq. 12 classes of a 2D map, or of a [iz, iy, ix] map seen from above (rule in the module
    docstring), [iy, ix]."""
    return _labels(prob, variance, np.int8, {c: c for c in CLASS_GREY})


def class_grey(prob: np.ndarray, variance: float = DEFAULT_VARIANCE) -> np.ndarray:
    """[iy, ix] grey levels of the Eq. 12 classes of a 2D or 3D probability map, CLASS_GREY's."""
    return _labels(prob, variance, np.uint8, CLASS_GREY)


def _labels(prob: np.ndarray, variance: float, dtype: type, label: dict[int, int]) -> np.ndarray:
    """[iy, ix] label[class] of each column's class, in one pass over the cells: a server draws a
    tile's picture on every change of it, and numpy's masks took 1.1 ms of a 256 x 256 tile
    (docs/BENCHMARKS.md, thirteenth session)."""
    free_max, occupied_min = class_bounds(variance)
    columns = prob if prob.ndim == 3 else prob[None]
    out = np.empty(columns.shape[1:], dtype)
    _column_labels(columns, free_max, occupied_min, label[FREE], label[OCCUPIED], label[UNKNOWN], out)
    return out


@njit(cache=True, nogil=True)
def _column_labels(columns, free_max, occupied_min, free, occupied, unknown, out):
    """out[iy, ix]: `occupied` if a voxel of column (iy, ix) is, else `free` if one is, else `unknown`."""
    for iy in range(columns.shape[1]):
        for ix in range(columns.shape[2]):
            label = unknown
            for iz in range(columns.shape[0]):
                p = columns[iz, iy, ix]
                if p >= occupied_min and p > 0.5:
                    label = occupied
                    break
                if p <= free_max and p < 0.5:
                    label = free
            out[iy, ix] = label


def probability_grey(prob: np.ndarray) -> np.ndarray:
    """[iy, ix] grey levels 255 (1 - p) of a 2D or 3D probability map."""
    if prob.ndim == 3:
        prob = top_down_probability(prob)
    return np.round(255.0 * (1.0 - np.clip(prob, 0.0, 1.0))).astype(np.uint8)


def _png(grey: np.ndarray) -> bytes:
    """An [iy, ix] grid of grey levels as an 8-bit greyscale PNG, north up: rows unfiltered, deflated
    at zlib's fastest level (a 256 x 256 tile of classes in 0.13 against PIL's 0.53 ms, and smaller:
    rows of three grey levels compress well without PNG's filters; docs/BENCHMARKS.md)."""
    height, width = grey.shape
    rows = np.zeros((height, width + 1), np.uint8)  # each row: filter type 0 (none), then its pixels
    rows[:, 1:] = grey[::-1]
    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)  # 8 bits, grey, deflate, no interlace
    return (
        b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(rows, 1)) + _chunk(b"IEND", b"")
    )


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def occupancy_png(prob: np.ndarray, variance: float = DEFAULT_VARIANCE) -> bytes:
    """The Eq. 12 classes of a 2D or 3D map with sigma^2 = `variance` in [0, 0.25], as a PNG."""
    return _png(class_grey(prob, variance))


def probability_png(prob: np.ndarray) -> bytes:
    """The probabilities of a 2D or 3D map as a PNG, grey = 1 - p."""
    return _png(probability_grey(prob))
