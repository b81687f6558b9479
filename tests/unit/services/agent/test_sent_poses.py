"""services/agent/sent_poses.py: which corrections go out, and what is held per node."""

from __future__ import annotations

import numpy as np
import pytest

from gmm_core import Pose
from services.agent.sent_poses import SentPoses, beam_reach


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
