"""A transform buffer in the manner of ROS tf2: static and timed transforms between named frames.

Every frame has at most one parent, so the frames form a forest. `lookup(target, source, stamp)`
walks from both frames up to their nearest common ancestor and composes the transforms on the
way; a timed transform is interpolated between the two samples around the stamp (translation
linearly, rotation by slerp). A stamp outside a timed transform's samples is an `Extrapolation`
(tf2 refuses to extrapolate too), a pair of frames with no common ancestor a DatasetError naming both.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from gmm_core.pose import Pose, slerp

from .common import DatasetError


class Extrapolation(DatasetError):
    """A stamp outside the time span of a timed transform (or of a pose topic)."""


@dataclass(frozen=True)
class TimedPoses:
    """One frame's poses in another at sorted stamps; `at(stamp)` interpolates between neighbours."""

    stamps: np.ndarray  # (k,) seconds, ascending
    translations: np.ndarray  # (k, 3)
    quaternions: np.ndarray  # (k, 4) w x y z, unit
    name: str  # what the samples are, for errors: "transform 'odom' -> 'base_link'", "/odom"

    @classmethod
    def from_samples(cls, samples: list[tuple[float, Pose]], name: str) -> TimedPoses:
        """The samples (stamp, 3D pose) in any order; at equal stamps the first one counts."""
        stamps = np.array([s for s, _ in samples], dtype=np.float64)
        order = np.argsort(stamps, kind="stable")
        poses = [samples[k][1] for k in order]
        return cls(
            stamps=stamps[order],
            translations=np.array([p.t for p in poses]).reshape(-1, 3),
            quaternions=np.array([p.as_quaternion() for p in poses]).reshape(-1, 4),
            name=name,
        )

    @property
    def span(self) -> tuple[float, float]:
        return float(self.stamps[0]), float(self.stamps[-1])

    def at(self, stamp: float) -> Pose:
        """The pose at `stamp`: a sample's own where a stamp matches, else interpolated."""
        j = int(np.searchsorted(self.stamps, stamp))  # first sample at or after the stamp
        if j < len(self.stamps) and self.stamps[j] == stamp:
            return Pose.from_quaternion(self.translations[j], self.quaternions[j])
        if j == 0 or j == len(self.stamps):
            lo, hi = self.span
            raise Extrapolation(f"{self.name}: no pose at {stamp:.9f} s, outside its samples' [{lo:.9f}, {hi:.9f}] s")
        s0, s1 = self.stamps[j - 1], self.stamps[j]
        f = (stamp - s0) / (s1 - s0)
        t = self.translations[j - 1] + f * (self.translations[j] - self.translations[j - 1])
        return Pose.from_quaternion(t, slerp(self.quaternions[j - 1], self.quaternions[j], f))


class TransformBuffer:
    """Transforms between frames; each pose maps the child frame's coordinates to its parent's."""

    def __init__(self) -> None:
        self._parent: dict[str, str] = {}
        self._static: dict[str, Pose] = {}
        self._samples: dict[str, list[tuple[float, Pose]]] = defaultdict(list)
        self._timed: dict[str, TimedPoses] = {}  # built from _samples on first use

    def add_static(self, parent: str, child: str, pose: Pose) -> None:
        """A fixed transform (a /tf_static message); a later one for the same child replaces it."""
        self._link(parent, child)
        if child in self._samples:
            raise DatasetError(f"frame {child!r}: a static transform, but timed ones too")
        self._static[child] = pose

    def add(self, parent: str, child: str, stamp: float, pose: Pose) -> None:
        """A transform valid at `stamp` (a /tf message)."""
        self._link(parent, child)
        if child in self._static:
            raise DatasetError(f"frame {child!r}: a timed transform, but a static one too")
        self._samples[child].append((stamp, pose))
        self._timed.pop(child, None)

    def forget_before(self, stamp: float) -> None:
        """Drop the timed samples before `stamp` but the last of each transform, so that a live
        buffer stays bounded; a lookup at `stamp` or later gives what it gave before."""
        for child, samples in self._samples.items():
            older = [s for s in samples if s[0] < stamp]
            if len(older) > 1:
                newest = max(s[0] for s in older)
                last = next(s for s in older if s[0] == newest)  # the first at equal stamps counts
                self._samples[child] = [last] + [s for s in samples if s[0] >= stamp]
                self._timed.pop(child, None)

    def _link(self, parent: str, child: str) -> None:
        if parent == child:
            raise DatasetError(f"transform from frame {child!r} to itself")
        known = self._parent.setdefault(child, parent)
        if known != parent:
            raise DatasetError(f"frame {child!r} has two parents, {known!r} and {parent!r}")

    @property
    def frames(self) -> set[str]:
        return set(self._parent) | set(self._parent.values())

    def _chain(self, frame: str) -> list[str]:
        """frame, its parent, the parent's parent, ... up to its tree's root."""
        chain = [frame]
        while chain[-1] in self._parent:
            chain.append(self._parent[chain[-1]])
            if chain[-1] in chain[:-1]:
                raise DatasetError(f"transforms form a loop: {' -> '.join(chain)}")
        return chain

    def root(self, frame: str) -> str:
        """The root of the tree that holds `frame` (e.g. map or odom)."""
        return self._chain(frame)[-1]

    def lookup(self, target: str, source: str, stamp: float) -> Pose:
        """The pose of frame `source` in frame `target` at `stamp` (maps source coordinates to target's)."""
        up_source, up_target = self._chain(source), self._chain(target)
        common = next((f for f in up_source if f in up_target), None)
        if common is None:
            raise DatasetError(
                f"no transform between frames {target!r} and {source!r} (frames known: {sorted(self.frames)})"
            )
        return (
            self._to_ancestor(up_target, common, stamp).inverse().compose(self._to_ancestor(up_source, common, stamp))
        )

    def _to_ancestor(self, chain: list[str], ancestor: str, stamp: float) -> Pose:
        pose = Pose.identity(3)
        for frame in chain[: chain.index(ancestor)]:
            pose = self._edge(frame, stamp).compose(pose)
        return pose

    def _edge(self, child: str, stamp: float) -> Pose:
        if child in self._static:
            return self._static[child]
        if child not in self._timed:
            name = f"transform {self._parent[child]!r} -> {child!r}"
            self._timed[child] = TimedPoses.from_samples(self._samples[child], name)
        return self._timed[child].at(stamp)
