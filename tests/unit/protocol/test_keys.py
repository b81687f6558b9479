"""protocol/keys.py: key expressions built and parsed, and every malformed key refused naming its part."""

import pytest

from protocol import (
    ProtocolError,
    ack_key,
    occupancy_key,
    parse_key,
    points_key,
    poses_key,
    poses_wildcard,
    scan_key,
    scan_wildcard,
)


def test_keys_build_and_parse():
    assert scan_key("f", "r-1", 42) == "gmmap/f/r-1/scan/42"
    assert poses_key("f", "r") == "gmmap/f/r/poses" and ack_key("f", "r") == "gmmap/f/r/ack"
    assert occupancy_key("f") == "gmmap/f/map/occupancy"
    assert scan_wildcard("f") == "gmmap/f/*/scan/*" and scan_wildcard() == "gmmap/*/*/scan/*"
    assert poses_wildcard("f") == "gmmap/f/*/poses"
    assert parse_key(scan_key("f", "r", 2**63 - 1)) == ("f", "r", "scan", 2**63 - 1)
    assert parse_key(poses_key("f", "r")) == ("f", "r", "poses", None)
    assert parse_key(ack_key("f", "r")) == ("f", "r", "ack", None)
    assert parse_key(occupancy_key("f")) == ("f", None, "occupancy", None)
    assert points_key("f") == "gmmap/f/map/points"
    assert parse_key(points_key("f")) == ("f", None, "points", None)
    assert parse_key("gmmap/f/map/poses") == ("f", "map", "poses", None)  # a robot may be called map


@pytest.mark.parametrize(
    "key, field",
    [
        ("other/f/r/poses", "key"),
        ("gmmap/f/r/scan", "key"),
        ("gmmap/f/r/scan/1/2", "key"),
        ("gmmap/f/r/scan/01", "key.node"),
        ("gmmap/f/r/scan/-1", "key.node"),
        ("gmmap/f/r/scan/*", "key.node"),
        (f"gmmap/f/r/scan/{2**63}", "key.node"),
        ("gmmap/f/r/scan/１", "key.node"),
        ("gmmap/f f/r/poses", "key.fleet"),
        ("gmmap/f/*/poses", "key.robot"),
        ("gmmap/f/r/status", "key"),
    ],
)
def test_parse_key_rejects(key, field):
    with pytest.raises(ProtocolError) as caught:
        parse_key(key)
    assert caught.value.field == field


def test_key_builders_reject_bad_ids():
    with pytest.raises(ProtocolError, match="^fleet:"):
        scan_key("a/b", "r", 1)
    with pytest.raises(ProtocolError, match="^node:"):
        scan_key("f", "r", -1)
    with pytest.raises(ProtocolError, match="^robot:"):
        poses_key("f", "*")
