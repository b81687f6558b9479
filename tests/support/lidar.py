"""Made-up spinning-lidar scans: a 64-ring one of an open outdoor scene (sparse far away, as a real
one is) and a 16-ring one down a rough tunnel (the mine sim's sensor)."""

from __future__ import annotations

import numpy as np

SENSOR_HEIGHT = 1.8  # m above the ground plane
WALLS = (40.0, 30.0)  # m: facades at x = +-40 and y = +-30 around the sensor
WALL_TOP = 8.0  # m above the sensor


def ring_scan(rng: np.random.Generator, rings: int = 64, columns: int = 1024, fov_deg: float = 45.0) -> np.ndarray:
    """(n, 3) returns in the sensor frame of `rings` beams over +-fov/2 of elevation and `columns`
    azimuths (an Ouster OS1-64's geometry): a ground plane and four facades, ranges 2-60 m, 1 cm of
    range noise; beams that reach neither within 60 m return nothing."""
    d = ring_directions(rings, columns, fov_deg)
    with np.errstate(divide="ignore"):
        ground = np.where(d[:, 2] < 0, -SENSOR_HEIGHT / d[:, 2], np.inf)
        facade = np.min(np.array(WALLS)[None, :] / np.abs(d[:, :2]), axis=1)
    facade = np.where(facade * d[:, 2] <= WALL_TOP, facade, np.inf)
    t = np.minimum(ground, facade)
    keep = (t >= 2.0) & (t <= 60.0)
    t = t[keep] + rng.normal(0.0, 0.01, keep.sum())
    return d[keep] * t[:, None]


def ring_directions(rings: int, columns: int, fov_deg: float) -> np.ndarray:
    """(rings * columns, 3) unit beams: `rings` elevations over +-fov/2, `columns` azimuths a ring."""
    elevation = np.radians(np.linspace(-fov_deg / 2, fov_deg / 2, rings))
    azimuth = np.linspace(0, 2 * np.pi, columns, endpoint=False)
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)


def tunnel_scan(
    rng: np.random.Generator, radius: float = 2.0, rough: float = 0.15, max_range: float = 30.0
) -> tuple[np.ndarray, np.ndarray]:
    """(hits, no-return directions) of a 16-ring lidar (+-15 deg, 1800 azimuths) on the axis of a
    tunnel along x whose radius varies by up to 1.5 `rough` with x and the angle around the axis
    (as the mine sim's noisy walls do), 2 cm of range noise."""
    d = ring_directions(16, 1800, 30.0)
    across = np.hypot(d[:, 1], d[:, 2])
    t = radius / across
    for _ in range(12):  # the range where the ray meets the wall's radius there (a fixed point)
        q = d * t[:, None]
        angle = np.arctan2(q[:, 2], q[:, 1])
        wall = radius + rough * (
            np.sin(2.7 * q[:, 0] + 1.3) * np.sin(3 * angle) + 0.5 * np.sin(7.1 * q[:, 0]) * np.cos(5 * angle + 0.4)
        )
        t = wall / across
    keep = t <= max_range
    return d[keep] * (t[keep] + rng.normal(0.0, 0.02, keep.sum()))[:, None], d[~keep]
