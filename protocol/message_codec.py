"""The maps of every message but the scan (docs/PROTOCOL.md): pose-graph updates, their node ids
as ranges and their poses as int32 codes (version 2's float64 poses still read), and the small
ones (acknowledgement, rejection, store inventory, map and point queries and replies) as plain
numbers and readable keys. protocol.codec frames them.
"""

from __future__ import annotations

import itertools

import numpy as np

from protocol.errors import ProtocolError
from protocol.keys import MAX_NODE, check_id
from protocol.messages import (
    MAX_QUERY_POINTS,
    Ack,
    MapQuery,
    MapReply,
    PointQuery,
    PointReply,
    PoseGraphUpdate,
    Rejection,
    StoreInventory,
    check_ranges,
    node_ranges,
)
from protocol.pose_codes import pose_codes, poses_of_codes
from protocol.wire import Fields, float32_bytes, float64_bytes, pose_bytes, pose_from_vector, pose_width

# --- pose-graph update: node ids as ranges, poses as int32 codes (protocol.pose_codes)


def _encode_poses(message: PoseGraphUpdate, encoding: str) -> dict:
    dim = message.dim
    # The anchor stays float64: one pose, and world frames (UTM, ECEF) lie millions of metres out.
    anchor = None if message.anchor is None else pose_bytes([message.anchor], "<f8", "anchor")
    nodes = [node for node, _ in message.poses]  # ascending: PoseGraphUpdate keeps them so
    return {
        "f": message.fleet,
        "r": message.robot,
        "d": dim,
        "rev": message.revision,
        "nodes": np.array(node_ranges(nodes), dtype="<u8").reshape(-1).tobytes(),
        "poses": pose_codes([pose for _, pose in message.poses], dim, "poses.poses").tobytes(),
        "anchor": anchor,
    }


def _decode_poses(f: Fields, max_components: int) -> PoseGraphUpdate:
    fleet, robot = check_id(f.get("f", "fleet"), "fleet"), check_id(f.get("r", "robot"), "robot")
    dim, revision = f.int("d", "dimension", 2, 3), f.int("rev", "revision")
    ranges = _ranges(f, "nodes", "poses.nodes")
    width, count = pose_width(dim), sum(stop - start for start, stop in ranges)
    codes = f.array("poses", "poses.poses", "<i4", count * width).reshape(count, width)  # sizes count first
    nodes = itertools.chain.from_iterable(range(start, stop) for start, stop in ranges)
    anchor = f.array("anchor", "anchor", "<f8", width, nullable=True)
    anchor_pose = None if anchor is None else pose_from_vector(anchor, "anchor")
    poses = tuple(zip(nodes, poses_of_codes(codes, dim, "poses.poses")))
    return PoseGraphUpdate(fleet, robot, revision, poses, anchor_pose)


def _ranges(f: Fields, key: str, field: str) -> tuple[tuple[int, int], ...]:
    """A bin u64 of start, stop pairs: sorted, disjoint, non-touching [start, stop), stop <= 2^63."""
    bounds = f.array(key, field, "<u8")
    if len(bounds) % 2:
        raise ProtocolError(field, f"must hold start, stop pairs, got {len(bounds)} numbers")
    values = bounds.tolist()
    return check_ranges(zip(values[::2], values[1::2]), field)


# --- version 2 (read, never written): float64 poses listed node by node, the anchor as in version 3


def _decode_poses_v2(f: Fields, max_components: int) -> PoseGraphUpdate:
    fleet, robot = check_id(f.get("f", "fleet"), "fleet"), check_id(f.get("r", "robot"), "robot")
    dim, revision = f.int("d", "dimension", 2, 3), f.int("rev", "revision")
    nodes = _counts(f.array("nodes", "poses.nodes", "<u8"), "poses.nodes")
    width = pose_width(dim)
    vectors = f.array("poses", "poses.poses", "<f8", len(nodes) * width).reshape(len(nodes), width)
    anchor = f.array("anchor", "anchor", "<f8", width, nullable=True)
    poses = tuple((node, pose_from_vector(vector, "poses.poses")) for node, vector in zip(nodes, vectors))
    anchor_pose = None if anchor is None else pose_from_vector(anchor, "anchor")
    return PoseGraphUpdate(fleet, robot, revision, poses, anchor_pose)


# --- ack, rejection, inventory, map query and reply: small, so plain numbers and readable keys


def _counts(array: np.ndarray, field: str) -> list[int]:
    if (array > MAX_NODE).any():
        raise ProtocolError(field, "must be integers in [0, 2^63-1]")
    return [int(value) for value in array]


def _encode_ack(message: Ack, encoding: str) -> dict:
    return {
        "f": message.fleet,
        "r": message.robot,
        "store": message.store,
        "kind": message.kind,
        "ids": np.array(message.ids, dtype="<u8").tobytes(),
        "queued": np.array(message.queued, dtype="<u8").tobytes(),
    }


def _decode_ack(f: Fields, max_components: int) -> Ack:
    fleet, robot = check_id(f.get("f", "fleet"), "fleet"), check_id(f.get("r", "robot"), "robot")
    ids = tuple(_counts(f.array("ids", "ids", "<u8"), "ids"))
    queued = tuple(_counts(f.array("queued", "queued", "<u8"), "queued"))
    return Ack(fleet, robot, check_id(f.get("store", "store"), "store"), f.get("kind", "kind"), ids, queued)


