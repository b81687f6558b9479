"""Acknowledgements bound to a store: an outbox remembers which store acknowledged what, and a
store that lacks what was acknowledged (a fresh data directory, a restored backup) gets it again."""

from __future__ import annotations

import re
import shutil

from support.net import free_port
from support.processes import store_db, stored_nodes


def store_identity(data) -> str:
    with store_db(data) as db:
        return db.execute("SELECT value FROM meta WHERE name = 'store'").fetchone()[0]


def stored_revision(data, robot: str) -> int | None:
    with store_db(data) as db:
        row = db.execute("SELECT revision FROM poses WHERE robot = ?", (robot,)).fetchone()
    return row and row[0]


def test_one_outbox_against_two_fresh_servers_fills_both(procs, data_dir, tmp_path):
    nodes = set(range(60))
    summaries = []
    for name in ("first", "second"):
        zport, hport, data = free_port(), free_port(), tmp_path / name
        procs.server(f"server-{name}", data, zport, hport)
        agent = procs.agent("a", zport, data_dir, "--scans", "0:60", "--timeout", "60")  # the same outbox
        assert procs.finish(agent, 120) == 0, procs.log(agent)
        summaries.append(procs.log(agent).strip().splitlines()[-1])
        assert stored_nodes(data, "a") == nodes, name
        assert stored_revision(data, "a") is not None  # the pose graph too
        assert procs.stop(f"server-{name}") == 0
    first, second = store_identity(tmp_path / "first"), store_identity(tmp_path / "second")
    assert first != second
    assert f"acknowledged by store {first}" in summaries[0] and "lacked" not in summaries[0], summaries[0]
    # the second run fitted nothing (all resumed) and sent the kept bytes to the store that lacked them
    assert f"acknowledged by store {second}" in summaries[1], summaries[1]
    assert "60 of them from a previous run: resumed" in summaries[1], summaries[1]
    assert f"acknowledged by store {first}" in summaries[1].split("sent again", 1)[1], summaries[1]


def test_a_server_restored_from_an_old_backup_gets_the_rest_again(procs, data_dir, tmp_path):
    zport, hport, data, backup = free_port(), free_port(), tmp_path / "data", tmp_path / "backup"
    procs.server("server", data, zport, hport)
    agent = procs.agent("a", zport, data_dir, "--scans", "0:20", "--timeout", "60")
    assert procs.finish(agent, 120) == 0, procs.log(agent)
    assert procs.stop("server") == 0
    shutil.copytree(data, backup)  # the backup holds scans 0-19
    procs.server("server", data, zport, hport)
    agent = procs.agent("a", zport, data_dir, "--scans", "0:50", "--timeout", "60")
    assert procs.finish(agent, 120) == 0, procs.log(agent)
    assert procs.stop("server") == 0
    shutil.rmtree(data)
    shutil.copytree(backup, data)  # disaster: the store is restored from the backup (same identity)
    procs.server("server", data, zport, hport)
    agent = procs.agent("a", zport, data_dir, "--scans", "0:50", "--timeout", "60")
    assert procs.finish(agent, 120) == 0, procs.log(agent)
    assert stored_nodes(data, "a") == set(range(50))
    summary = procs.log(agent).strip().splitlines()[-1]
    lacked = re.search(r"the store lacked (\d+) acknowledged messages", summary)
    assert lacked and int(lacked[1]) >= 30, summary  # scans 20-49, and the pose-graph updates after the backup


def test_what_the_outbox_no_longer_keeps_is_fitted_again_from_the_source(procs, data_dir, tmp_path):
    zport, hport = free_port(), free_port()
    procs.server("server-1", tmp_path / "one", zport, hport)
    agent = procs.agent("a", zport, data_dir, "--scans", "0:30", "--timeout", "60", "--keep-acked-mb", "0")
    assert procs.finish(agent, 120) == 0, procs.log(agent)
    assert procs.stop("server-1") == 0
    procs.server("server-2", tmp_path / "two", zport, hport)  # a fresh store; the outbox kept no bytes
    agent = procs.agent("a", zport, data_dir, "--scans", "0:30", "--timeout", "60", "--keep-acked-mb", "0")
    assert procs.finish(agent, 120) == 0, procs.log(agent)
    assert stored_nodes(tmp_path / "two", "a") == set(range(30))
    assert "30 scans no longer kept were fitted again" in procs.log(agent).strip().splitlines()[-1]
