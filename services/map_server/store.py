"""Durable store of a map server: every scan message once, and each robot's pose graph.

SQLite in WAL mode, one file `gmmap.db` in the data directory. Scans are kept as the bytes
received (the codec is the schema), so a restart decodes exactly what the robots sent and the
same query gives the same bytes.

Pose graphs are kept node by node: `node_poses` holds each node's pose and the revision that set
it, `poses` each robot's newest revision applied and its anchor with the anchor's revision.
Updates are applied node by node (pose_graph.PoseGraph) and one writes the rows of the nodes it
took and its robot's row, in one transaction: it costs what it lists, not what the graph holds.
Poses are kept as held, t then R in float64, so a restarted server compares a late update's
poses bit for bit with the very poses the live server held (pose_graph.same_pose) and judges it
as the live server did. A store of the first two schemas (one merged PoseGraphUpdate per robot
in `poses.raw`) is converted when it is opened.
"""

from __future__ import annotations

import sqlite3
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gmm_core import Pose
from gmm_core.pose import poses_from_arrays
from protocol import PoseGraphUpdate, ScanMessage, StoreInventory, decode

from .nodes import NodeKey, ScanEntry
from .pose_graph import PoseGraph

DB_NAME = "gmmap.db"
SCAN_CHUNK = 2048  # scans read per query at a restart: bounded memory, and the lock held briefly

TABLES = (
    # entry, components: what the fleet map holds of the scan besides its bytes (nodes.ScanEntry), so a
    # restart need not decode the models; NULL in rows written before they existed (decoded then).
    """CREATE TABLE IF NOT EXISTS scans (
        fleet TEXT NOT NULL, robot TEXT NOT NULL, node INTEGER NOT NULL,
        stamp REAL NOT NULL, size INTEGER NOT NULL, received REAL NOT NULL, raw BLOB NOT NULL,
        entry BLOB, components INTEGER,
        PRIMARY KEY (fleet, robot, node)
    ) WITHOUT ROWID""",
    "CREATE TABLE IF NOT EXISTS meta (name TEXT PRIMARY KEY, value TEXT NOT NULL)",
    # One row per robot with a pose graph. anchor: a pose blob, NULL (and anchor_revision NULL) when none came.
    """CREATE TABLE IF NOT EXISTS poses (
        fleet TEXT NOT NULL, robot TEXT NOT NULL, revision INTEGER NOT NULL, received REAL NOT NULL,
        anchor BLOB, anchor_revision INTEGER,
        PRIMARY KEY (fleet, robot)
    ) WITHOUT ROWID""",
    """CREATE TABLE IF NOT EXISTS node_poses (
        fleet TEXT NOT NULL, robot TEXT NOT NULL, node INTEGER NOT NULL,
        revision INTEGER NOT NULL, pose BLOB NOT NULL,
        PRIMARY KEY (fleet, robot, node)
    ) WITHOUT ROWID""",
)
POSE_DIMS = {8 * (d + d * d): d for d in (2, 3)}  # a pose blob's length -> its dimension
ENTRY_DIMS = {4 * d + d * d: d for d in (2, 3)}  # values in a scan's entry blob -> its dimension


