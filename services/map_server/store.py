"""Durable store of a map server: every scan message once, and each robot's pose graph.

SQLite in WAL mode, one file `gmmap.db` in the data directory. Scans are kept as the bytes
received (the codec is the schema), so a restart decodes exactly what the robots sent and the
same query gives the same bytes. Per robot, the pose graph is kept as one encoded
PoseGraphUpdate at the newest revision applied, holding every node's pose and the anchor (an
update lists only the nodes it moves; the others keep their last pose), beside the revision
that set each of them: updates are applied node by node (pose_graph.PoseGraph), and a restart
must judge a late update exactly as the live server did.
"""

from __future__ import annotations

import sqlite3
import threading
import time
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from protocol import PoseGraphUpdate, ScanMessage, StoreInventory, decode, encode

from .pose_graph import PoseGraph

DB_NAME = "gmmap.db"

SCHEMA = """
CREATE TABLE IF NOT EXISTS scans (
    fleet TEXT NOT NULL, robot TEXT NOT NULL, node INTEGER NOT NULL,
    stamp REAL NOT NULL, size INTEGER NOT NULL, received REAL NOT NULL, raw BLOB NOT NULL,
    PRIMARY KEY (fleet, robot, node)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS meta (name TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS poses (
    fleet TEXT NOT NULL, robot TEXT NOT NULL, revision INTEGER NOT NULL,
    received REAL NOT NULL, raw BLOB NOT NULL,
    node_revisions BLOB, anchor_revision INTEGER,
    PRIMARY KEY (fleet, robot)
) WITHOUT ROWID;
"""
# Columns added to `poses` since the first schema, as a store made before them lacks them.
POSES_ADDED = {
    # Revision of each pose of `raw`, in its order: u64 little-endian. NULL: every node at the row's
    # revision (a row written before this column, or an update that makes the whole graph, kept as sent).
    "node_revisions": "BLOB",
    "anchor_revision": "INTEGER",  # of raw's anchor; NULL: the row's revision (or no anchor)
}


@dataclass(frozen=True)
class Stored:
    """One record a restart replays: a scan (with its wire size) or one revision of a robot's pose graph."""

    message: ScanMessage | PoseGraphUpdate
    size: int  # of a scan, as received; 0 for a pose graph's revision (rebuilt, never sent as such)


