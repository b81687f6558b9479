"""Durable outbox of an agent: every message stays on disk until the server acknowledges it.

A message is written (and committed) before it is first published and deleted only when its
Ack arrives, so a crash of the agent, of the server or of the link loses nothing: whatever
is still here is resent. `acked` keeps what a server confirmed, with the store that did (its
identity, from the Ack) and, up to `keep_bytes` (the oldest forgotten first), the message's bytes:
a server that later lacks them (a fresh data directory, a restored backup) gets them again
(`requeue_missing`). It also tells a restarted agent what to skip. `rejected` keeps what the server
refused for good (a Rejection: not resent, reported), and `meta` the next pose-graph revision,
which must keep increasing across restarts.
"""

from __future__ import annotations

import sqlite3
import threading
import time
from pathlib import Path

MAX_DOUBLINGS = 4  # a held message waits at most 16 resend timeouts between two sendings

SCHEMA = """
CREATE TABLE IF NOT EXISTS outbox (
    kind TEXT NOT NULL, id INTEGER NOT NULL, key TEXT NOT NULL, raw BLOB NOT NULL,
    sent REAL NOT NULL, attempts INTEGER NOT NULL, first_sent REAL NOT NULL DEFAULT 0, PRIMARY KEY (kind, id)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS acked (
    kind TEXT NOT NULL, id INTEGER NOT NULL, at REAL NOT NULL, store TEXT NOT NULL DEFAULT '',
    key TEXT, raw BLOB, PRIMARY KEY (kind, id)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS rejected (
    kind TEXT NOT NULL, id INTEGER NOT NULL, reason TEXT NOT NULL, detail TEXT NOT NULL, at REAL NOT NULL,
    PRIMARY KEY (kind, id)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS meta (name TEXT PRIMARY KEY, value TEXT NOT NULL);
"""