@dataclass(frozen=True)
class Stored:
    """One record a restart replays: a scan (with its wire size) or one revision of a robot's pose graph."""

    message: ScanEntry | PoseGraphUpdate
    size: int  # of a scan, as received; 0 for a pose graph's revision (rebuilt, never sent as such)
    raw: bytes | None = None  # a scan's bytes as received (the map holds them, not the decoded model)


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
        self._db.execute("BEGIN IMMEDIATE")  # the schema, and a conversion, whole or not at all
        try:
            merged = merged_columns(self._db)
            if merged:
                self._db.execute("ALTER TABLE poses RENAME TO merged_poses")
            for table in TABLES:
                self._db.execute(table)
            columns = {row[1] for row in self._db.execute("PRAGMA table_info(scans)")}
            for column in ("entry BLOB", "components INTEGER"):  # a store of an earlier schema gains them
                if column.split()[0] not in columns:
                    self._db.execute(f"ALTER TABLE scans ADD COLUMN {column}")
            if merged:
                _convert_merged(self._db, merged)
            # The store's identity, made once with the data directory: Acks name it, so a robot can tell
            # this store from another (a fresh data directory, a restored backup) and resend what it lacks.
            self._db.execute("INSERT OR IGNORE INTO meta VALUES ('store', ?)", (uuid.uuid4().hex,))
            self._db.execute("COMMIT")
        except BaseException:
            self._db.execute("ROLLBACK")
            self._db.close()
            raise
        self.identity: str = self._db.execute("SELECT value FROM meta WHERE name = 'store'").fetchone()[0]
        self._graphs: dict[tuple[str, str], PoseGraph] = {}  # held pose graphs, as committed, decoded once

    def close(self) -> None:
        with self._lock:
            self._db.close()

    # -- writes: each call is one transaction, committed before it returns ---------------------
    def put_scans(
        self, batch: Sequence[tuple[ScanMessage, bytes]], entries: Sequence[ScanEntry] | None = None
    ) -> list[bool]:
        """Store each (message, raw bytes) unless its (fleet, robot, node) is held; one commit.
        `entries`: ScanEntry.of each message, when the caller has them already (ingest maps them too).

        Returns, per message, whether it was newly stored.
        """
        if entries is None:
            entries = [ScanEntry.of(m) for m, _ in batch]
        now = time.time()
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                new = [
                    self._db.execute(
                        "INSERT OR IGNORE INTO scans VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                        (m.fleet, m.robot, m.node, m.stamp, len(raw), now, bytes(raw), *entry_row(entry)),
                    ).rowcount
                    == 1
                    for (m, raw), entry in zip(batch, entries)
                ]
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
        return new

    def put_scan(self, msg: ScanMessage, raw: bytes) -> bool:
        return self.put_scans([(msg, raw)])[0]

    def put_poses(self, update: PoseGraphUpdate) -> bool:
        """Apply `update` node by node to the robot's held pose graph and write what it took; False
        if it changes nothing (every node it lists, and its anchor, set by a newer revision, or a
        resent part)."""
        key = (update.fleet, update.robot)
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                graph = self._held_graph(*key) or PoseGraph()
                applied, taken = graph.take(update)
                if not applied.changed:
                    self._db.execute("ROLLBACK")
                    return False
                _write_graph(self._db, *key, graph, taken, time.time())
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
            graph = read_graph(self._db, fleet, robot)
            if graph is None:
                return None
            self._graphs[key] = graph
        return self._graphs[key]

    # -- reads ---------------------------------------------------------------------------------
    def load(self, fleet: str) -> Iterator[Stored]:
        """Everything a restart replays into a FleetMap: each robot's pose graph revision by revision
        (applied in order, they give a map the per-node revisions too), then scans by (robot, node).

        Poses first: a FleetMap gives a scan the correction it holds for it as the scan lands, while
        a correction applied after its scans re-poses each of them once per revision. Scans are read
        SCAN_CHUNK at a time, the lock held only while reading, each decoded as it is yielded.
        """
        with self._lock:
            robots = [
                robot
                for (robot,) in self._db.execute("SELECT robot FROM poses WHERE fleet = ? ORDER BY robot", (fleet,))
            ]
        for robot in robots:
            with self._lock:
                pieces = self._held_graph(fleet, robot).by_revision(fleet, robot)
            for update in pieces:
                yield Stored(update, 0)
        after = ("", -1)  # (robot, node) of the last scan read; robot ids are never empty
        while True:
            with self._lock:
                rows = self._db.execute(
                    "SELECT robot, node, raw, size, entry, components FROM scans "
                    "WHERE fleet = ? AND (robot, node) > (?, ?) ORDER BY robot, node LIMIT ?",
                    (fleet, *after, SCAN_CHUNK),
                ).fetchall()
            for entry in scan_entries(rows):
                yield Stored(entry, entry.size, entry.raw)
            if len(rows) < SCAN_CHUNK:
                return
            after = rows[-1][:2]

    def last_received(self, fleet: str) -> dict[str, float]:
        """When (time.time()) the newest scan or pose-graph revision of each robot was stored: when
        a restarted server last saw it."""
        with self._lock:
            rows = self._db.execute(
                "SELECT robot, MAX(received) FROM (SELECT robot, received FROM scans WHERE fleet = ?1 "
                "UNION ALL SELECT robot, received FROM poses WHERE fleet = ?1) GROUP BY robot",
                (fleet,),
            ).fetchall()
        return dict(rows)

    def scan_count(self, fleet: str, robot: str | None = None) -> int:
        query, args = "SELECT COUNT(*) FROM scans WHERE fleet = ?", [fleet]
        if robot is not None:
            query, args = query + " AND robot = ?", args + [robot]
        with self._lock:
            return self._db.execute(query, args).fetchone()[0]

    def inventory(self, fleet: str, robot: str) -> StoreInventory:
        """What this store holds of `robot`: its node ids and the newest pose-graph revision applied."""
        with self._lock:
            row = self._db.execute(
                "SELECT revision FROM poses WHERE fleet = ? AND robot = ?", (fleet, robot)
            ).fetchone()
        return StoreInventory.of(fleet, robot, self.identity, self.nodes(fleet, robot), row and row[0])

    def nodes(self, fleet: str, robot: str) -> set[int]:
        with self._lock:
            rows = self._db.execute("SELECT node FROM scans WHERE fleet = ? AND robot = ?", (fleet, robot))
            return {node for (node,) in rows}

    def scan_reader(self, fleet: str) -> Callable[[NodeKey], bytes]:
        """scan_reader of this store's file."""
        return scan_reader(self.path, fleet)

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


