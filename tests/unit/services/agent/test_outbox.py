"""The agent's durable outbox: back-off and flow control of resends, and its memory of what stores
acknowledged (kept bytes, requeueing what a store lacks, forgetting the oldest beyond its budget,
opening an outbox written before stores had names)."""

from __future__ import annotations

import sqlite3
import time

import pytest

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
    assert sorted((k, i, raw) for k, i, _, raw in box.unsent(10)) == [
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
    assert sorted(i for _, i, _, _ in box.unsent(10)) == [4, 5]
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


def test_outbox_backs_off_exponentially_and_measures_round_trips_of_first_sendings(tmp_path):
    box = Outbox(tmp_path / "o.db", "default", "r")
    box.add("scan", 1, "k1", b"one")
    box.add("scan", 2, "k2", b"two")
    box.mark_sent([("scan", 1), ("scan", 2)])
    box.mark_sent([("scan", 2)])  # a second sending: due again after 2 s, then 4 s, ... up to 16 s
    sent = time.time()
    due = lambda after: [i for _, i, _, _ in box.due(sent + after, 1.0, True, 0.0)]  # noqa: E731
    assert due(0.5) == [] and due(1.5) == [1] and due(2.5) == [1, 2]
    box.mark_sent([("scan", 2)] * 6)  # 8 sendings: 128 s, but at most 16
    assert due(15.5) == [1] and due(16.5) == [1, 2]
    trips, latest = box.acknowledge("scan", (1, 2), "s1")
    assert len(trips) == 1 and 0 <= trips[0] < 5  # scan 2 was sent more than once (Karn's rule)
    assert sent - 1 < latest <= time.time()
    box.close()


def test_outbox_resends_only_to_a_silent_server_or_what_a_later_ack_passed_over(tmp_path):
    box = Outbox(tmp_path / "o.db", "default", "r")
    for node in (1, 2, 3):
        box.add("scan", node, f"k{node}", b"x")
    assert [i for _, i, _, _ in box.unsent(2)] == [1, 2]
    box.mark_sent([("scan", 1), ("scan", 2)])
    assert box.in_flight() == 2 and [i for _, i, _, _ in box.unsent(5)] == [3]
    later = time.time() + 10
    assert box.due(later, 1.0, False, 0.0) == []  # the server answers others: slow, not silent
    assert [i for _, i, _, _ in box.due(later, 1.0, True, 0.0)] == [1, 2]  # silent
    assert [i for _, i, _, _ in box.due(later, 1.0, False, later)] == [1, 2]  # a message sent after them was acked
    box.mark_sent([("scan", 2)], again=False)  # a busy server says it has 2 queued: its timer restarts
    assert [i for _, i, _, _ in box.due(time.time() + 0.5, 1.0, True, 0.0)] == []
    box.close()


def test_an_ack_of_a_resent_message_does_not_pass_over_those_sent_in_between(tmp_path):
    """First sendings order the messages: scan 1 resent after 2 and 3 were first sent says nothing
    of 2 and 3 (they may be queued), an Ack of 3 says 2 was passed over."""
    box = Outbox(tmp_path / "o.db", "default", "r")
    for node in (1, 2, 3, 4):
        box.add("scan", node, f"k{node}", b"x")
    for node in (1, 2, 3, 4, 1):  # scan 1 is resent last
        box.mark_sent([("scan", node)])
        time.sleep(0.01)
    box.mark_sent([("scan", 4)], again=False)  # announced as queued: its timer restarts, not its order
    _, passed = box.acknowledge("scan", (1,), "A")
    later = time.time() + 10
    assert box.due(later, 1.0, False, passed) == []
    _, passed = box.acknowledge("scan", (3,), "A")
    assert [i for _, i, _, _ in box.due(later, 1.0, False, passed)] == [2]
    box.close()


def test_an_outbox_written_before_first_sendings_were_kept_opens(tmp_path):
    path = tmp_path / "old.db"
    db = sqlite3.connect(path)
    db.executescript(
        "CREATE TABLE outbox (kind TEXT NOT NULL, id INTEGER NOT NULL, key TEXT NOT NULL, raw BLOB NOT NULL, "
        "sent REAL NOT NULL, attempts INTEGER NOT NULL, PRIMARY KEY (kind, id)) WITHOUT ROWID; "
        "INSERT INTO outbox VALUES ('scan', 7, 'k7', x'00', 1.0, 1);"
    )
    db.commit()
    db.close()
    box = Outbox(path, "default", "r")
    assert [i for _, i, _, _ in box.due(time.time(), 1.0, True, 0.0)] == [7]
    box.add("scan", 8, "k8", b"y")
    assert [i for _, i, _, _ in box.unsent(5)] == [8]
    box.close()


def test_outbox_keeps_messages_until_acknowledged(tmp_path):
    box = Outbox(tmp_path / "o.db", "default", "r")
    box.add("scan", 1, "k1", b"one")
    box.add("poses", 1, "kp", b"graph")
    assert [(k, i) for k, i, _, _ in box.unsent(5)] == [("scan", 1), ("poses", 1)]  # scans first
    box.mark_sent([("scan", 1), ("poses", 1)])
    assert box.unsent(5) == [] and box.due(time.time(), 1.0, True, 0.0) == []
    assert [k for k, *_ in box.due(time.time() + 1.0, 1.0, True, 0.0)] == ["scan", "poses"]
    assert len(box.acknowledge("scan", (1, 7), "s1")[0]) == 1  # one round trip: scan 1, sent once
    assert box.pending() == 1 and box.acked("scan") == {1, 7}
    assert [box.next_revision(), box.next_revision()] == [1, 2]
    box.close()
    box = Outbox(tmp_path / "o.db", "default", "r")  # what is unacknowledged survives a restart
    assert box.pending() == 1 and box.next_revision() == 3
    box.close()
    with pytest.raises(ValueError, match="belongs to default/r"):
        Outbox(tmp_path / "o.db", "default", "other")


def test_known_is_what_was_acknowledged_or_is_held_whichever_table_holds_it(tmp_path):
    # A restarted agent does not fit these again; a store's inventory moves acknowledged messages
    # back into the outbox and their answers move them out, so the two are read as one.
    box = Outbox(tmp_path / "o.db", "default", "r")
    for ident in (1, 2, 3):
        box.add("scan", ident, f"k{ident}", b"x")
    box.add("poses", 9, "kp", b"graph")
    box.mark_sent([("scan", 1), ("scan", 2), ("scan", 3), ("poses", 9)])
    box.acknowledge("scan", (1, 2), "s1")
    assert box.known("scan") == {1, 2, 3} and box.known("poses") == {9}
    box.requeue_missing({2}, None)  # a fresh store lacks scan 1: held again
    assert box.held("scan") == {1, 3} and box.acked("scan") == {2} and box.known("scan") == {1, 2, 3}
    box.close()