class Store:
    """Thread-safe: one connection behind a lock (writes are short; SQLite serialises them anyway).

    synchronous: "NORMAL" (default) or "FULL". In WAL mode a commit with NORMAL is appended to
    the WAL file before COMMIT returns, but not fsynced: it survives the death of the process
    (kill -9 included), which is what acknowledging after commit promises; only an OS crash or
    power loss can drop the last transactions. "FULL" fsyncs every commit for that case too, at
    a cost of milliseconds per commit (batched commits keep ingest fast either way).
    """

    def __init__(self, data_dir: str | Path, *, synchronous: str = "NORMAL"):
        if synchronous.upper() not in ("NORMAL", "FULL"):
            raise ValueError(f"synchronous must be NORMAL or FULL, got {synchronous!r}")
        self.path = Path(data_dir) / DB_NAME
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute(f"PRAGMA synchronous={synchronous.upper()}")
        self._db.execute("PRAGMA busy_timeout=5000")  # readers in other processes (tests, tools)
        self._db.executescript(SCHEMA)
        columns = {row[1] for row in self._db.execute("PRAGMA table_info(poses)")}
        for name, kind in POSES_ADDED.items():
            if name not in columns:
                self._db.execute(f"ALTER TABLE poses ADD COLUMN {name} {kind}")
        # The store's identity, made once with the data directory: Acks name it, so a robot can tell
        # this store from another (a fresh data directory, a restored backup) and resend what it lacks.
        self._db.execute("INSERT OR IGNORE INTO meta VALUES ('store', ?)", (uuid.uuid4().hex,))
        self.identity: str = self._db.execute("SELECT value FROM meta WHERE name = 'store'").fetchone()[0]
        self._graphs: dict[tuple[str, str], PoseGraph] = {}  # held pose graphs, as committed, decoded once

    def close(self) -> None:
        with self._lock:
            self._db.close()

    # -- writes: each call is one transaction, committed before it returns ---------------------
    def put_scans(self, batch: Sequence[tuple[ScanMessage, bytes]]) -> list[bool]:
        """Store each (message, raw bytes) unless its (fleet, robot, node) is held; one commit.

        Returns, per message, whether it was newly stored.
        """
        now = time.time()
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                new = [
                    self._db.execute(
                        "INSERT OR IGNORE INTO scans VALUES (?, ?, ?, ?, ?, ?, ?)",
                        (m.fleet, m.robot, m.node, m.stamp, len(raw), now, bytes(raw)),
                    ).rowcount
                    == 1
                    for m, raw in batch
                ]
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
        return new

    def put_scan(self, msg: ScanMessage, raw: bytes) -> bool:
        return self.put_scans([(msg, raw)])[0]

    def put_poses(self, update: PoseGraphUpdate, raw: bytes) -> bool:
        """Apply `update` node by node to the robot's held pose graph; False if it changes nothing
        (every node it lists, and its anchor, set by a newer revision, or a resent part)."""
        key = (update.fleet, update.robot)
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                graph = self._held_graph(*key) or PoseGraph()
                if not graph.apply(update).changed:
                    self._db.execute("ROLLBACK")
                    return False
                as_sent = graph.is_exactly(update)  # a robot's first update, or one listing its whole graph
                self._db.execute(
                    "INSERT OR REPLACE INTO poses (fleet, robot, revision, received, raw, node_revisions, "
                    "anchor_revision) VALUES (?, ?, ?, ?, ?, ?, ?)",
                    (
                        *key,
                        graph.revision,
                        time.time(),
                        bytes(raw) if as_sent else encode(graph.as_update(*key)),
                        None if as_sent else graph.node_revisions(),
                        graph.anchor_revision if graph.anchor is not None else None,
                    ),
                )
                self._db.execute("COMMIT")
                self._graphs[key] = graph
            except BaseException:
                self._graphs.pop(key, None)  # it may hold what was not committed: read it again
                if self._db.in_transaction:
                    self._db.execute("ROLLBACK")
                raise
        return True

    def _held_graph(self, fleet: str, robot: str) -> PoseGraph | None:
        """The robot's pose graph as committed (caller holds the lock)."""
        key = (fleet, robot)
        if key not in self._graphs:
            row = self._db.execute(
                "SELECT raw, node_revisions, anchor_revision FROM poses WHERE fleet = ? AND robot = ?", key
            ).fetchone()
            if row is None:
                return None
            self._graphs[key] = _graph(*row)
        return self._graphs[key]

    # -- reads ---------------------------------------------------------------------------------
    def load(self, fleet: str) -> Iterator[Stored]:
        """Everything a restart replays into a FleetMap: scans by (robot, node), then pose graphs."""
        with self._lock:
            scans = self._db.execute(
                "SELECT raw, size FROM scans WHERE fleet = ? ORDER BY robot, node", (fleet,)
            ).fetchall()
            graphs = self._db.execute(
                "SELECT robot, raw, node_revisions, anchor_revision FROM poses WHERE fleet = ? ORDER BY robot", (fleet,)
            ).fetchall()
        for raw, size in scans:
            yield Stored(decode(raw, expect=ScanMessage), size)
        for robot, *row in graphs:
            # Revision by revision: applied in order, they give a map the per-node revisions too.
            for update in _graph(*row).by_revision(fleet, robot):
                yield Stored(update, 0)

    def scan_count(self, fleet: str, robot: str | None = None) -> int:
        query, args = "SELECT COUNT(*) FROM scans WHERE fleet = ?", [fleet]
        if robot is not None:
            query, args = query + " AND robot = ?", args + [robot]
        with self._lock:
            return self._db.execute(query, args).fetchone()[0]

    def inventory(self, fleet: str, robot: str) -> StoreInventory:
        """What this store holds of `robot`: its node ids and the newest pose-graph revision applied."""
        with self._lock:
            graph = self._held_graph(fleet, robot)
        revision = None if graph is None else graph.revision
        return StoreInventory.of(fleet, robot, self.identity, self.nodes(fleet, robot), revision)

    def nodes(self, fleet: str, robot: str) -> set[int]:
        with self._lock:
            rows = self._db.execute("SELECT node FROM scans WHERE fleet = ? AND robot = ?", (fleet, robot))
            return {node for (node,) in rows}

    def scan_bytes(self, fleet: str, robot: str, node: int) -> bytes | None:
        with self._lock:
            row = self._db.execute(
                "SELECT raw FROM scans WHERE fleet = ? AND robot = ? AND node = ?", (fleet, robot, node)
            ).fetchone()
        return row[0] if row else None

    def pose_graph(self, fleet: str, robot: str) -> PoseGraphUpdate | None:
        """The robot's pose graph as committed: every node's pose and the anchor, at the newest revision."""
        with self._lock:
            graph = self._held_graph(fleet, robot)
            return None if graph is None else graph.as_update(fleet, robot)


def _graph(raw: bytes, node_revisions: bytes | None, anchor_revision: int | None) -> PoseGraph:
    """A `poses` row's graph. A merged graph may outgrow the wire's size cap; the store wrote it, so allow its size."""
    merged = decode(raw, expect=PoseGraphUpdate, max_bytes=max(len(raw), 1))
    return PoseGraph.from_stored(merged, node_revisions, anchor_revision)
