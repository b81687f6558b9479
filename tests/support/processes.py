"""`gmmap` subprocesses of one test (server, agents, router), each logging to a file, and readers
of the SQLite files they leave (the server's store, an agent's outbox)."""
from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
from pathlib import Path

from support.net import wait_for
from support.paths import ROOT

HALVES = {"a": "0:455", "b": "455:910"}  # the two robots of the Intel replays, by scan range


class Processes:
    """Subprocesses of one test, each logging to a file; all killed at the end."""

    def __init__(self, tmp_path: Path):
        self.tmp = tmp_path
        self.running: list[subprocess.Popen] = []
        self.env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")

    def start(self, name: str, *args: str) -> subprocess.Popen:
        log = open(self.tmp / f"{name}.log", "ab")
        proc = subprocess.Popen([sys.executable, "-m", "services.cli", *args], cwd=self.tmp, env=self.env,
                                stdout=log, stderr=subprocess.STDOUT)
        proc.log_path = self.tmp / f"{name}.log"
        self.running.append(proc)
        return proc

    def log(self, proc) -> str:
        return proc.log_path.read_text(errors="replace")

    def ready(self, proc, banner: str) -> subprocess.Popen:
        wait_for(lambda: banner in self.log(proc) or proc.poll() is not None, 30, banner)
        assert proc.poll() is None, self.log(proc)
        return proc

    def server(self, name: str, data: Path, zport: int, hport: int, *zenoh: str) -> subprocess.Popen:
        zenoh = zenoh or ("--zenoh-listen", f"tcp/127.0.0.1:{zport}")
        proc = self.start(name, "server", *zenoh, "--http", f"127.0.0.1:{hport}", "--data-dir", str(data))
        return self.ready(proc, "gmmap server ready")

    def agent(self, robot: str, zport: int, data_dir: Path, *extra: str) -> subprocess.Popen:
        return self.start(f"agent-{robot}", "agent", "--robot", robot, "--zenoh-connect", f"tcp/127.0.0.1:{zport}",
                          "--source", f"carmen:{data_dir / 'radish' / 'intel.clf.bz2'}",
                          "--corrections", str(data_dir / "carmen" / "intel-corrected.log.gz"),
                          "--scans", HALVES[robot], "--outbox", str(self.tmp / f"outbox-{robot}.db"), *extra)

    def finish(self, proc, timeout: float) -> int:
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"{proc.args[3:5]} still running after {timeout} s:\n{self.log(proc)[-3000:]}")

    def kill_all(self) -> None:
        for proc in self.running:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def store_db(data: Path) -> sqlite3.Connection:
    return sqlite3.connect(f"file:{data / 'gmmap.db'}?mode=ro", uri=True, timeout=10)


def stored_nodes(data: Path, robot: str) -> set[int]:
    with store_db(data) as db:
        return {n for (n,) in db.execute("SELECT node FROM scans WHERE robot = ?", (robot,))}


def acked_nodes(outbox: Path) -> set[int]:
    db = sqlite3.connect(f"file:{outbox}?mode=ro", uri=True, timeout=10)
    try:
        return {n for (n,) in db.execute("SELECT id FROM acked WHERE kind = 'scan'")}
    finally:
        db.close()
