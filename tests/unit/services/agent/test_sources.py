"""The back ends that correct an agent's nodes: a log's fixed poses, a simulated optimiser's."""

from __future__ import annotations

import numpy as np

from gmm_core import Pose
from services.agent.sources import FixedCorrections, Node, RelaxingCorrections


def node(k: int, error: float) -> Node:
    truth = Pose.from_xytheta(float(k), 0.0, 0.0)
    return Node(k, None, Pose.from_xytheta(k + error, 0.0, 0.0), truth)  # type: ignore[arg-type]


def test_a_simulated_optimiser_moves_newer_nodes_more_and_converges_at_the_end():
    back_end, nodes = RelaxingCorrections(), {}
    residuals = []
    for closure in range(4):
        nodes[closure] = node(closure, 1.0)  # one new node per closure, 1 m off
        poses = back_end.closure(nodes, final=False)
        residuals.append({k: poses[k].t[0] - k for k in nodes})
    np.testing.assert_allclose(list(residuals[-1].values()), [1 / 16, 1 / 8, 1 / 4, 1 / 2])
    moves = [residuals[-2][k] - residuals[-1][k] for k in range(3)]
    assert moves[0] < moves[1] < moves[2]  # the closure moves old nodes less
    final = back_end.closure(nodes, final=True)
    assert all(np.allclose(final[k].t, nodes[k].corrected.t) for k in nodes)


def test_settled_nodes_are_left_out_until_the_last_closure():
    back_end = RelaxingCorrections()
    nodes = {0: node(0, 1.0)}
    for _ in range(RelaxingCorrections.HALVINGS):
        assert list(back_end.closure(nodes, final=False)) == [0]  # 2^-20 of its offset left at the 20th
    nodes[1] = node(1, 1.0)
    assert list(back_end.closure(nodes, final=False)) == [1]
    assert sorted(back_end.closure(nodes, final=True)) == [0, 1]


def test_a_log_back_end_gives_the_corrected_poses_as_they_are():
    nodes = {k: node(k, 0.3) for k in range(3)}
    poses = FixedCorrections().closure(nodes, final=False)
    assert all(poses[k] is nodes[k].corrected for k in nodes)
