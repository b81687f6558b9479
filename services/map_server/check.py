"""Audit of a server's store, for crash trials, fuzzing and operators: is the file sound, and is
every row something the server would have accepted?

Opened read-only, so it can run beside a live server or on what a killed one left behind
(WAL included), without changing either.
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass, field
from pathlib import Path

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
        for fleet, robot, revision, raw in db.execute("SELECT fleet, robot, revision, raw FROM poses"):
            result.poses += 1
            try:
                m = decode(raw, expect=PoseGraphUpdate, max_bytes=max(len(raw), 1))  # merged graphs may be large
                if (m.fleet, m.robot, m.revision) != (fleet, robot, revision):
                    raise ProtocolError(
                        "key", f"row says {fleet}/{robot} r{revision}, message {m.fleet}/{m.robot} r{m.revision}"
                    )
            except ProtocolError as error:
                result.bad.append(f"poses {fleet}/{robot}: {error}")
        return result
    finally:
        db.close()
