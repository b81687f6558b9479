"""The outbox's memory of what stores acknowledged: kept bytes, requeueing what a store lacks,
forgetting the oldest beyond its budget, and opening an outbox written before stores had names."""

from __future__ import annotations

import sqlite3

from protocol import StoreInventory
from services.agent.outbox import Outbox


def test_a_store_that_lacks_acknowledged_messages_gets_them_again(tmp_path):
    box = Outbox(tmp_path / "o.db", "default", "r")
    for node in range(5):
        box.add("scan", node, f"k{node}", b"scan %d" % node)
    box.add("poses", 1, "kp", b"graph 1")
    box.mark_sent([("scan", n) for n in range(5)] + [("poses", 1)])
    box.acknowledge("scan", tuple(range(5)), "A")
    box.acknowledge("poses", (1,), "A")
    assert box.pending() == 0 and box.acked("scan") == set(range(5))
    # store A, restored from an old backup, holds scans 0-2 and no pose graph
    requeued, gone = box.requeue_missing(StoreInventory.of("default", "r", "A", [0, 1, 2]), None)
    assert requeued == {"A": 3} and gone == set()
    assert sorted((k, i, raw) for k, i, _, raw in box.due(0, 1.0)) == [
        ("poses", 1, b"graph 1"),
        ("scan", 3, b"scan 3"),
        ("scan", 4, b"scan 4"),
    ]
    box.acknowledge("scan", (3, 4), "B")
    box.acknowledge("poses", (1,), "B")
    assert box.requeue_missing(StoreInventory.of("default", "r", "B", range(5), 1), 1) == ({}, set())
    box.close()


def test_beyond_its_budget_the_outbox_forgets_the_oldest_bytes_and_says_which_nodes(tmp_path):
    box = Outbox(tmp_path / "o.db", "default", "r", keep_bytes=250)
    for node in range(6):
        box.add("scan", node, f"k{node}", bytes(100))
        box.mark_sent([("scan", node)])
        box.acknowledge("scan", (node,), "A")
    # 600 bytes acknowledged, at most 250 kept: the newest two
    requeued, gone = box.requeue_missing(StoreInventory.of("default", "r", "B", []), None)
    assert requeued == {"A": 2} and gone == {0, 1, 2, 3}
    assert sorted(i for _, i, _, _ in box.due(0, 1.0)) == [4, 5]
    box.close()


def test_an_outbox_of_protocol_version_1_opens_and_its_acks_have_no_store(tmp_path):
    path = tmp_path / "old.db"
    db = sqlite3.connect(path)
    db.executescript(
        "CREATE TABLE acked (kind TEXT NOT NULL, id INTEGER NOT NULL, at REAL NOT NULL, PRIMARY KEY (kind, id)) "
        "WITHOUT ROWID; INSERT INTO acked VALUES ('scan', 0, 1.0), ('scan', 1, 1.0);"
    )
    db.commit()
    db.close()
    box = Outbox(path, "default", "r")
    assert box.acked("scan") == {0, 1}
    # a store without node 1: its bytes were never kept, so the agent must fit it again
    assert box.requeue_missing(StoreInventory.of("default", "r", "A", [0]), None) == ({}, {1})
    box.close()
