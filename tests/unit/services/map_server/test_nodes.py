"""The node store: change-log positions survive dropped entries; pose-graph updates apply node
by node (protocol v2) and move only the nodes whose world pose changed."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gmm_core import fit_scan
from protocol import ScanMessage
from services.map_server import nodes
from services.map_server.nodes import ChangeLog, NodeKey, NodeStore, ScanEntry
from support.pose_graphs import FLEET, ReferenceGraph, pose, random_history, update


def test_change_log_positions_survive_dropped_entries(monkeypatch):
    monkeypatch.setattr(nodes, "CHANGE_LOG_LIMIT", 8)
    log = ChangeLog()
    r = [NodeKey("r", i) for i in range(3)]
    log.extend([r[i % 3] for i in range(6)])  # each node twice: held once, at its latest change
    assert (log.start, log.end, len(log), log.since(2)) == (0, 6, 3, [r[2], r[1], r[0]])
    assert log.since(5) == [r[2]]
    log.drop_before(4)
    assert (log.start, len(log), log.since(4)) == (4, 2, [r[2], r[1]])
    with pytest.raises(ValueError, match="dropped"):
        log.since(3)
    s = [NodeKey("s", i) for i in range(7)]
    log.extend(s)  # 9 entries > 8: the oldest go, 4 are kept
    assert (log.start, log.end, log.since(9)) == (9, 13, s[:2:-1])


def test_change_log_holds_each_node_once_however_often_it_moves():
    log = ChangeLog()
    keys = [NodeKey("r", i) for i in range(100)]
    for _ in range(50):
        log.extend(keys)
    assert (len(log), log.end) == (100, 5000)
    assert set(log.since(4950)) == set(keys[50:]) and len(log.since(4900)) == 100


def test_the_oldest_changes_come_first_with_the_position_they_account_up_to_and_their_time(monkeypatch):
    clock = iter([10.0, 20.0, 30.0])
    monkeypatch.setattr(nodes.time, "monotonic", lambda: next(clock))
    log = ChangeLog()
    r = [NodeKey("r", i) for i in range(5)]
    log.extend(r[:3])  # positions 0-2 at t 10
    log.extend([r[0], r[3]])  # r0 moves again: 3, 4 at t 20
    log.extend([r[4]])  # 5 at t 30
    assert log.oldest_since(0, None) == (log.since(0), 6)
    assert log.oldest_since(0, 2) == ([r[2], r[1]], 3)  # r0's latest change (3) is past them
    assert log.oldest_since(3, 2) == ([r[3], r[0]], 5)
    assert log.oldest_since(3, 5) == (log.since(3), 6)
    assert [log.time_of(p) for p in (0, 2, 3, 4, 5)] == [10.0, 10.0, 20.0, 20.0, 30.0]
    log.drop_before(4)
    assert [log.time_of(p) for p in (4, 5)] == [20.0, 30.0] and len(log._batches) == 2


def test_batch_times_stay_bounded_and_never_make_a_change_look_newer(monkeypatch):
    monkeypatch.setattr(nodes, "BATCH_TIMES_LIMIT", 8)
    clock = iter(range(1, 100))
    monkeypatch.setattr(nodes.time, "monotonic", lambda: float(next(clock)))
    log = ChangeLog()
    for i in range(40):  # no tile drops them
        log.extend([NodeKey("r", i)])
    assert len(log._batches) <= 8
    assert all(log.time_of(p) <= p + 1 for p in range(40)) and log.time_of(39) > 30


@pytest.fixture(scope="module")
def model():
    rng = np.random.default_rng(1)
    return fit_scan(rng.normal(size=(40, 2)) * 0.2 + [2.0, 0.0], np.zeros((0, 2)))


def scan(model, node, x=0.0):
    return ScanMessage(FLEET, "r", node, float(node), model, pose(x))


def held_store(model, nodes):
    """A NodeStore holding scans `nodes` of robot r at the origin, and the boxes it marked moved."""
    marked = []
    store = NodeStore(moved=lambda lo, hi: marked.append(len(lo)))
    for n in nodes:
        store.add(scan(model, n, x=-1.0))
    marked.clear()
    return store, marked


def map_x(store, node):
    return float(store.robots["r"].nodes[node].map_pose.t[0])


def test_a_late_older_revision_sets_the_nodes_the_newer_one_does_not_list(model):
    store, _ = held_store(model, [0, 1, 2])
    assert store.robot_rows()[0]["pose_revision"] is None  # none yet: null, as a store inventory says it
    assert store.apply(update(2, [(0, 1.0), (1, 1.0)]))
    assert store.apply(update(1, [(1, 0.5), (2, 0.5)]))
    assert [map_x(store, n) for n in (0, 1, 2)] == [1.0, 1.0, 0.5]  # node 1 keeps revision 2's pose
    assert not store.apply(update(1, [(1, 0.5)]))
    assert store.robot_rows()[0]["pose_revision"] == 2


def test_corrections_of_scans_still_on_the_way_are_ordered_by_revision(model):
    store, _ = held_store(model, [])
    assert store.apply(update(3, [(5, 1.0)]))
    assert not store.apply(update(2, [(5, 0.5)]))  # older than the held correction
    assert store.apply(update(3, [(6, 1.5)]))  # another part of revision 3
    store.add(scan(model, 5))
    store.add(scan(model, 6))
    assert (map_x(store, 5), map_x(store, 6)) == (1.0, 1.5)
    assert store.apply(update(4, [(5, 0.0)])) and map_x(store, 5) == 0.0


def test_only_nodes_whose_world_pose_changed_are_moved(model):
    store, marked = held_store(model, [0, 1])
    assert store.apply(update(1, [(0, 1.0)], anchor=0.5)) and marked == [4]  # the anchor moves both, once each
    start, stamps = store.log.end, [store.posed(NodeKey("r", n)).stamp for n in (0, 1)]
    assert store.apply(update(2, [(0, 1.0)], anchor=0.5))  # the same poses at a newer revision
    assert (marked, store.log.end) == ([4], start)
    assert store.apply(update(1, [(1, 0.0)], anchor=0.0))  # node 1 had no correction; the anchor is revision 2's
    assert (marked, store.log.since(start)) == ([4, 2], [NodeKey("r", 1)])
    assert store.posed(NodeKey("r", 0)).stamp == stamps[0] and store.posed(NodeKey("r", 1)).stamp != stamps[1]
    assert float(store.robots["r"].anchor.t[0]) == 0.5
    assert not store.apply(update(1, [(0, 0.0)])) and marked == [4, 2]


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1))
def test_random_histories_with_scans_arriving_between_agree_with_the_plain_model(model, seed):
    """Each update: the same judgement as the model; each held node where the model puts it; moved
    (logged) exactly the held nodes whose world pose changed."""
    rng = np.random.default_rng(seed)
    history = random_history(rng, nodes=6)
    arrivals = {int(i): n for n, i in enumerate(rng.integers(0, len(history) + 1, size=6))}  # scan n before update i
    store, reference = NodeStore(moved=lambda lo, hi: None), ReferenceGraph()
    estimate = -1.0  # every scan's own pose: never one of X_VALUES

    def where(model_state, node):
        return model_state[0].get(node, (None, estimate))[1], model_state[1] and model_state[1][1]

    for i, message in enumerate(history + [None]):
        for n in sorted(n for j, n in arrivals.items() if j == i):
            store.add(scan(model, n, x=estimate))
        if message is None:
            break
        before, start = (dict(reference.nodes), reference.anchor), store.log.end
        assert store.apply(message) == reference.apply(message)
        after = (reference.nodes, reference.anchor)
        held = store.robots["r"].nodes
        assert {n: map_x(store, n) for n in held} == {n: where(after, n)[0] for n in held}
        assert set(store.log.since(start)) == {NodeKey("r", n) for n in held if where(before, n) != where(after, n)}
    assert store.robots["r"].revision == max(m.revision for m in history)
    anchor_x = reference.anchor[1] if reference.anchor is not None else 0.0  # all poses are along x
    for n in store.robots["r"].nodes:
        assert store.posed(NodeKey("r", n)).pose.t[0] == anchor_x + where(after, n)[0]


def test_a_batch_of_scans_is_held_as_the_same_scans_one_by_one(model):
    boxes = []
    one_by_one = NodeStore(moved=lambda lo, hi: boxes.append((lo, hi)))
    batched = NodeStore(moved=lambda lo, hi: boxes.append((lo, hi)))
    messages = [scan(model, n, x=0.5 * n) for n in range(5)] + [scan(model, 2, x=9.0)]  # node 2 twice
    messages.append(ScanMessage(FLEET, "q", 0, 0.0, model, pose(3.0)))
    assert [one_by_one.add(m, 10) for m in messages] == [True] * 5 + [False, True]
    assert batched.add_many([ScanEntry.of(m, 10) for m in messages]) == [True] * 5 + [False, True]
    assert len(boxes) == 6 + 1  # one by one, then once for the whole batch
    for robot in ("r", "q"):
        assert np.array_equal(batched.trajectory(robot), one_by_one.trajectory(robot))
    assert batched.robot_rows() == [
        {**row, "last_seen": batched.robots[row["robot"]].last_seen} for row in one_by_one.robot_rows()
    ]
    assert np.array_equal(np.concatenate([lo for lo, _ in boxes[:6]]), boxes[6][0])
    assert batched.log.since(0) == one_by_one.log.since(0)
