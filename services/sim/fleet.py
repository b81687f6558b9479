"""A simulated fleet: one seeded world, and every robot's path, odometry and scan stream.

Each robot's agent and the `gmmap sim` harness that grades the map build the fleet from the
same five numbers (world, robots, scans, rate, seed) and get the same paths, odometry and
beams: nothing else crosses between the processes.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from services.datasets.common import RangeScan
from services.sim.sensor import sensor_for
from services.sim.trajectory import ClosureSchedule, Motion, OdometryNoise, odometry, plan_paths, robot_events
from services.sim.worlds import WORLDS, make_world

DEFAULT_RATE = 5.0  # scans per second when the agent publishes as fast as it can
CORRECTION_PERIOD_S = 10.0  # a loop closure (pose-graph update) every 10 s of driving
# Robots sharing a process (services.sim.robots) simulate one scan at a time: the world's
# parallel numba kernels must not be entered from two threads at once (workqueue layer).
_SIMULATING = threading.Lock()
_BUILDING = threading.Lock()


@dataclass(frozen=True)
class SimSource:
    """`sim:WORLD:INDEX:ROBOTS[:SEED]`: robot INDEX of a fleet of ROBOTS in the seeded world."""

    world: str
    index: int
    robots: int
    seed: int = 0

    @staticmethod
    def parse(text: str) -> SimSource:
        parts = text.split(":")
        try:
            if len(parts) not in (4, 5) or parts[0] != "sim":
                raise ValueError
            source = SimSource(parts[1], *(int(p) for p in parts[2:]))
        except ValueError:
            raise ValueError(f"--source: expected sim:WORLD:INDEX:ROBOTS[:SEED], got {text!r}") from None
        if source.world not in WORLDS:
            raise ValueError(f"--source: world must be one of {sorted(WORLDS)}, got {source.world!r}")
        if not (0 <= source.index < source.robots):
            raise ValueError(f"--source: INDEX must lie in [0, ROBOTS), got {source.index} of {source.robots}")
        return source

    def __str__(self) -> str:
        return f"sim:{self.world}:{self.index}:{self.robots}:{self.seed}"


def correction_interval(rate: float) -> int:
    """Scans between loop closures at `rate` scans per second."""
    return max(1, round(CORRECTION_PERIOD_S * rate))


def shared_fleet(world: str, robots: int, scans: int, rate: float, seed: int) -> SimulatedFleet:
    """One SimulatedFleet per process for robots of the same run (services.sim.robots), built once
    however many robot threads ask for it at the same time."""
    with _BUILDING:
        return _fleet(world, robots, scans, rate, seed)


@lru_cache(maxsize=4)
def _fleet(world: str, robots: int, scans: int, rate: float, seed: int) -> SimulatedFleet:
    return SimulatedFleet(world, robots, scans, rate, seed)


def robot_name(index: int) -> str:
    return f"r{index}"


class SimulatedFleet:
    """`robots` paths of `scans` poses each, `speed / rate` apart, with drifting odometry."""

    def __init__(
        self, world: str, robots: int, scans: int, rate: float = DEFAULT_RATE, seed: int = 0, spread_closures=True
    ):
        self.world = make_world(world, seed)
        self.sensor = sensor_for(self.world)
        self.rate = rate
        self.seed = seed
        self.spread_closures = spread_closures  # False: every robot closes its loops at the same instant
        self.paths = plan_paths(self.world, robots, scans, seed, Motion(rate=rate))
        self.odometry = [
            odometry(path, OdometryNoise(), np.random.default_rng([seed, 7, i])) for i, path in enumerate(self.paths)
        ]

    @property
    def robots(self) -> int:
        return len(self.paths)

    def closures(self, index: int, correct_every: int) -> ClosureSchedule:
        """Robot `index`'s loop closures, one every `correct_every` scans (0: never)."""
        return ClosureSchedule.of_robot(index, self.robots, correct_every, self.spread_closures)

    def scans(self, index: int, correct_every: int) -> Iterator[RangeScan]:
        """Robot `index`'s scans, simulated one by one: `pose` true, `odom_pose` its own estimate.

        The estimate is odometry chained onto the latest loop closure (`closures`), so it equals
        what the robot knows when it publishes the scan.
        """
        noise_seed = int(np.random.SeedSequence([self.seed, 11, index]).generate_state(1)[0])
        events = robot_events(
            self.world,
            self.sensor,
            self.paths[index],
            self.odometry[index],
            rate=self.rate,
            closures=self.closures(index, correct_every),
            seed=noise_seed,
        )
        while True:
            with _SIMULATING:
                kind, *event = next(events, (None,))
            if kind is None:
                return
            if kind == "scan":
                yield event[0]
