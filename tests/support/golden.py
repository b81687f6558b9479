"""Golden vectors of the wire protocol as plain JSON: what a vector's bytes hold (the wire map,
the decoded values, the codes of encoding "q"), shared by tests/golden/make_vectors.py, which
writes them, and tests/unit/protocol/test_golden.py, which checks them."""

from __future__ import annotations

import json
from pathlib import Path

import msgpack
import numpy as np

from gmm_core.mixture import Mixture
from protocol import quantize as qz
from protocol.bitstream import unpack_records
from protocol.codec import decode
from protocol.messages import (
    Ack,
    MapQuery,
    Message,
    PointQuery,
    PointReply,
    PoseGraphUpdate,
    Rejection,
    ScanMessage,
    StoreInventory,
)
from protocol.wire import pose_bytes, pose_vector

FOLDER = Path(__file__).resolve().parents[1] / "golden"


def wire_map(value):
    """The msgpack structure with bins as {"bin": hex}; JSON keeps the key order."""
    if isinstance(value, dict):
        return {key: wire_map(item) for key, item in value.items()}
    if isinstance(value, list):
        return [wire_map(item) for item in value]
    if isinstance(value, bytes):
        return {"bin": value.hex()}
    return value


def mixture_values(mixture: Mixture) -> dict:
    return {
        "support": mixture.support,
        "weights": mixture.weights.tolist(),
        "means": mixture.means.tolist(),
        "covariances": mixture.covariances.tolist(),
    }


def decoded_values(message: Message) -> dict:
    """The values of a decoded message; poses as their wire vectors, grids in C order."""
    kind = type(message).__name__
    if isinstance(message, ScanMessage):
        model = message.model
        return {
            "type": kind,
            "fleet": message.fleet,
            "robot": message.robot,
            "node": message.node,
            "stamp": message.stamp,
            "dim": message.dim,
            "pose": pose_vector(message.pose).tolist(),
            "origin": model.origin.tolist(),
            "max_range": model.max_range,
            "occupied": mixture_values(model.occupied),
            "free": mixture_values(model.free),
        }
    if isinstance(message, PoseGraphUpdate):
        return {
            "type": kind,
            "fleet": message.fleet,
            "robot": message.robot,
            "revision": message.revision,
            "dim": message.dim,
            "nodes": [node for node, _ in message.poses],
            "poses": [pose_vector(pose).tolist() for _, pose in message.poses],
            "anchor": None if message.anchor is None else pose_vector(message.anchor).tolist(),
        }
    if isinstance(message, (Ack, Rejection, StoreInventory)):
        values = {name: getattr(message, name) for name in message.__dataclass_fields__}
        if isinstance(message, StoreInventory):
            values["ranges"] = [list(pair) for pair in message.ranges]
        return {"type": kind} | {
            key: list(value) if isinstance(value, tuple) else value for key, value in values.items()
        }
    if isinstance(message, MapQuery):
        robots = None if message.robots is None else list(message.robots)
        return {"type": kind, "fleet": message.fleet, "lo": message.lo.tolist(), "hi": message.hi.tolist()} | {
            "resolution": message.resolution,
            "robots": robots,
        }
    if isinstance(message, PointQuery):
        robots = None if message.robots is None else list(message.robots)
        return {"type": kind, "fleet": message.fleet, "points": message.points.tolist()} | {
            "resolution": message.resolution,
            "robots": robots,
            "method": message.method,
        }
    if isinstance(message, PointReply):
        return {"type": kind, "fleet": message.fleet, "resolution": message.resolution} | {
            "probabilities": message.probabilities.tolist(),
            "method": message.method,
        }
    return {
        "type": kind,
        "fleet": message.fleet,
        "origin": message.origin.tolist(),
        "resolution": message.resolution,
        "shape": list(message.probabilities.shape),
        "probabilities": message.probabilities.reshape(-1).tolist(),
    }


def version_2_update(update: PoseGraphUpdate) -> bytes:
    """The bytes a version-2 encoder wrote for `update`: node ids one by one (u64), poses and the
    anchor as float64 (theta = -pi sent as pi), keys in the order of version 3."""
    wire = {"v": 2, "t": 2, "f": update.fleet, "r": update.robot, "d": update.dim, "rev": update.revision}
    wire["nodes"] = np.array([node for node, _ in update.poses], "<u8").tobytes()
    wire["poses"] = pose_bytes([pose for _, pose in update.poses], "<f8", "poses.poses")
    wire["anchor"] = None if update.anchor is None else pose_bytes([update.anchor], "<f8", "anchor")
    return msgpack.packb(wire, use_bin_type=True)


def record_codes(raw_mixture: dict, dim: int) -> list[dict]:
    """Every record of a "q" stream as {field: code}, in stream order."""
    fields = qz.record_fields(dim)
    stream = raw_mixture["c"]
    count = 8 * len(stream) // qz.record_bits(dim)
    codes = unpack_records(stream, count, qz.FIELD_WIDTHS[dim], "components")
    return [{name: int(code) for (name, _), code in zip(fields, record)} for record in codes]


def describe(data: bytes, about: str, encoding: str, fixed_point: bool) -> dict:
    """The JSON of a golden vector: the wire map, the decoded values and, for "q", the codes."""
    raw = msgpack.unpackb(data, raw=False)
    message = decode(data, max_bytes=len(data))
    scan = isinstance(message, ScanMessage)
    result = {"about": about, "encoding": encoding if scan else None, "bytes": len(data), "fixed_point": fixed_point}
    result |= {"wire": wire_map(raw), "decoded": decoded_values(message)}
    if scan and encoding == "q":
        result["codes"] = {
            part: record_codes(raw[key], message.dim) for part, key in (("occupied", "O"), ("free", "F"))
        }
    return result


def to_json(value, indent: str = "") -> str:
    """JSON with one key per line and every list of numbers (a row) on one line."""
    inner = indent + "  "
    if isinstance(value, dict) and value:
        items = [f"{inner}{json.dumps(key)}: {to_json(item, inner)}" for key, item in value.items()]
        return "{\n" + ",\n".join(items) + "\n" + indent + "}"
    if isinstance(value, list) and value and any(isinstance(item, (dict, list)) for item in value):
        return "[\n" + ",\n".join(inner + to_json(item, inner) for item in value) + "\n" + indent + "]"
    return json.dumps(value, ensure_ascii=False, separators=(", ", ": "))
