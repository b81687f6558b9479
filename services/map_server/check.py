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

from protocol import PoseGraphUpdate, ProtocolError, ScanMessage, decode

from .store import DB_NAME


@dataclass
class StoreCheck:
    integrity: str  # what PRAGMA integrity_check says: "ok" when sound
    scans: int = 0
    poses: int = 0
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
        columns = {row[1] for row in db.execute("PRAGMA table_info(poses)")}
        per_node = "node_revisions, anchor_revision" if "node_revisions" in columns else "NULL, NULL"  # a v1 store
        for fleet, robot, revision, raw, node_revisions, anchor_revision in db.execute(
            f"SELECT fleet, robot, revision, raw, {per_node} FROM poses"
        ):
            result.poses += 1
            try:
                m = decode(raw, expect=PoseGraphUpdate, max_bytes=max(len(raw), 1))  # merged graphs may be large
                if (m.fleet, m.robot, m.revision) != (fleet, robot, revision):
                    raise ProtocolError(
                        "key", f"row says {fleet}/{robot} r{revision}, message {m.fleet}/{m.robot} r{m.revision}"
                    )
                _check_revisions(m, node_revisions, anchor_revision)
            except ProtocolError as error:
                result.bad.append(f"poses {fleet}/{robot}: {error}")
        return result
    finally:
        db.close()


def _check_revisions(graph: PoseGraphUpdate, node_revisions: bytes | None, anchor_revision: int | None) -> None:
    """The per-node revisions of a merged graph: one u64 per pose, none newer than the graph's."""
    if node_revisions is not None:
        if len(node_revisions) != 8 * len(graph.poses):
            raise ProtocolError(
                "node_revisions", f"{len(node_revisions)} bytes for {len(graph.poses)} poses (8 bytes each)"
            )
        if len(node_revisions) and int(np.frombuffer(node_revisions, dtype="<u8").max()) > graph.revision:
            raise ProtocolError("node_revisions", f"a node's revision is newer than the graph's {graph.revision}")
    if anchor_revision is not None and anchor_revision > graph.revision:
        raise ProtocolError("anchor_revision", f"{anchor_revision} is newer than the graph's {graph.revision}")
