"""Audit of a server's store, for crash trials, fuzzing and operators: is the file sound, and is
every row something the server would have accepted?

Opened read-only, so it can run beside a live server or on what a killed one left behind
(WAL included), without changing either.
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from protocol import ProtocolError, ScanMessage, decode

from .pose_graph import PoseGraph
from .store import DB_NAME, merged_columns, read_graph


@dataclass
class StoreCheck:
    integrity: str  # what PRAGMA integrity_check says: "ok" when sound
    scans: int = 0
    poses: int = 0  # robots with a pose graph
    bad: list[str] = field(default_factory=list)  # rows that do not decode, or disagree with their key

    @property
    def ok(self) -> bool:
        return self.integrity == "ok" and not self.bad


def check_store(data_dir: str | Path) -> StoreCheck:
    db = sqlite3.connect(f"file:{Path(data_dir) / DB_NAME}?mode=ro", uri=True, timeout=10)
    try:
        result = StoreCheck("; ".join(row[0] for row in db.execute("PRAGMA integrity_check")))
        for fleet, robot, node, size, raw in db.execute("SELECT fleet, robot, node, size, raw FROM scans"):
            result.scans += 1
            try:
                m = decode(raw, expect=ScanMessage)
                if (m.fleet, m.robot, m.node, len(raw)) != (fleet, robot, node, size):
                    raise ProtocolError(
                        "key",
                        f"row says {fleet}/{robot}/{node} ({size} B), message "
                        f"{m.fleet}/{m.robot}/{m.node} ({len(raw)} B)",
                    )
            except ProtocolError as error:
                result.bad.append(f"scan {fleet}/{robot}/{node}: {error}")
        if merged_columns(db):
            result.bad.append(
                "poses: merged graphs of an older schema; the server converts them when it opens the store"
            )
            return result
        for fleet, robot in db.execute("SELECT fleet, robot FROM poses").fetchall():
            result.poses += 1
            try:
                _check_graph(read_graph(db, fleet, robot))
            except ValueError as error:  # ProtocolError is one
                result.bad.append(f"poses {fleet}/{robot}: {error}")
        orphans = db.execute(
            "SELECT fleet, robot, COUNT(*) FROM node_poses "
            "WHERE (fleet, robot) NOT IN (SELECT fleet, robot FROM poses) GROUP BY fleet, robot"
        )
        for fleet, robot, count in orphans:
            result.bad.append(f"node_poses {fleet}/{robot}: {count} node poses of a robot without a row in poses")
        return result
    finally:
        db.close()


def _check_graph(graph: PoseGraph) -> None:
    """What the store's rows must hold beyond decoding: node ids the protocol allows, and no node or
    anchor revision newer than the graph's."""
    nodes = np.fromiter(graph.poses, dtype=np.int64, count=len(graph.poses))
    revisions = np.fromiter((rev for rev, _ in graph.poses.values()), dtype=np.int64, count=len(graph.poses))
    if len(nodes) and nodes.min() < 0:
        raise ProtocolError("node_poses.node", f"node {nodes.min()} is negative")
    if len(revisions) and (revisions.min() < 0 or revisions.max() > graph.revision):
        raise ProtocolError(
            "node_poses.revision", f"revisions {revisions.min()}..{revisions.max()} outside 0..{graph.revision}"
        )
    if graph.anchor is not None and not 0 <= graph.anchor_revision <= graph.revision:
        raise ProtocolError("poses.anchor_revision", f"{graph.anchor_revision} outside 0..{graph.revision}")
