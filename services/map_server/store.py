"""Durable store of a map server: every scan message once, and each robot's pose graph.

SQLite in WAL mode, one file `gmmap.db` in the data directory. Scans are kept as the bytes
received (the codec is the schema), so a restart decodes exactly what the robots sent and the
same query gives the same bytes. Per robot, the pose graph is kept as one encoded
PoseGraphUpdate: the newest revision, merged with the node poses and anchor of older ones
(an update lists only the nodes it moves; the others keep their last pose).
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
    PRIMARY KEY (fleet, robot)
) WITHOUT ROWID;
"""


@dataclass(frozen=True)
class Stored:
    """One record a restart replays: a scan (with its wire size) or a robot's pose graph."""

    message: ScanMessage | PoseGraphUpdate
    size: int


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
        # The store's identity, made once with the data directory: Acks name it, so a robot can tell
        # this store from another (a fresh data directory, a restored backup) and resend what it lacks.
        self._db.execute("INSERT OR IGNORE INTO meta VALUES ('store', ?)", (uuid.uuid4().hex,))
        self.identity: str = self._db.execute("SELECT value FROM meta WHERE name = 'store'").fetchone()[0]
        self._graphs: dict[tuple[str, str], PoseGraphUpdate] = {}  # held pose graphs, decoded once

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
        """Merge `update` into the robot's held pose graph; False if its revision is older."""
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                held = self._held_graph(update.fleet, update.robot)
                if held is not None and update.revision < held.revision:
                    self._db.execute("ROLLBACK")
                    return False
                merged = _merge(held, update)
                self._db.execute(
                    "INSERT OR REPLACE INTO poses VALUES (?, ?, ?, ?, ?)",
                    (
                        update.fleet,
                        update.robot,
                        update.revision,
                        time.time(),
                        bytes(raw) if merged is update else encode(merged),
                    ),
                )
                self._db.execute("COMMIT")
                self._graphs[(update.fleet, update.robot)] = merged
            except BaseException:
                if self._db.in_transaction:
                    self._db.execute("ROLLBACK")
                raise
        return True

    def _held_graph(self, fleet: str, robot: str) -> PoseGraphUpdate | None:
        """The robot's pose graph as committed (caller holds the lock)."""
        key = (fleet, robot)
        if key not in self._graphs:
            row = self._db.execute("SELECT raw FROM poses WHERE fleet = ? AND robot = ?", key).fetchone()
            if row is None:
                return None
            # A merged graph may outgrow the wire's size cap; the store wrote it, so allow its size.
            self._graphs[key] = decode(row[0], expect=PoseGraphUpdate, max_bytes=max(len(row[0]), 1))
        return self._graphs[key]

    # -- reads ---------------------------------------------------------------------------------
    def load(self, fleet: str) -> Iterator[Stored]:
        """Everything a restart replays into a FleetMap: scans by (robot, node), then pose graphs."""
        with self._lock:
            scans = self._db.execute(
                "SELECT raw, size FROM scans WHERE fleet = ? ORDER BY robot, node", (fleet,)
            ).fetchall()
            graphs = self._db.execute("SELECT raw FROM poses WHERE fleet = ? ORDER BY robot", (fleet,)).fetchall()
        for raw, size in scans:
            yield Stored(decode(raw, expect=ScanMessage), size)
        for (raw,) in graphs:
            yield Stored(decode(raw, expect=PoseGraphUpdate, max_bytes=max(len(raw), 1)), len(raw))

    def scan_count(self, fleet: str, robot: str | None = None) -> int:
        query, args = "SELECT COUNT(*) FROM scans WHERE fleet = ?", [fleet]
        if robot is not None:
            query, args = query + " AND robot = ?", args + [robot]
        with self._lock:
            return self._db.execute(query, args).fetchone()[0]

    def inventory(self, fleet: str, robot: str) -> StoreInventory:
        """What this store holds of `robot`: its node ids and the newest pose-graph revision applied."""
        graph = self.pose_graph(fleet, robot)
        return StoreInventory.of(fleet, robot, self.identity, self.nodes(fleet, robot), graph and graph.revision)

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
        with self._lock:
            return self._held_graph(fleet, robot)


def _merge(held: PoseGraphUpdate | None, update: PoseGraphUpdate) -> PoseGraphUpdate:
    """`update` with the node poses and anchor of `held` that it does not replace.

    Returns `update` itself when nothing of `held` survives, so its bytes can be kept as sent.
    """
    if held is None:
        return update
    poses = dict(held.poses)
    poses.update(update.poses)
    anchor = update.anchor if update.anchor is not None else held.anchor
    if len(poses) == len(update.poses) and anchor is update.anchor:
        return update
    return PoseGraphUpdate(update.fleet, update.robot, update.revision, tuple(sorted(poses.items())), anchor)
