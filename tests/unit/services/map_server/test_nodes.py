"""The node store's change log: positions survive dropped entries."""

import pytest

from services.map_server import nodes
from services.map_server.nodes import ChangeLog, NodeKey


def test_change_log_positions_survive_dropped_entries(monkeypatch):
    monkeypatch.setattr(nodes, "CHANGE_LOG_LIMIT", 8)
    log = ChangeLog()
    keys = [NodeKey("r", i % 3) for i in range(6)]
    log.extend(keys)
    assert (log.start, log.end, log.since(2)) == (0, 6, [NodeKey("r", 2), NodeKey("r", 0), NodeKey("r", 1)])
    log.drop_before(4)
    assert (log.start, len(log), log.since(4)) == (4, 2, [NodeKey("r", 1), NodeKey("r", 2)])
    with pytest.raises(ValueError, match="dropped"):
        log.since(3)
    log.extend([NodeKey("s", i) for i in range(7)])  # 9 entries > 8: the oldest go, 4 are kept
    assert (log.start, log.end, log.since(9)) == (9, 13, [NodeKey("s", i) for i in range(3, 7)])
