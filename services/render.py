"""Occupancy probabilities as pictures: free white, occupied black, unknown grey."""
from __future__ import annotations

import io

import numpy as np
from PIL import Image


def project_3d(prob: np.ndarray) -> np.ndarray:
    """Top-down view of a [iz, iy, ix] map: a column is as occupied as its most occupied voxel,
    or, if none is above 0.5, as free as its freest one (all unknown stays 0.5)."""
    top, bottom = prob.max(axis=0), prob.min(axis=0)
    return np.where(top > 0.5, top, bottom)


def occupancy_image(prob: np.ndarray) -> Image.Image:
    """8-bit grey image, north up: row 0 of the image is the grid's largest y."""
    if prob.ndim == 3:
        prob = project_3d(prob)
    grey = np.round(255.0 * (1.0 - np.clip(prob, 0.0, 1.0))).astype(np.uint8)
    return Image.fromarray(grey[::-1], mode="L")


def occupancy_png(prob: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    occupancy_image(prob).save(buffer, format="PNG")
    return buffer.getvalue()
