"""Simulated range sensors: a 2D laser scanner and a 16-ring spinning 3D lidar, with range noise."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from gmm_core.pose import Pose
from services.datasets.common import RangeScan
from services.sim.worlds import World


@dataclass(frozen=True)
class Laser2D:
    """A planar scanner: `beams` evenly over 360 degrees, the first at -180 degrees."""

    beams: int = 360
    max_range: float = 30.0  # m
    noise: float = 0.01  # m, std of Gaussian range noise

    @property
    def dim(self) -> int:
        return 2


@dataclass(frozen=True)
class Lidar3D:
    """A spinning lidar: `rings` elevations evenly over +-`elevation_deg`, `azimuth_steps` per turn."""

    rings: int = 16
    elevation_deg: float = 15.0
    azimuth_steps: int = 1800
    max_range: float = 100.0  # m
    noise: float = 0.02  # m

    @property
    def dim(self) -> int:
        return 3


Sensor = Laser2D | Lidar3D


@lru_cache(maxsize=8)
def beam_directions(sensor: Sensor) -> np.ndarray:
    """(n, d) unit beam directions in the sensor frame (x forward, z up)."""
    if isinstance(sensor, Laser2D):
        angle = -np.pi + np.arange(sensor.beams) * (2 * np.pi / sensor.beams)
        directions = np.column_stack([np.cos(angle), np.sin(angle)])
    else:
        # Firing order: all rings at one azimuth, then the next azimuth.
        azimuth, elevation = np.meshgrid(
            np.arange(sensor.azimuth_steps) * (2 * np.pi / sensor.azimuth_steps),
            np.radians(np.linspace(-sensor.elevation_deg, sensor.elevation_deg, sensor.rings)),
            indexing="ij",
        )
        azimuth, elevation = azimuth.ravel(), elevation.ravel()
        directions = np.column_stack(
            [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
        )
    directions.setflags(write=False)
    return directions


def sensor_for(world: World) -> Sensor:
    """The default sensor of a world: the 2D laser on floor plans, the 3D lidar in the mine."""
    return Laser2D() if world.dim == 2 else Lidar3D()


def simulate_scan(
    world: World,
    sensor: Sensor,
    pose: Pose,
    rng: np.random.Generator,
    *,
    index: int = 0,
    stamp: float = 0.0,
    odom_pose: Pose | None = None,
) -> RangeScan:
    """One scan from the sensor at the true `pose`: noisy hits and no-return directions, sensor frame."""
    if sensor.dim != world.dim or pose.dim != world.dim:
        raise ValueError(f"sensor and pose must be {world.dim}D in the {world.name} world")
    directions = beam_directions(sensor)
    ranges = world.cast(pose.t, directions @ pose.R.T, sensor.max_range)
    hit = np.isfinite(ranges)
    measured = ranges[hit] + rng.normal(0.0, sensor.noise, int(hit.sum()))
    return RangeScan(
        index=index,
        stamp=stamp,
        pose=pose,
        odom_pose=odom_pose,
        hits=np.ascontiguousarray(directions[hit] * measured[:, None]),
        no_return=np.ascontiguousarray(directions[~hit]),
    )