# -- pose graphs as rows ---------------------------------------------------------------------------
def pose_blob(pose: Pose) -> bytes:
    """A pose as kept: t, then R row by row, float64 little-endian (the pose exactly as held)."""
    return np.concatenate([pose.t, pose.R.ravel()]).astype("<f8", copy=False).tobytes()


def poses_of_blobs(blobs: Sequence[bytes], field: str) -> list[Pose]:
    """pose_blob's poses, decoded at once; one dimension for all. ValueError naming `field` if a
    blob is not a pose."""
    if not blobs:
        return []
    width = len(blobs[0])
    dim = POSE_DIMS.get(width)
    if dim is None or any(len(blob) != width for blob in blobs):
        lengths = sorted({len(blob) for blob in blobs})
        raise ValueError(f"{field}: pose blobs of {lengths} bytes; a pose is {sorted(POSE_DIMS)} bytes, one for all")
    values = np.frombuffer(b"".join(blobs), dtype="<f8").astype(np.float64).reshape(len(blobs), dim + dim * dim)
    try:
        return poses_from_arrays(values[:, dim:].reshape(-1, dim, dim), values[:, :dim])
    except ValueError as error:
        raise ValueError(f"{field}: {error}") from None


def read_graph(db: sqlite3.Connection, fleet: str, robot: str) -> PoseGraph | None:
    """The robot's pose graph from its rows (two queries, its poses decoded at once); None if it has none."""
    head = db.execute(
        "SELECT revision, anchor, anchor_revision FROM poses WHERE fleet = ? AND robot = ?", (fleet, robot)
    ).fetchone()
    if head is None:
        return None
    revision, anchor, anchor_revision = head
    rows = db.execute(
        "SELECT node, revision, pose FROM node_poses WHERE fleet = ? AND robot = ? ORDER BY node", (fleet, robot)
    ).fetchall()
    nodes, revisions, blobs = zip(*rows) if rows else ((), (), ())
    poses = poses_of_blobs(blobs, f"node_poses.pose of {fleet}/{robot}")
    anchor_pose = None if anchor is None else poses_of_blobs([anchor], f"poses.anchor of {fleet}/{robot}")[0]
    if poses and anchor_pose is not None and anchor_pose.dim != poses[0].dim:
        raise ValueError(f"poses.anchor of {fleet}/{robot}: {anchor_pose.dim}D, its nodes {poses[0].dim}D")
    return PoseGraph.from_rows(
        revision, nodes, revisions, poses, anchor_pose, -1 if anchor_revision is None else anchor_revision
    )


def _write_graph(
    db: sqlite3.Connection, fleet: str, robot: str, graph: PoseGraph, nodes: Iterable[int], received: float
) -> None:
    """The rows of `nodes` of `graph`, and the robot's row (its revision and anchor)."""
    db.executemany(
        "INSERT OR REPLACE INTO node_poses VALUES (?, ?, ?, ?, ?)",
        ((fleet, robot, node, graph.poses[node][0], pose_blob(graph.poses[node][1])) for node in nodes),
    )
    anchor = None if graph.anchor is None else pose_blob(graph.anchor)
    db.execute(
        "INSERT OR REPLACE INTO poses VALUES (?, ?, ?, ?, ?, ?)",
        (fleet, robot, graph.revision, received, anchor, None if anchor is None else graph.anchor_revision),
    )


