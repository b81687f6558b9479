"""A 64-ring lidar scan of an open outdoor scene, made up: sparse far away, as a real one is."""

from __future__ import annotations

import numpy as np

SENSOR_HEIGHT = 1.8  # m above the ground plane
WALLS = (40.0, 30.0)  # m: facades at x = +-40 and y = +-30 around the sensor
WALL_TOP = 8.0  # m above the sensor


def ring_scan(rng: np.random.Generator, rings: int = 64, columns: int = 1024, fov_deg: float = 45.0) -> np.ndarray:
    """(n, 3) returns in the sensor frame of `rings` beams over +-fov/2 of elevation and `columns`
    azimuths (an Ouster OS1-64's geometry): a ground plane and four facades, ranges 2-60 m, 1 cm of
    range noise; beams that reach neither within 60 m return nothing."""
    elevation = np.radians(np.linspace(-fov_deg / 2, fov_deg / 2, rings))
    azimuth = np.linspace(0, 2 * np.pi, columns, endpoint=False)
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        ground = np.where(d[:, 2] < 0, -SENSOR_HEIGHT / d[:, 2], np.inf)
        facade = np.min(np.array(WALLS)[None, :] / np.abs(d[:, :2]), axis=1)
    facade = np.where(facade * d[:, 2] <= WALL_TOP, facade, np.inf)
    t = np.minimum(ground, facade)
    keep = (t >= 2.0) & (t <= 60.0)
    t = t[keep] + rng.normal(0.0, 0.01, keep.sum())
    return d[keep] * t[:, None]
