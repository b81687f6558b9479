"""The store audit: a sound store passes, a corrupt row is named."""

from __future__ import annotations

import sqlite3

from gmm_core import Pose
from protocol import PoseGraphUpdate
from services.map_server.check import check_store
from services.map_server.store import DB_NAME, Store


def test_the_audit_names_node_poses_that_do_not_fit_their_graph(tmp_path):
    store = Store(tmp_path)
    for revision, node in ((1, 0), (2, 1)):  # two updates of different nodes
        update = PoseGraphUpdate("f", "r", revision, ((node, Pose.from_xytheta(node, 0, 0)),))
        assert store.put_poses(update)
    store.close()
    assert check_store(tmp_path).ok and check_store(tmp_path).poses == 1

    def corrupt(statement, *args):
        with sqlite3.connect(tmp_path / DB_NAME) as db:
            db.execute(statement, args)
        db.close()
        return check_store(tmp_path).bad

    bad = corrupt("UPDATE node_poses SET revision = 7 WHERE node = 1")
    assert len(bad) == 1 and "node_poses.revision" in bad[0] and "outside 0..2" in bad[0]
    bad = corrupt("UPDATE node_poses SET revision = 1, pose = ? WHERE node = 1", bytes(40))
    assert len(bad) == 1 and "node_poses.pose of f/r" in bad[0] and "[40, 48]" in bad[0]
    bad = corrupt("UPDATE node_poses SET pose = ? WHERE node = 1", bytes(48))  # R = 0 is no rotation
    assert len(bad) == 1 and "not a rotation" in bad[0]
    bad = corrupt("DELETE FROM poses")
    assert bad == ["node_poses f/r: 2 node poses of a robot without a row in poses"]
