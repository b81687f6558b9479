"""`gmmap` subprocesses of one test (server, agents, router) on the product's harness
(services.sim.processes), and readers of the SQLite files they leave (the server's store, an
agent's outbox)."""

from __future__ import annotations

import sqlite3
import subprocess
from pathlib import Path

from services.sim.processes import EVERY_SCAN, Processes

HALVES = {"a": "0:455", "b": "455:910"}  # the two robots of the Intel replays, by scan range


class TestProcesses(Processes):
    """The product's `Processes` in the tests' terms: helpers take the Popen that `start`
    returned, `server` and `agent` take a name and the Intel halves, `finish` fails with the log."""

    __test__ = False  # not a test class, despite its name

    def __init__(self, tmp_path: Path):
        super().__init__(tmp_path)
        self.names: dict[subprocess.Popen, str] = {}

    def start(self, name: str, *args: str, **options) -> subprocess.Popen:
        proc = super().start(name, *args, **options)
        self.names[proc] = name
        return proc

    def log(self, proc: subprocess.Popen) -> str:
        """The whole log of the child's name: its predecessors of that name included."""
        return self.log_path(self.names[proc]).read_text(errors="replace")

    def ready(self, proc: subprocess.Popen, banner: str) -> subprocess.Popen:
        return self.wait_ready(self.names[proc], banner)

    def server(
        self, name: str, data: Path, zport: int, hport: int, *zenoh: str, extra: tuple[str, ...] = ()
    ) -> subprocess.Popen:
        """A ready map server on HTTP port `hport`, listening on `zport` unless `zenoh` options say otherwise;
        `extra`: more `gmmap server` options."""
        zenoh_port = None if zenoh else zport
        return super().server(zenoh_port, f"127.0.0.1:{hport}", data, "default", *zenoh, *extra, name=name)

    def agent(self, robot: str, zport: int, data_dir: Path, *extra: str) -> subprocess.Popen:
        """Robot a or b replaying its half of the Intel log (raw scans, corrected poses) to `zport`;
        every scan is a node (no keyframe policy), so the tests can count them."""
        return self.start(
            f"agent-{robot}",
            "agent",
            "--robot",
            robot,
            "--zenoh-connect",
            f"tcp/127.0.0.1:{zport}",
            "--source",
            f"carmen:{data_dir / 'radish' / 'intel.clf.bz2'}",
            "--corrections",
            str(data_dir / "carmen" / "intel-corrected.log.gz"),
            "--scans",
            HALVES[robot],
            "--outbox",
            str(self.workdir / f"outbox-{robot}.db"),
            *EVERY_SCAN,
            *extra,
        )

    def finish(self, proc: subprocess.Popen, timeout: float) -> int:
        """The child's exit code; an AssertionError with its log if it still runs after `timeout` s."""
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            tail = self.log(proc)[-3000:]
            raise AssertionError(f"{self.names[proc]} still running after {timeout} s:\n{tail}") from None


def store_db(data: Path) -> sqlite3.Connection:
    return sqlite3.connect(f"file:{data / 'gmmap.db'}?mode=ro", uri=True, timeout=10)


def stored_nodes(data: Path, robot: str) -> set[int]:
    with store_db(data) as db:
        return {n for (n,) in db.execute("SELECT node FROM scans WHERE robot = ?", (robot,))}


def acked_nodes(outbox: Path) -> set[int]:
    """Scans the server has acknowledged to the agent of `outbox` (which that agent must have opened)."""
    return _scans_in(outbox, "SELECT id FROM acked WHERE kind = 'scan'")


def written_nodes(outbox: Path) -> set[int]:
    """Scans the agent of `outbox` has put in it (the first step of sending one): acknowledged or held.

    One query, so one snapshot: a scan acknowledged between two reads would be in neither.
    """
    return _scans_in(outbox, "SELECT id FROM acked WHERE kind = 'scan' UNION SELECT id FROM outbox WHERE kind = 'scan'")


def rejected_nodes(outbox: Path) -> set[int]:
    """Scans the server refused for good to the agent of `outbox` (its table `rejected`)."""
    return _scans_in(outbox, "SELECT id FROM rejected WHERE kind = 'scan'")


def _scans_in(outbox: Path, query: str) -> set[int]:
    db = sqlite3.connect(f"file:{outbox}?mode=ro", uri=True, timeout=10)
    try:
        return {n for (n,) in db.execute(query)}
    finally:
        db.close()
