"""The store audit: a sound store passes, a corrupt row is named."""

from __future__ import annotations

import sqlite3

from gmm_core import Pose
from protocol import PoseGraphUpdate, encode
from services.map_server.check import check_store
from services.map_server.store import DB_NAME, Store


def test_the_audit_names_per_node_revisions_that_do_not_fit_their_graph(tmp_path):
    store = Store(tmp_path)
    for revision, node in ((1, 0), (2, 1)):  # two updates of different nodes: a merged graph
        update = PoseGraphUpdate("f", "r", revision, ((node, Pose.from_xytheta(node, 0, 0)),))
        assert store.put_poses(update, encode(update))
    store.close()
    assert check_store(tmp_path).ok
    with sqlite3.connect(tmp_path / DB_NAME) as db:
        db.execute("UPDATE poses SET node_revisions = ?", (bytes(8),))  # one revision for two poses
    bad = check_store(tmp_path).bad
    assert len(bad) == 1 and "node_revisions" in bad[0] and "2 poses" in bad[0]
    with sqlite3.connect(tmp_path / DB_NAME) as db:
        db.execute("UPDATE poses SET node_revisions = ?", ((7).to_bytes(8, "little") * 2,))
    assert "newer than the graph's 2" in check_store(tmp_path).bad[0]
