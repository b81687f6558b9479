"""Pose-graph histories for the server's node-by-node rule (protocol v2), and the plain model they
are checked against.

A history is what one robot sends: revisions with gaps, each listing some nodes (poses x along the
x axis, from a few values so that equal poses at newer revisions occur) and sometimes an anchor,
split into parts, some parts resent, all of it arriving in a random order.
"""

from __future__ import annotations

import numpy as np

from gmm_core import Pose
from protocol import PoseGraphUpdate

FLEET = "default"
X_VALUES = (0.0, 0.5, 1.0, 1.5)


def pose(x: float) -> Pose:
    return Pose.from_xytheta(x, 0.0, 0.0)


def update(revision: int, items, anchor: float | None = None, robot: str = "r") -> PoseGraphUpdate:
    """An update setting node n to pose(x) for each (n, x) of `items`, and the anchor to pose(anchor)."""
    return PoseGraphUpdate(
        FLEET, robot, revision, tuple((n, pose(x)) for n, x in items), None if anchor is None else pose(anchor)
    )


class ReferenceGraph:
    """The rule, plainly: {node: (revision, x)}, the anchor's (revision, x); an entry is taken when
    its revision is not older than the held one."""

    def __init__(self):
        self.nodes: dict[int, tuple[int, float]] = {}
        self.anchor: tuple[int, float] | None = None

    def apply(self, message: PoseGraphUpdate) -> bool:
        """Whether the update changed the model."""
        before = (dict(self.nodes), self.anchor)
        for node, p in message.poses:
            if node not in self.nodes or self.nodes[node][0] <= message.revision:
                self.nodes[node] = (message.revision, float(p.t[0]))
        if message.anchor is not None and (self.anchor is None or self.anchor[0] <= message.revision):
            self.anchor = (message.revision, float(message.anchor.t[0]))
        return (self.nodes, self.anchor) != before


def random_history(rng: np.random.Generator, nodes: int = 8, revisions: int = 6) -> list[PoseGraphUpdate]:
    """Updates in arrival order. Parts of one revision list disjoint nodes and the same anchor, so
    the state once all have arrived does not depend on their order (see `newest`)."""
    parts = []
    for revision in sorted(rng.choice(20, size=revisions, replace=False).tolist()):
        listed = rng.permutation(nodes)[: rng.integers(0, nodes + 1)]
        anchor = float(rng.choice(X_VALUES)) if rng.random() < 0.4 else None
        if not len(listed) and anchor is None:
            listed = [int(rng.integers(nodes))]
        split = np.array_split(np.asarray(listed, dtype=int), int(rng.integers(1, 4)))
        carries = rng.random(len(split)) < 0.5
        carries[rng.integers(len(split))] = True  # at least one part carries the revision's anchor
        for chunk, carry in zip(split, carries):
            part_anchor = anchor if carry else None
            if len(chunk) or part_anchor is not None:
                items = [(int(n), float(rng.choice(X_VALUES))) for n in chunk]
                parts.append(update(revision, items, part_anchor))
    resent = [parts[i] for i in rng.choice(len(parts), size=len(parts) // 3)]
    arrival = parts + resent
    return [arrival[i] for i in rng.permutation(len(arrival))]


def newest(history: list[PoseGraphUpdate]) -> ReferenceGraph:
    """What the rule must end at, whatever the order: each node at the newest revision listing it."""
    final = ReferenceGraph()
    for message in sorted(history, key=lambda m: m.revision):
        final.apply(message)
    return final