# -- stores of the first two schemas: one merged PoseGraphUpdate per robot -------------------------
def merged_columns(db: sqlite3.Connection) -> set[str]:
    """The columns of a `poses` table of merged graphs (it has `raw`); empty for any other store."""
    columns = {row[1] for row in db.execute("PRAGMA table_info(poses)")}
    return columns if "raw" in columns else set()


def _convert_merged(db: sqlite3.Connection, columns: set[str]) -> None:
    """Rows of `merged_poses` (the old `poses`) into `poses` and `node_poses`; then drop it. A first-
    schema row (no per-node revisions) has every node and the anchor at its revision."""
    per_node = "node_revisions, anchor_revision" if "node_revisions" in columns else "NULL, NULL"
    rows = db.execute(f"SELECT fleet, robot, received, raw, {per_node} FROM merged_poses").fetchall()
    for fleet, robot, received, raw, node_revisions, anchor_revision in rows:
        try:  # a merged graph may outgrow the wire's size cap; the store wrote it, so allow its size
            merged = decode(raw, expect=PoseGraphUpdate, max_bytes=max(len(raw), 1))
            graph = PoseGraph.from_merged(merged, node_revisions, anchor_revision)
        except ValueError as error:  # the whole conversion is rolled back: the old store stays as it was
            raise ValueError(f"poses of {fleet}/{robot}: {error}") from None
        _write_graph(db, fleet, robot, graph, graph.poses, received)
    db.execute("DROP TABLE merged_poses")


def entry_row(entry: ScanEntry) -> tuple[bytes, int]:
    """The `entry` and `components` columns of a scan: its node-frame box, sensor origin and pose
    (t, then R, float64 as decoded), so that a restart rebuilds its node without decoding the model."""
    values = (entry.local_lo, entry.local_hi, entry.origin, entry.pose.t, entry.pose.R.ravel())
    return np.concatenate(values).astype("<f8").tobytes(), entry.components


def scan_entries(rows: Sequence[tuple]) -> list[ScanEntry]:
    """ScanEntry of each (robot, node, raw, size, entry, components) row; a row written before the
    entry columns existed is decoded. The poses are built at once (poses_from_arrays)."""
    entries: list[ScanEntry | None] = [
        ScanEntry.of(decode(raw, expect=ScanMessage), size, raw) if entry is None else None
        for _, _, raw, size, entry, _ in rows
    ]
    kept = [i for i, entry in enumerate(entries) if entry is None]
    if kept:
        table = np.stack([np.frombuffer(rows[i][4], dtype="<f8") for i in kept])  # one dimension per map
        d = ENTRY_DIMS[table.shape[1]]
        poses = poses_from_arrays(table[:, 4 * d :].reshape(-1, d, d), table[:, 3 * d : 4 * d])
        for i, v, pose in zip(kept, table, poses):
            robot, node, raw, size, _, components = rows[i]
            entries[i] = ScanEntry(robot, node, pose, v[2 * d : 3 * d], v[:d], v[d : 2 * d], components, size, raw)
    return entries  # type: ignore[return-value]


def scan_reader(path: Path, fleet: str) -> Callable[[NodeKey], bytes]:
    """A scan's bytes by (robot, node) from the store file `path`, read from any thread or process
    (a map server's nodes hold none: nodes.py; its tracer processes read them too): each thread
    reads on a read-only connection of its own, which in WAL mode never waits for ingest's commits,
    so a tracer drawing a node's samples does not queue behind the writer."""
    local = threading.local()
    uri = f"{Path(path).resolve().as_uri()}?mode=ro"

    def read(key: NodeKey) -> bytes:
        db = getattr(local, "db", None)
        if db is None:
            db = local.db = sqlite3.connect(uri, uri=True, check_same_thread=False)
        row = db.execute(
            "SELECT raw FROM scans WHERE fleet = ? AND robot = ? AND node = ?", (fleet, key.robot, key.node)
        ).fetchone()
        if row is None:
            raise LookupError(f"scan {key.robot}/{key.node} of fleet {fleet!r} is not in the store {path}")
        return row[0]

    return read
