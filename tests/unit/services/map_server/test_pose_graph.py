"""A robot's pose graph applied node by node (protocol v2): out of order, in parts, anchors, and
as the store keeps it; checked against the plain model on random histories."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from services.map_server.pose_graph import PoseGraph
from support.pose_graphs import FLEET, ReferenceGraph, newest, random_history, update


def state(graph: PoseGraph):
    """The graph in the model's terms: {node: (revision, x)}, (anchor revision, x)."""
    nodes = {n: (rev, float(p.t[0])) for n, (rev, p) in graph.poses.items()}
    return nodes, None if graph.anchor is None else (graph.anchor_revision, float(graph.anchor.t[0]))


def applied(*updates) -> PoseGraph:
    graph = PoseGraph()
    for u in updates:
        graph.apply(u)
    return graph


def test_an_older_revision_sets_the_nodes_the_newer_one_does_not_list():
    graph = PoseGraph()
    assert graph.apply(update(2, [(0, 1.0), (1, 1.0)])) == (True, [0, 1], False)
    assert graph.apply(update(1, [(1, 0.5), (2, 0.5)])) == (True, [2], False)  # node 1 keeps revision 2's
    assert state(graph) == ({0: (2, 1.0), 1: (2, 1.0), 2: (1, 0.5)}, None)
    assert graph.revision == 2
    assert graph.apply(update(1, [(1, 0.5)])) == (False, [], False)  # nothing left for it to set


def test_parts_of_one_revision_all_apply_and_a_resent_part_changes_nothing():
    graph = applied(update(3, [(0, 1.0)]), update(3, [(1, 1.5)]))
    assert state(graph) == ({0: (3, 1.0), 1: (3, 1.5)}, None)
    assert graph.apply(update(3, [(0, 1.0)])) == (False, [], False)


def test_an_equal_pose_at_a_newer_revision_moves_nothing_but_outranks_older_parts():
    graph = applied(update(2, [(0, 1.0)]))
    assert graph.apply(update(4, [(0, 1.0)])) == (True, [], False)
    assert graph.apply(update(2, [(0, 0.5)])) == (False, [], False)  # a late part of revision 2 loses
    assert state(graph) == ({0: (4, 1.0)}, None)


def test_the_newest_revision_that_carried_an_anchor_wins():
    graph = PoseGraph()
    assert graph.apply(update(5, [], anchor=1.0)) == (True, [], True)
    assert graph.apply(update(3, [(0, 0.5)], anchor=0.5)) == (True, [0], False)  # its node, not its anchor
    assert graph.apply(update(7, [(0, 0.5)])) == (True, [], False)  # no anchor: the held one stays
    assert state(graph) == ({0: (7, 0.5)}, (5, 1.0))
    assert graph.apply(update(6, [], anchor=1.0)) == (True, [], False)  # same anchor, newer revision
    assert graph.apply(update(5, [], anchor=0.0)) == (False, [], False)
    assert graph.apply(update(8, [], anchor=0.0)) == (True, [], True)


def test_the_stored_form_and_the_revision_by_revision_replay_give_the_same_graph():
    graph = applied(update(4, [(1, 1.0), (5, 0.5)], anchor=1.5), update(2, [(0, 0.0), (1, 0.5)]), update(9, [(5, 0)]))
    merged = graph.as_update(FLEET, "r")
    assert (merged.revision, [n for n, _ in merged.poses]) == (9, [0, 1, 5])
    node_revisions = np.array([2, 4, 9], "<u8").tobytes()  # as the first schemas kept them beside `merged`
    assert state(PoseGraph.from_merged(merged, node_revisions, graph.anchor_revision)) == state(graph)
    pieces = graph.by_revision(FLEET, "r")
    assert [(p.revision, [n for n, _ in p.poses], p.anchor is not None) for p in pieces] == [
        (2, [0], False),
        (4, [1], True),
        (9, [5], False),
    ]
    assert state(applied(*pieces)) == state(graph) and applied(*pieces).revision == 9


def test_a_row_written_before_per_node_revisions_puts_everything_at_its_revision():
    old = PoseGraph.from_merged(update(6, [(0, 1.0), (3, 0.5)], anchor=0.0), None, None)
    assert state(old) == ({0: (6, 1.0), 3: (6, 0.5)}, (6, 0.0)) and old.revision == 6


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_random_histories_in_random_orders_agree_with_the_plain_model(seed):
    history = random_history(np.random.default_rng(seed))
    graph, model, newest_seen = PoseGraph(), ReferenceGraph(), -1
    for message in history:
        before = dict(graph.poses)
        applied_now, taken = graph.take(message)
        assert applied_now.changed == model.apply(message)
        assert sorted(taken) == sorted(
            n for n in graph.poses if graph.poses[n] is not before.get(n)
        )  # the rows to write
        newest_seen = max(newest_seen, message.revision)
        assert state(graph) == (model.nodes, model.anchor) and graph.revision == newest_seen
    final = newest(history)  # the order did not matter
    assert state(graph) == (final.nodes, final.anchor)
    assert state(applied(*graph.by_revision(FLEET, "r"))) == state(graph)
