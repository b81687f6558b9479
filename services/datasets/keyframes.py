"""Keyframes: which scans become pose-graph nodes (the `keyframe` section of the configuration).

A robot standing still for an hour would otherwise send 36,000 fits of one room. In the spirit
of the paper's Sec. IV-C (spend components where there is new information) a scan becomes a
node only when the sensor moved `distance` metres or turned `angle` degrees since the last node,
or `period` seconds passed; 0 turns each reason off, and all three 0 keep every scan. The first
scan is always a node. The pose judged is the one the robot has when the scan arrives (its
odometry or on-line estimate), so the agent, `replay` and `inspect` decide alike.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from gmm_core.pose import Pose
from gmm_core.validation import require_number

T = TypeVar("T")


@dataclass(frozen=True)
class KeyframeConfig:
    # Defaults measured on the real indoor logs (bench/keyframes.py, docs/BENCHMARKS.md).
    distance: float = 0.15  # m the sensor moved since the last node; 0: not a reason
    angle: float = 10.0  # degrees it turned since the last node; 0: not a reason
    period: float = 0.0  # s since the last node; 0: not a reason

    def __post_init__(self):
        require_number("keyframe.distance", self.distance, positive=False)
        require_number("keyframe.angle", self.angle, positive=False)
        require_number("keyframe.period", self.period, positive=False)

    @classmethod
    def every_scan(cls) -> KeyframeConfig:
        return cls(distance=0.0, angle=0.0, period=0.0)

    @property
    def keeps_every_scan(self) -> bool:
        return self.distance == 0 and self.angle == 0 and self.period == 0


def turned(a: Pose, b: Pose) -> float:
    """The angle of the rotation from a to b, degrees (2D or 3D)."""
    R = a.R.T @ b.R
    # trace = 2 cos(theta) in 2D, 1 + 2 cos(theta) in 3D
    cos = (np.trace(R) - (a.dim - 2)) / 2
    return math.degrees(math.acos(min(1.0, max(-1.0, cos))))


class KeyframeFilter:
    """Decides, scan by scan in order, whether a scan becomes a node."""

    def __init__(self, config: KeyframeConfig):
        self.config = config
        self._last: tuple[Pose, float] | None = None  # pose and stamp of the last node

    def keep(self, pose: Pose, stamp: float) -> bool:
        c = self.config
        last = self._last
        if not (
            last is None
            or c.keeps_every_scan
            or (c.distance > 0 and np.linalg.norm(pose.t - last[0].t) >= c.distance)
            or (c.angle > 0 and turned(last[0], pose) >= c.angle)
            or (c.period > 0 and stamp - last[1] >= c.period)
        ):
            return False
        self._last = (pose, stamp)
        return True


def keyframes(
    items: Iterable[T], config: KeyframeConfig, pose_and_stamp: Callable[[T], tuple[Pose, float]]
) -> Iterator[T]:
    """The items that become nodes, in order; `pose_and_stamp` reads what the policy judges."""
    decide = KeyframeFilter(config)
    return (item for item in items if decide.keep(*pose_and_stamp(item)))
