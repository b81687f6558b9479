"""Zenoh key expressions, all in one place, and the id rules they rely on.

    gmmap/<fleet>/<robot>/scan/<node>   ScanMessage        (robot -> server, put)
    gmmap/<fleet>/<robot>/poses         PoseGraphUpdate    (robot -> server, put)
    gmmap/<fleet>/<robot>/ack           Ack, Rejection     (server -> robot, put)
    gmmap/<fleet>/<robot>/inventory     StoreInventory     (queryable of the map server: robot gets)
    gmmap/<fleet>/map/occupancy         MapQuery/MapReply  (queryable of the map server)
    gmmap/<fleet>/map/points            PointQuery/PointReply (queryable of the map server)

Ids match `[A-Za-z0-9_-]{1,64}`, so they can never contain the key separators or the
wildcards `*`, `$`, `?`, `#`.
"""

from __future__ import annotations

import re

from protocol.errors import ProtocolError

PREFIX = "gmmap"
ID_PATTERN = re.compile(r"[A-Za-z0-9_-]{1,64}")
MAX_NODE = 2**63 - 1  # node ids and revisions fit a signed 64-bit integer (SQLite INTEGER)


def check_id(value, field: str) -> str:
    """Return `value` if it is a valid fleet or robot id, else raise ProtocolError(field)."""
    if not isinstance(value, str) or ID_PATTERN.fullmatch(value) is None:
        raise ProtocolError(field, f"must match [A-Za-z0-9_-]{{1,64}}, got {value!r:.80}")
    return value


def check_count(value, field: str) -> int:
    """Return `value` if it is an int in [0, 2^63 - 1] (node id, revision), else raise."""
    if type(value) is not int or not 0 <= value <= MAX_NODE:  # bool is not a count
        raise ProtocolError(field, f"must be an integer in [0, 2^63-1], got {value!r:.80}")
    return value


def scan_key(fleet: str, robot: str, node: int) -> str:
    return f"{PREFIX}/{check_id(fleet, 'fleet')}/{check_id(robot, 'robot')}/scan/{check_count(node, 'node')}"


def poses_key(fleet: str, robot: str) -> str:
    return f"{PREFIX}/{check_id(fleet, 'fleet')}/{check_id(robot, 'robot')}/poses"


def ack_key(fleet: str, robot: str) -> str:
    return f"{PREFIX}/{check_id(fleet, 'fleet')}/{check_id(robot, 'robot')}/ack"


def inventory_key(fleet: str, robot: str) -> str:
    """Queryable of what a server's store holds of one robot (a StoreInventory)."""
    return f"{PREFIX}/{check_id(fleet, 'fleet')}/{check_id(robot, 'robot')}/inventory"


def occupancy_key(fleet: str) -> str:
    return f"{PREFIX}/{check_id(fleet, 'fleet')}/map/occupancy"


def points_key(fleet: str) -> str:
    """Queryable of the occupancy at points (a PointQuery, answered by a PointReply)."""
    return f"{PREFIX}/{check_id(fleet, 'fleet')}/map/points"


def _fleet_or_any(fleet: str | None) -> str:
    return "*" if fleet is None else check_id(fleet, "fleet")


def scan_wildcard(fleet: str | None = None) -> str:
    """Every robot's scans in `fleet` (every fleet when None)."""
    return f"{PREFIX}/{_fleet_or_any(fleet)}/*/scan/*"


def poses_wildcard(fleet: str | None = None) -> str:
    """Every robot's pose-graph updates in `fleet` (every fleet when None)."""
    return f"{PREFIX}/{_fleet_or_any(fleet)}/*/poses"


def inventory_wildcard(fleet: str | None = None) -> str:
    return f"{PREFIX}/{_fleet_or_any(fleet)}/*/inventory"


def occupancy_wildcard() -> str:
    """The occupancy queryables of every fleet."""
    return f"{PREFIX}/*/map/occupancy"


def parse_key(key: str) -> tuple[str, str | None, str, int | None]:
    """Split a concrete key into (fleet, robot, kind, node).

    kind is "scan", "poses", "ack", "inventory", "occupancy" or "points"; node is set for scans only,
    robot is None for occupancy and points. Anything else, including wildcards and non-canonical node numbers, raises.
    """
    parts = key.split("/") if isinstance(key, str) else []
    if len(parts) < 4 or parts[0] != PREFIX:
        raise ProtocolError("key", f"not a gmmap key: {key!r:.200}")
    fleet = check_id(parts[1], "key.fleet")
    if len(parts) == 4 and parts[2] == "map" and parts[3] in ("occupancy", "points"):
        return fleet, None, parts[3], None
    robot = check_id(parts[2], "key.robot")
    if len(parts) == 4 and parts[3] in ("poses", "ack", "inventory"):
        return fleet, robot, parts[3], None
    if len(parts) == 5 and parts[3] == "scan":
        text = parts[4]
        # Canonical decimal only, as scan_key writes it: no sign, no leading zeros.
        if not (text.isascii() and text.isdigit()) or str(int(text)) != text or int(text) > MAX_NODE:
            raise ProtocolError("key.node", f"must be a canonical decimal node id, got {text!r:.80}")
        return fleet, robot, "scan", int(text)
    raise ProtocolError("key", f"unknown key layout: {key!r:.200}")