class Outbox:
    """Thread-safe (one connection behind a lock): the main loop adds, the Ack callback removes.

    WAL with synchronous=NORMAL: a committed row survives the agent being killed.
    """

    def __init__(self, path: str | Path, fleet: str, robot: str, keep_bytes: int = 256 * 2**20):
        self.path = Path(path)
        self.keep_bytes = keep_bytes
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        # Python's implicit transactions; every write below is one `with self._db:` commit.
        self._db = sqlite3.connect(self.path, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.execute("PRAGMA busy_timeout=5000")
        self._db.executescript(SCHEMA)
        if "first_sent" not in {row[1] for row in self._db.execute("PRAGMA table_info(outbox)")}:
            self._db.execute("ALTER TABLE outbox ADD COLUMN first_sent REAL NOT NULL DEFAULT 0")
        columns = {row[1] for row in self._db.execute("PRAGMA table_info(acked)")}
        for column in ("store TEXT NOT NULL DEFAULT ''", "key TEXT", "raw BLOB"):  # an outbox of protocol v1
            if column.split()[0] not in columns:
                self._db.execute(f"ALTER TABLE acked ADD COLUMN {column}")
        self._retained = self._db.execute("SELECT COALESCE(SUM(LENGTH(raw)), 0) FROM acked").fetchone()[0]
        owner = f"{fleet}/{robot}"
        with self._db:
            self._db.execute("INSERT OR IGNORE INTO meta VALUES ('owner', ?)", (owner,))
        held = self._db.execute("SELECT value FROM meta WHERE name = 'owner'").fetchone()[0]
        if held != owner:
            raise ValueError(f"--outbox {self.path} belongs to {held}, not {owner}")

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def add(self, kind: str, ident: int, key: str, raw: bytes) -> None:
        """Keep a message (replacing one of the same kind and id); sent time 0: due at once."""
        with self._lock, self._db:
            self._db.execute(
                "INSERT OR REPLACE INTO outbox (kind, id, key, raw, sent, attempts) VALUES (?, ?, ?, ?, 0, 0)",
                (kind, ident, key, raw),
            )
            self._db.execute("DELETE FROM rejected WHERE kind = ? AND id = ?", (kind, ident))  # a new attempt

    def mark_sent(self, items: list[tuple[str, int]], again: bool = True) -> None:
        """The messages were sent now (again=False: heard of now, their resend timer restarts);
        `first_sent` keeps when each was first sent, whatever came after."""
        now = time.time()
        with self._lock, self._db:
            self._db.executemany(
                f"UPDATE outbox SET sent = ?, attempts = attempts + {int(again)}, "
                "first_sent = CASE WHEN attempts = 0 THEN ? ELSE first_sent END "
                "WHERE kind = ? AND id = ? AND (? OR attempts > 0)",
                [(now, now, kind, ident, again) for kind, ident in items],
            )

    def acknowledge(self, kind: str, ids: tuple[int, ...], store: str) -> tuple[list[float], float]:
        """Move acknowledged messages to `acked` (bytes kept, up to keep_bytes); returns the round-trip
        times (s) of those sent exactly once, and the latest time one of them was first sent (0 if none).

        A message sent more than once says nothing about the round trip: its Ack may answer
        either sending (Karn's rule).
        """
        now = time.time()
        latest = 0.0
        with self._lock, self._db:
            round_trips = []
            for i in ids:
                row = self._db.execute(
                    "DELETE FROM outbox WHERE kind = ? AND id = ? RETURNING sent, attempts, key, raw, first_sent",
                    (kind, i),
                ).fetchone()
                if row is None:  # a repeated Ack, or one for a message this outbox no longer holds
                    self._db.execute(
                        "INSERT INTO acked (kind, id, at, store) VALUES (?, ?, ?, ?) "
                        "ON CONFLICT (kind, id) DO UPDATE SET store = excluded.store",
                        (kind, i, now, store),
                    )
                    continue
                if row[1] == 1:
                    round_trips.append(now - row[0])
                latest = max(latest, row[4])
                raw = row[3] if self.keep_bytes > 0 else None
                self._db.execute(
                    "INSERT OR REPLACE INTO acked VALUES (?, ?, ?, ?, ?, ?)", (kind, i, now, store, row[2], raw)
                )
                self._retained += len(raw or b"")
            self._db.executemany("DELETE FROM rejected WHERE kind = ? AND id = ?", [(kind, i) for i in ids])
            if self._retained > self.keep_bytes:
                self._forget_oldest()
        return round_trips, latest

    def _forget_oldest(self) -> None:
        """Drop the bytes of the oldest acknowledged messages down to 90% of keep_bytes (lock held)."""
        excess = self._retained - int(0.9 * self.keep_bytes)
        rows = self._db.execute(
            "SELECT kind, id, LENGTH(raw) FROM acked WHERE raw IS NOT NULL ORDER BY at, kind, id"
        ).fetchall()
        drop = []
        for kind, ident, size in rows:
            if excess <= 0:
                break
            drop.append((kind, ident))
            excess -= size
            self._retained -= size
        self._db.executemany("UPDATE acked SET raw = NULL, key = NULL WHERE kind = ? AND id = ?", drop)

    def requeue_missing(self, scans, revision: int | None) -> tuple[dict[str, int], set[int]]:
        """After a store's inventory (`scans`: a container of the node ids it holds, `revision`: the
        newest pose-graph revision it applied): put back into the outbox the acknowledged messages it
        lacks whose bytes are kept. Returns ({store that had acknowledged them: messages requeued},
        node ids it lacks whose bytes are gone)."""
        with self._lock, self._db:
            rows = self._db.execute("SELECT kind, id, key, raw, store FROM acked").fetchall()
            missing = [
                row
                for row in rows
                if (row[1] not in scans if row[0] == "scan" else revision is None or row[1] > revision)
            ]
            kept = [row for row in missing if row[3] is not None]
            self._db.executemany("DELETE FROM acked WHERE kind = ? AND id = ?", [row[:2] for row in kept])
            self._db.executemany(
                "INSERT OR REPLACE INTO outbox (kind, id, key, raw, sent, attempts) VALUES (?, ?, ?, ?, 0, 0)",
                [row[:4] for row in kept],
            )
            self._retained -= sum(len(row[3]) for row in kept)
            by_store: dict[str, int] = {}
            for row in kept:
                by_store[row[4]] = by_store.get(row[4], 0) + 1
            gone = {row[1] for row in missing if row[0] == "scan" and row[3] is None}
        return by_store, gone

    def reject(self, kind: str, ids: tuple[int, ...], reason: str, detail: str) -> int:
        """Drop messages the server refused for good, keeping why; returns how many were still held."""
        now = time.time()
        with self._lock, self._db:
            removed = sum(
                self._db.execute("DELETE FROM outbox WHERE kind = ? AND id = ?", (kind, i)).rowcount for i in ids
            )
            self._db.executemany(
                "INSERT OR REPLACE INTO rejected VALUES (?, ?, ?, ?, ?)", [(kind, i, reason, detail, now) for i in ids]
            )
        return removed

    def rejected(self) -> list[tuple[str, int, str, str]]:
        """(kind, id, reason, detail) of every message refused and not accepted since."""
        with self._lock:
            return self._db.execute("SELECT kind, id, reason, detail FROM rejected ORDER BY kind, id").fetchall()

    def held(self, kind: str = "scan") -> set[int]:
        """Ids of the messages of `kind` still waiting for an answer."""
        with self._lock:
            return {i for (i,) in self._db.execute("SELECT id FROM outbox WHERE kind = ?", (kind,))}

    def unsent(self, limit: int) -> list[tuple[str, int, str, bytes]]:
        """Up to `limit` messages never sent yet, scans first, oldest first."""
        with self._lock:
            return self._db.execute(
                "SELECT kind, id, key, raw FROM outbox WHERE attempts = 0 ORDER BY kind DESC, id LIMIT ?", (limit,)
            ).fetchall()

    def in_flight(self) -> int:
        """Messages sent and not answered yet."""
        with self._lock:
            return self._db.execute("SELECT COUNT(*) FROM outbox WHERE attempts > 0").fetchone()[0]

    def due(self, now: float, timeout: float, silent: bool, passed: float) -> list[tuple[str, int, str, bytes]]:
        """Sent messages to send again at `now` (epoch s), oldest first: unanswered for `timeout` s
        since they were last sent or announced as queued, doubling after each further sending
        (MAX_DOUBLINGS times), and either the server is `silent` or it acknowledged a message first
        sent after their own first sending (at `passed`), so they were lost, not merely queued behind
        others. First sendings, not the latest: a resent message's Ack says nothing of the messages
        sent between its two sendings, which may well be queued.

        A server that is slow but answering is left to work through its queue: resending would only
        deepen it. The back-off's cap keeps a server that comes back after an outage from waiting
        long for the rest.
        """
        with self._lock:
            return self._db.execute(
                "SELECT kind, id, key, raw FROM outbox WHERE attempts > 0 AND "
                "sent + ? * (1 << MIN(attempts - 1, ?)) <= ? AND (? OR first_sent < ?) ORDER BY sent, kind DESC, id",
                (timeout, MAX_DOUBLINGS, now, silent, passed),
            ).fetchall()

    def pending(self) -> int:
        with self._lock:
            return self._db.execute("SELECT COUNT(*) FROM outbox").fetchone()[0]

    def acked(self, kind: str = "scan") -> set[int]:
        with self._lock:
            return {i for (i,) in self._db.execute("SELECT id FROM acked WHERE kind = ?", (kind,))}

    def known(self, kind: str = "scan") -> set[int]:
        """Ids of `kind` acknowledged or still held, read at once: an answer or a store's inventory
        moves a message between the two between two reads, and one read of each could miss it
        (a restarted agent once fitted such a scan again)."""
        with self._lock:
            rows = self._db.execute(
                "SELECT id FROM acked WHERE kind = ?1 UNION SELECT id FROM outbox WHERE kind = ?1", (kind,)
            )
            return {i for (i,) in rows}

    def resends(self) -> int:
        """Publications beyond the first of the messages still held."""
        with self._lock:
            return self._db.execute("SELECT COALESCE(SUM(MAX(attempts - 1, 0)), 0) FROM outbox").fetchone()[0]

    def last_id(self, kind: str = "scan") -> int | None:
        """The largest id of `kind` this outbox ever held (sent, acknowledged or refused)."""
        with self._lock:
            return self._db.execute(
                "SELECT MAX(id) FROM (SELECT id FROM outbox WHERE kind = ?1 UNION ALL "
                "SELECT id FROM acked WHERE kind = ?1 UNION ALL SELECT id FROM rejected WHERE kind = ?1)",
                (kind,),
            ).fetchone()[0]

    def next_revision(self) -> int:
        """1, 2, 3, ... across runs of this outbox: the server ignores revisions older than it holds."""
        with self._lock, self._db:
            row = self._db.execute("SELECT value FROM meta WHERE name = 'revision'").fetchone()
            revision = int(row[0]) + 1 if row else 1
            self._db.execute("INSERT OR REPLACE INTO meta VALUES ('revision', ?)", (str(revision),))
        return revision
