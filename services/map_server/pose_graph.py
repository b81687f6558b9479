"""One robot's pose graph as a receiver holds it (protocol v2 and later): node by node, the pose of the newest
revision that listed the node and that revision; the anchor likewise.

The live map (nodes.NodeStore) and the durable store (store.Store) both apply updates through this
one class, so the map a restart replays judges a late update exactly as the live map did.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from gmm_core import Pose
from protocol import PoseGraphUpdate


class Applied(NamedTuple):
    """What one update did to a graph."""

    changed: bool  # a pose or the revision that set it was taken: the graph differs from before
    moved: list[int]  # nodes whose pose is new or differs from the one they had
    anchor_moved: bool  # the anchor is new or differs from the one held


def same_pose(a: Pose, b: Pose) -> bool:
    """Bit for bit (a tenth of np.array_equal's cost); -0.0 and 0.0 differ, which only costs a
    needless move."""
    return a is b or (a.t.tobytes() == b.t.tobytes() and a.R.tobytes() == b.R.tobytes())


class PoseGraph:
    """Not thread-safe: its owner holds a lock around it."""

    def __init__(self):
        self.poses: dict[int, tuple[int, Pose]] = {}  # node -> (revision that set it, pose in the map frame)
        self.anchor: Pose | None = None  # robot map frame -> world
        self.anchor_revision = -1  # of the update that set `anchor`
        self.revision = -1  # the newest revision applied

    def pose(self, node: int) -> Pose | None:
        held = self.poses.get(node)
        return held[1] if held is not None else None

    def apply(self, update: PoseGraphUpdate) -> Applied:
        """Take each pose of `update` whose node no newer revision set, and its anchor likewise.

        An equal revision is taken too: a revision may come in parts. Taking an equal pose at a
        newer revision changes the graph (a later part of the older revision must now lose) but
        moves nothing.
        """
        return self.take(update)[0]

    def take(self, update: PoseGraphUpdate) -> tuple[Applied, list[int]]:
        """`apply`, and the nodes whose entry it set (a new pose, or the update's revision on an
        equal one): the rows a store writes."""
        revision, moved, taken = update.revision, [], []
        for node, pose in update.poses:
            held = self.poses.get(node)
            if held is not None and held[0] > revision:
                continue
            if held is None or not same_pose(held[1], pose):
                moved.append(node)
            elif held[0] == revision:
                continue  # a resent part: nothing to take
            self.poses[node] = (revision, pose)
            taken.append(node)
        changed = bool(taken)
        anchor_moved = False
        if update.anchor is not None and self.anchor_revision <= revision:
            anchor_moved = self.anchor is None or not same_pose(self.anchor, update.anchor)
            changed = changed or anchor_moved or self.anchor_revision != revision
            self.anchor, self.anchor_revision = update.anchor, revision
        # Whatever an update lists ends at its revision or a newer one, so this is also the
        # newest revision any node or the anchor holds.
        self.revision = max(self.revision, revision)
        return Applied(changed, moved, anchor_moved), taken

    # -- as stored -----------------------------------------------------------------------------
    def as_update(self, fleet: str, robot: str) -> PoseGraphUpdate:
        """Every pose (by node id) and the anchor, at the newest revision applied."""
        poses = tuple((node, pose) for node, (_, pose) in sorted(self.poses.items()))
        return PoseGraphUpdate(fleet, robot, self.revision, poses, self.anchor)

    @classmethod
    def from_rows(
        cls,
        revision: int,
        nodes: Sequence[int],
        revisions: Sequence[int],
        poses: Sequence[Pose],
        anchor: Pose | None = None,
        anchor_revision: int = -1,
    ) -> PoseGraph:
        """The graph holding node nodes[i] at (revisions[i], poses[i]), the anchor at anchor_revision,
        its newest revision applied `revision`."""
        graph = cls()
        graph.poses = dict(zip(nodes, zip(revisions, poses)))
        graph.anchor, graph.anchor_revision = anchor, anchor_revision if anchor is not None else -1
        graph.revision = revision
        return graph

    @classmethod
    def from_merged(cls, merged: PoseGraphUpdate, node_revisions: bytes | None, anchor_revision: int | None):
        """The graph of a store row of the first two schemas: `merged` (as_update), the revision of
        each of its poses (u64 little-endian, in its order) and the anchor's; a None (a row written
        before per-node revisions) puts every node, or the anchor, at the merged revision."""
        if node_revisions is None:
            revisions = [merged.revision] * len(merged.poses)
        else:
            if len(node_revisions) != 8 * len(merged.poses):
                raise ValueError(
                    f"pose graph of {merged.fleet}/{merged.robot}: {len(node_revisions)} bytes of node "
                    f"revisions for {len(merged.poses)} poses (8 bytes each)"
                )
            revisions = np.frombuffer(node_revisions, dtype="<u8").tolist()
        nodes, poses = [node for node, _ in merged.poses], [pose for _, pose in merged.poses]
        anchor = merged.revision if anchor_revision is None else anchor_revision
        return cls.from_rows(merged.revision, nodes, revisions, poses, merged.anchor, anchor)

    def by_revision(self, fleet: str, robot: str) -> list[PoseGraphUpdate]:
        """One update per revision still held, oldest first: applied in order to an empty graph
        (or map), they give this graph, per-node revisions included."""
        listed: dict[int, list[tuple[int, Pose]]] = defaultdict(list)
        for node, (rev, pose) in sorted(self.poses.items()):
            listed[rev].append((node, pose))
        if self.anchor is not None:
            listed.setdefault(self.anchor_revision, [])
        return [
            PoseGraphUpdate(fleet, robot, rev, tuple(listed[rev]), self.anchor if rev == self.anchor_revision else None)
            for rev in sorted(listed)
        ]