def _encode_rejection(message: Rejection, encoding: str) -> dict:
    return {
        "f": message.fleet,
        "r": message.robot,
        "store": message.store,
        "kind": message.kind,
        "ids": np.array(message.ids, dtype="<u8").tobytes(),
        "reason": message.reason,
        "detail": message.detail,
    }


def _decode_rejection(f: Fields, max_components: int) -> Rejection:
    fleet, robot = check_id(f.get("f", "fleet"), "fleet"), check_id(f.get("r", "robot"), "robot")
    ids = tuple(_counts(f.array("ids", "ids", "<u8"), "ids"))
    store, kind = check_id(f.get("store", "store"), "store"), f.get("kind", "kind")
    return Rejection(fleet, robot, store, kind, ids, f.get("reason", "reason"), f.get("detail", "detail"))


def _encode_inventory(message: StoreInventory, encoding: str) -> dict:
    return {
        "f": message.fleet,
        "r": message.robot,
        "store": message.store,
        "ranges": np.array(message.ranges, dtype="<u8").reshape(-1).tobytes(),
        "rev": message.revision,
    }


def _decode_inventory(f: Fields, max_components: int) -> StoreInventory:
    fleet, robot = check_id(f.get("f", "fleet"), "fleet"), check_id(f.get("r", "robot"), "robot")
    ranges = _ranges(f, "ranges", "ranges")
    revision = f.get("rev", "revision")
    if revision is not None:
        revision = f.int("rev", "revision")
    store = check_id(f.get("store", "store"), "store")
    return StoreInventory(fleet, robot, store, ranges, revision)


def _encode_map_query(message: MapQuery, encoding: str) -> dict:
    return {
        "f": message.fleet,
        "d": message.dim,
        "lo": float64_bytes(message.lo, "bbox.lo"),
        "hi": float64_bytes(message.hi, "bbox.hi"),
        "res": message.resolution + 0.0,
        "robots": None if message.robots is None else list(message.robots),
    }


def _decode_map_query(f: Fields, max_components: int) -> MapQuery:
    dim = f.int("d", "dimension", 2, 3)
    return MapQuery(
        check_id(f.get("f", "fleet"), "fleet"),
        f.array("lo", "bbox.lo", "<f8", dim),
        f.array("hi", "bbox.hi", "<f8", dim),
        f.float("res", "resolution"),
        _robots(f),
    )


def _encode_map_reply(message: MapReply, encoding: str) -> dict:
    return {
        "f": message.fleet,
        "d": message.dim,
        "origin": float64_bytes(message.origin, "origin"),
        "res": message.resolution + 0.0,
        "shape": list(message.probabilities.shape),
        "p": float32_bytes(message.probabilities, "probabilities"),
    }


def _decode_map_reply(f: Fields, max_components: int) -> MapReply:
    dim = f.int("d", "dimension", 2, 3)
    shape = f.get("shape", "shape")
    if type(shape) is not list or len(shape) != dim or any(type(n) is not int or not 1 <= n <= 2**31 for n in shape):
        raise ProtocolError("shape", f"must be {dim} integers in [1, 2^31], got {shape!r:.80}")
    cells = int(np.prod(shape, dtype=object))
    grid = f.array("p", "probabilities", "<f4", cells).reshape(shape)
    return MapReply(
        check_id(f.get("f", "fleet"), "fleet"),
        f.array("origin", "origin", "<f8", dim),
        f.float("res", "resolution"),
        grid,
    )


def _robots(f: Fields) -> tuple[str, ...] | None:
    robots = f.get("robots", "robots")
    if robots is not None and type(robots) is not list:
        raise ProtocolError("robots", f"must be an array of robot ids or nil, got {type(robots).__name__}")
    return None if robots is None else tuple(robots)


def _method(f: Fields) -> str:
    method = f.get("m", "method")
    if type(method) is not str:
        raise ProtocolError("method", f"must be a string, got {type(method).__name__}")
    return method


def _encode_point_query(message: PointQuery, encoding: str) -> dict:
    return {
        "f": message.fleet,
        "d": message.dim,
        "n": message.points.shape[0],
        "p": float64_bytes(message.points, "points"),
        "res": message.resolution + 0.0,
        "robots": None if message.robots is None else list(message.robots),
        "m": message.method,
    }


def _decode_point_query(f: Fields, max_components: int) -> PointQuery:
    dim = f.int("d", "dimension", 2, 3)
    n = f.int("n", "count", 1, MAX_QUERY_POINTS)
    return PointQuery(
        check_id(f.get("f", "fleet"), "fleet"),
        f.array("p", "points", "<f8", n * dim).reshape(n, dim),
        f.float("res", "resolution"),
        _robots(f),
        _method(f),
    )


def _encode_point_reply(message: PointReply, encoding: str) -> dict:
    return {
        "f": message.fleet,
        "res": message.resolution + 0.0,
        "p": float32_bytes(message.probabilities, "probabilities"),
        "m": message.method,
    }


def _decode_point_reply(f: Fields, max_components: int) -> PointReply:
    probabilities = f.array("p", "probabilities", "<f4")
    return PointReply(check_id(f.get("f", "fleet"), "fleet"), f.float("res", "resolution"), probabilities, _method(f))
