"""services/agent/sent_poses.py: the vectorised displacement bound against a pose-by-pose reference
(the translation's norm plus reach times the turn, by scipy's Rotation), and what is held per node."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gmm_core import Pose
from services.agent.sent_poses import SentPoses, beam_reach, displacement
from support.fuzz import random_rotations


def reference(a: Pose, b: Pose, reach: float) -> float:
    turn = a.R.T @ b.R
    if a.dim == 2:
        turn = np.block([[turn, np.zeros((2, 1))], [np.zeros((1, 2)), np.ones((1, 1))]])
    return float(np.linalg.norm(b.t - a.t)) + reach * float(Rotation.from_matrix(turn).magnitude())


@pytest.mark.parametrize("dim", [2, 3])
def test_displacement_matches_the_pose_by_pose_reference(dim):
    rng = np.random.default_rng(dim)
    n = 500
    R0 = random_rotations(rng, n, dim)
    small = random_rotations(rng, n, dim)  # turned by up to a few mrad from R0, or anything
    steps = rng.choice([1e-4, 1e-3, 1e-2, 1.0], n)
    if dim == 2:
        theta = rng.normal(0.0, 1.0, n) * steps
        small = np.stack([np.stack([np.cos(theta), -np.sin(theta)], 1), np.stack([np.sin(theta), np.cos(theta)], 1)], 1)
    else:
        axis = rng.normal(size=(n, 3))
        small = np.array([Pose.from_quaternion(np.zeros(3), [1.0, *(a * s)]).R for a, s in zip(axis, steps)])
    R1 = R0 @ small
    t0, t1 = rng.normal(0, 20, (n, dim)), rng.normal(0, 20, (n, dim)) * steps[:, None]
    t1 += t0
    reach = rng.uniform(0, 30, n)
    got = displacement(t0, R0, t1, R1, reach)
    want = [reference(Pose(a, x), Pose(b, y), r) for a, x, b, y, r in zip(R0, t0, R1, t1, reach)]
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)


def test_moved_compares_with_the_pose_held_and_counts_unknown_nodes_as_moved():
    held = SentPoses()
    held.scan_sent(1, Pose.from_xytheta(0.0, 0.0, 0.0), 10.0)
    held.scan_sent(2, Pose.from_xytheta(5.0, 0.0, 0.0), 10.0)
    held.corrections_sent({3: Pose.from_xytheta(9.0, 0.0, 0.0)})  # its scan was sent by an earlier run
    poses = {1: Pose.from_xytheta(0.0, 0.0, 0.0011), 2: Pose.from_xytheta(5.0, 0.0, 0.0009)}
    poses |= {3: Pose.from_xytheta(9.0, 0.0, 0.0), 4: Pose.from_xytheta(1.0, 1.0, 0.0)}
    assert sorted(held.moved(poses, 0.01)) == [1, 3, 4]  # 11 mm; 9 mm; reach unknown; never seen
    held.corrections_sent({1: poses[1]})
    assert held.moved({1: poses[1]}, 0.01) == {}
    held.scan_sent(1, Pose.from_xytheta(0.0, 0.0, 0.0), 10.0)  # sent again: the correction stays held
    assert held.moved({1: poses[1]}, 0.01) == {} and len(held) == 4 - 1  # node 4 was never recorded
    with pytest.raises(ValueError, match="3D"):
        held.moved({1: Pose.identity(3)}, 0.01)


def test_rows_grow_past_their_first_allocation():
    held = SentPoses()
    for node in range(3000):
        held.scan_sent(node, Pose.from_xytheta(node, 0.0, 0.0), 1.0)
    assert len(held) == 3000
    shifted = {node: Pose.from_xytheta(node + (0.02 if node % 1000 == 0 else 0.0), 0.0, 0.0) for node in range(3000)}
    assert sorted(held.moved(shifted, 0.01)) == [0, 1000, 2000]


def test_beam_reach_counts_hits_and_no_return_ends():
    hits = np.array([[3.0, 4.0], [1.0, 0.0]])
    assert beam_reach(hits, np.empty((0, 2)), 10.0) == 5.0
    assert beam_reach(hits, np.array([[0.6, 0.8]]), 10.0) == pytest.approx(10.0)
    assert beam_reach(np.empty((0, 3)), np.empty((0, 3)), 10.0) == 0.0
