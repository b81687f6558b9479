"""The back ends that correct an agent's nodes: a log's fixed poses, a simulated optimiser's; what a
--source names."""

from __future__ import annotations

import numpy as np
import pytest

from gmm_core import Pose
from services.agent.sources import FixedCorrections, Node, RelaxingCorrections, load_nodes, parse_slice, parse_source


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


def test_a_source_is_a_known_kind_a_path_with_colons_or_named_as_an_unknown_kind(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "run:3.xyz").write_text("1 0 0\n0 1 0.5\n")
    assert parse_source("carmen:run:3.log") == ("carmen", "run:3.log")
    assert parse_source("run:3.xyz") == (None, "run:3.xyz")  # 'run' is no kind, but the file is there
    assert len(load_nodes("run:3.xyz")) == 1  # the xyz format guessed, colon and all
    with pytest.raises(ValueError, match=r"unknown source kind 'foo' \(known: carmen, .*rosbag, sim, ros2\)"):
        load_nodes("foo:/dir")
    with pytest.raises(FileNotFoundError, match="no such file or directory"):  # a path, not a kind
        load_nodes(str(tmp_path / "gone:1.xyz"))


def test_scans_a_to_b_must_select_some():
    assert parse_slice("2:5") == slice(2, 5) and parse_slice("-10:") == slice(-10, None)
    assert parse_slice("3:-1") == slice(3, -1)  # from either end: the log's length decides
    for empty in ("10:5", "4:4", "-2:-5"):
        with pytest.raises(ValueError, match="selects no scans"):
            parse_slice(empty)
