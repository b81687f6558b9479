"""What the map server holds of each node's pose, so that a correction goes out only where it moves
the map: the agent's side of bounded pose-graph cost over a shift (issue 16).

A node's pose as the server holds it is the scan's own pose until a correction was sent for it,
then the last correction sent. A new pose `(R1, t1)` against the held `(R0, t0)` moves a point `p`
of the scan (sensor frame) by `|(t1 - t0) + (R1 - R0) p| <= |t1 - t0| + |p| ||R1 - R0||`
(gmm_core.pose.displacements): with
`reach`, the node's farthest beam end from its sensor, the bound is what a correction can move any
cell the scan touched, and one below the tolerance is not worth its bytes.

The pose held is the one sent, before the wire rounds it (float32 for a scan's pose, 0.1 mm codes
for a correction): the server's copy is within half a step of it, and the error does not add up,
since every comparison is with the last pose sent.

Held compactly for a shift of nodes: one float64 row per node (t, R row-major, reach: 7 numbers in
2D, 13 in 3D) and a dict entry: 194 B per node in 2D, 282 in 3D (tracemalloc over 18,000 nodes, the
table grown by doubling), where a Pose object alone takes about 330.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from gmm_core import Pose
from gmm_core.pose import displacements


def beam_reach(hits: np.ndarray, no_return: np.ndarray, max_range: float) -> float:
    """The farthest beam end from the sensor: returned points, and no-return directions (unit
    vectors) ended at `max_range` as the fit ends them (gmm_core.scan.fit_scan)."""
    ends = [np.linalg.norm(hits, axis=1).max(initial=0.0)]
    if len(no_return):
        ends.append(float(np.linalg.norm(no_return, axis=1).max()) * max_range)
    return float(max(ends))


class SentPoses:
    """Per node: the pose the server holds and the node's reach (NaN: unknown). Not thread-safe."""

    def __init__(self) -> None:
        self._rows: dict[int, int] = {}  # node -> row of _table
        self._table: np.ndarray | None = None  # (capacity, d + d*d + 1), allocated for the first dimension
        self._dim = 0

    def __len__(self) -> int:
        return len(self._rows)

    def check_dim(self, pose: Pose, name: str = "pose") -> None:
        """ValueError naming `name` unless `pose` has the dimension of the nodes sent so far."""
        if self._dim and pose.dim != self._dim:
            raise ValueError(f"{name}: {pose.dim}D, the nodes sent before were {self._dim}D")

    def scan_sent(self, node: int, pose: Pose, reach: float) -> None:
        """A scan went out with `pose` (the server holds it until a correction) and beams ending
        at most `reach` from the sensor. A node sent again (a resend, a refit) keeps the pose held."""
        row = self._rows.get(node)
        if row is None:
            self._set(node, pose, reach)
        else:
            self._table[row, -1] = reach

    def corrections_sent(self, poses: Mapping[int, Pose]) -> None:
        """These corrected poses went out: the server holds them now."""
        for node, pose in poses.items():
            row = self._rows.get(node)
            self._set(node, pose, np.nan if row is None else self._table[row, -1])

    def moved(self, poses: Mapping[int, Pose], tolerance: float) -> dict[int, Pose]:
        """The poses whose node would move some point of its scan by more than `tolerance` metres
        from the pose the server holds; a node of unknown reach or pose counts as moved."""
        if not poses:
            return {}
        nodes = list(poses)
        rows = np.array([self._rows.get(node, -1) for node in nodes])
        known = rows >= 0
        if self._table is None or not known.any():
            return dict(poses)
        d = self._dim
        held = self._table[rows[known]]
        new = [poses[node] for node, k in zip(nodes, known) if k]
        t1 = np.array([pose.t for pose in new])
        R1 = np.array([pose.R for pose in new])
        if t1.shape[1] != d:
            raise ValueError(f"poses: {t1.shape[1]}D, the nodes sent were {d}D")
        R0 = held[:, d : d + d * d].reshape(-1, d, d)
        far = np.ones(len(nodes), dtype=bool)  # unknown nodes, and NaN reach (the comparison is False)
        far[known] = ~(displacements(held[:, :d], R0, t1, R1, held[:, -1]) <= tolerance)
        return {node: poses[node] for node, f in zip(nodes, far) if f}

    def _set(self, node: int, pose: Pose, reach: float) -> None:
        if self._table is None:
            self._dim = pose.dim
            self._table = np.empty((1024, pose.dim + pose.dim**2 + 1))
        self.check_dim(pose, f"pose of node {node}")
        row = self._rows.get(node)
        if row is None:
            row = self._rows[node] = len(self._rows)
            if row == len(self._table):
                self._table = np.concatenate([self._table, np.empty_like(self._table)])
        self._table[row, : self._dim] = pose.t
        self._table[row, self._dim : -1] = pose.R.reshape(-1)
        self._table[row, -1] = reach
