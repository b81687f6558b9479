"""msgpack codec: encode(message) -> bytes and decode(bytes) -> message; layout in docs/PROTOCOL.md.

Every message is one msgpack map with a version "v" and a type code "t". Scan messages also
name the encoding "e" of their two mixtures: "f32" (float32 tables, lossless for float32
inputs) or "q" (quantised, about a third of the size; see protocol.quantize). Pose-graph updates
carry int32 pose codes (protocol.pose_codes) since version 3; version 2 messages are still read.
decode() trusts nothing: whatever the bytes, it returns a valid message or raises ProtocolError.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np

from gmm_core.mixture import Mixture
from gmm_core.scan import ScanModel
from protocol.errors import ProtocolError
from protocol.keys import MAX_NODE, check_id
from protocol.messages import (
    MAX_QUERY_POINTS,
    Ack,
    MapQuery,
    MapReply,
    Message,
    PointQuery,
    PointReply,
    PoseGraphUpdate,
    Rejection,
    ScanMessage,
    StoreInventory,
    check_ranges,
    node_ranges,
)
from protocol.pose_codes import pose_codes, poses_of_codes
from protocol.quantize import dequantize, quantize, record_bits, stream_bytes
from protocol.wire import Fields, float32_bytes, float64_bytes, pose_bytes, pose_from_vector, pose_width

VERSION = 3  # what the encoder writes
# Versions the decoder reads: version 2 differs only in its pose-graph updates (float64 poses,
# listed node by node), which map servers' stores and robots' outboxes still hold.
READS = (2, 3)
# What changed from a version no longer read, for the error an old peer's message gets.
VERSION_CHANGES = {1: "acknowledgements name the store; pose-graph updates apply node by node"}
ENCODINGS = ("q", "f32")
MAX_COMPONENTS = 4096  # default cap on occupied + free components of one scan
MAX_BYTES = 1 << 20  # default cap on a payload, checked before unpacking
MAX_LIST = 65536  # msgpack arrays (robot lists, grid shapes) are short
WEIGHT_SUM_TOLERANCE = 1e-3
SYMMETRY_TOLERANCE = 1e-6  # relative to the component's largest covariance entry
UNCHECKED = "unchecked error"  # prefix of errors caught by the safety net, not a named check

TYPE_CODES = {
    ScanMessage: 1,
    PoseGraphUpdate: 2,
    Ack: 3,
    MapQuery: 4,
    MapReply: 5,
    Rejection: 6,
    StoreInventory: 7,
    PointQuery: 8,
    PointReply: 9,
}


def encode(message: Message, encoding: str = "q") -> bytes:
    """Message -> bytes. `encoding` ("q" or "f32") applies to scan mixtures; other messages
    ignore it. Raises ProtocolError for anything decode() would reject (NaN, non-PD, ...)."""
    if encoding not in ENCODINGS:
        raise ProtocolError("encoding", f"must be one of {ENCODINGS}, got {encoding!r:.80}")
    code = TYPE_CODES.get(type(message))
    if code is None:
        raise ProtocolError("message", f"cannot encode {type(message).__name__}")
    body = _ENCODERS[code](message, encoding)
    return msgpack.packb({"v": VERSION, "t": code, **body}, use_bin_type=True)


def decode(
    data: bytes, *, expect: type | None = None, max_components: int = MAX_COMPONENTS, max_bytes: int = MAX_BYTES
) -> Message:
    """bytes -> a valid message, or ProtocolError naming the offending field; nothing else.

    `expect` (a message class) rejects any other type; `max_components` caps the components
    of a scan (occupied + free); `max_bytes` caps the payload (raise it for large MapReply).
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError("message", f"must be bytes, got {type(data).__name__}")
    if len(data) > max_bytes:
        raise ProtocolError("message", f"payload of {len(data)} bytes exceeds the maximum of {max_bytes}")
    try:
        raw = msgpack.unpackb(
            bytes(data),
            raw=False,
            strict_map_key=True,
            object_pairs_hook=_map_without_duplicates,
            max_str_len=1024,
            max_bin_len=max_bytes,
            max_array_len=MAX_LIST,
            max_map_len=64,
            max_ext_len=0,
            ext_hook=_refuse_ext,  # max_ext_len lets an ext of 0 bytes through
        )
    except Exception as error:  # msgpack raises several types (FormatError, ValueError, StackError, ...)
        raise ProtocolError("message", f"malformed msgpack: {type(error).__name__}: {error}") from None
    try:
        message = _decode_message(Fields(raw), max_components)
    except ProtocolError:
        raise
    except Exception as error:  # a check we missed must still surface as a protocol error
        raise ProtocolError("message", f"{UNCHECKED}: {type(error).__name__}: {error}") from None
    if expect is not None and not isinstance(message, expect):
        raise ProtocolError("type", f"expected {expect.__name__}, got {type(message).__name__}")
    return message


def _refuse_ext(code, data):
    raise ValueError(f"ext type {code} is not part of the protocol")


def _map_without_duplicates(pairs):
    result = dict(pairs)
    if len(result) != len(pairs):
        raise ValueError("duplicate map key")
    return result


def _decode_message(f: Fields, max_components: int) -> Message:
    version = f.get("v", "version")
    if type(version) is not int or version not in READS:
        known = type(version) is int and version in VERSION_CHANGES
        change = f" (version {version + 1}: {VERSION_CHANGES[version]}; upgrade the peer)" if known else ""
        reads = " and ".join(map(str, READS))
        raise ProtocolError("version", f"unsupported version {version!r:.80}, this decoder reads {reads}{change}")
    code = f.get("t", "type")
    decoder = (_DECODERS if version == VERSION else _DECODERS_V2).get(code) if type(code) is int else None
    if decoder is None:
        raise ProtocolError("type", f"unknown message type {code!r:.80}")
    return decoder(f, max_components)


# --- mixtures


def _check_mixture(mixture: Mixture, field: str) -> None:
    """What both encodings demand of a mixture: finite, weights >= 0 summing to 1, symmetric
    positive definite covariances (Cholesky must succeed, as the map server will run it)."""
    for name in ("weights", "means", "covariances"):
        if not np.isfinite(getattr(mixture, name)).all():
            raise ProtocolError(f"{field}.{name}", "must be finite (no NaN or inf)")
    if mixture.n_components == 0:
        return
    weights, covs = mixture.weights, mixture.covariances
    if (weights < 0).any():
        raise ProtocolError(f"{field}.weights", f"negative weight at component {int(np.argmax(weights < 0))}")
    if abs(weights.sum() - 1) > WEIGHT_SUM_TOLERANCE:
        raise ProtocolError(f"{field}.weights", f"sum to {weights.sum():.6g}, not 1")
    scale = np.abs(covs).max(axis=(1, 2))
    asymmetric = np.abs(covs - np.swapaxes(covs, 1, 2)).max(axis=(1, 2)) > SYMMETRY_TOLERANCE * scale
    if asymmetric.any():
        raise ProtocolError(f"{field}.covariances", f"not symmetric at component {int(np.argmax(asymmetric))}")
    try:
        np.linalg.cholesky(covs)
    except np.linalg.LinAlgError:
        bad = np.linalg.eigvalsh(covs).min(axis=1) <= 0
        where = f" at component {int(np.argmax(bad))}" if bad.any() else ""
        raise ProtocolError(f"{field}.covariances", f"not positive definite{where}") from None


def _f32_columns(dim: int) -> int:
    return dim + dim * (dim + 1) // 2 + 1  # mean, upper triangle of the covariance, weight


def _mixture_from_table(table: np.ndarray, dim: int, support: int) -> Mixture:
    table = table.astype(np.float64)
    rows, cols = np.triu_indices(dim)
    covs = np.zeros((len(table), dim, dim))
    covs[:, rows, cols] = table[:, dim:-1]
    covs[:, cols, rows] = table[:, dim:-1]
    return Mixture(table[:, -1], table[:, :dim], covs, support)


def _encode_mixture(mixture: Mixture, encoding: str, field: str) -> dict:
    _check_mixture(mixture, field)
    k, d = mixture.n_components, mixture.dim
    if encoding == "f32":
        rows, cols = np.triu_indices(d)
        table = np.concatenate([mixture.means, mixture.covariances[:, rows, cols], mixture.weights[:, None]], axis=1)
        packed = float32_bytes(table, f"{field}.components")
        # float32 rounding can break positive definiteness of a thin component: check what we send
        _check_mixture(_mixture_from_table(np.frombuffer(packed, "<f4").reshape(k, _f32_columns(d)), d, 0), field)
        return {"N": mixture.support, "c": packed}
    float32_bytes(mixture.means, f"{field}.means")  # the box of the means is sent as float32
    bounds, stream = quantize(mixture)
    wire = {"N": mixture.support, "c": stream}
    if k:  # an empty mixture has no box of means
        wire["b"] = float32_bytes(bounds, f"{field}.bounds")
    return wire


def _component_count(stream: np.ndarray, dim: int, encoding: str, field: str) -> int:
    """K follows from the length of "c": 4 * columns bytes per f32 row; for "q", records of
    record_bits(dim) > 8 bits padded to a whole byte, so each length fits at most one K."""
    if encoding == "f32":
        row = 4 * _f32_columns(dim)
        if len(stream) % row:
            raise ProtocolError(field, f"length {len(stream)} is not a multiple of {row} bytes")
        return len(stream) // row
    count = 8 * len(stream) // record_bits(dim)
    if stream_bytes(count, dim) != len(stream):
        raise ProtocolError(field, f"length {len(stream)} bytes fits no whole number of {record_bits(dim)}-bit records")
    return count


def _decode_mixture(f: Fields, stream: np.ndarray, count: int, dim: int, encoding: str) -> Mixture:
    support = f.int("N", "support")
    if encoding == "f32":
        table = np.frombuffer(stream, "<f4").reshape(count, _f32_columns(dim))
        if not np.isfinite(table).all():
            raise ProtocolError(f.name("components"), "must be finite (no NaN or inf)")
        mixture = _mixture_from_table(table, dim, support)
        _check_mixture(mixture, f.prefix)
        return mixture
    if count == 0:
        return Mixture(np.zeros(0), np.zeros((0, dim)), np.zeros((0, dim, dim)), support)
    bounds = f.array("b", "bounds", "<f4", 2 * dim)
    corners = bounds.tolist()  # Python floats: quicker than numpy for the few numbers of a box
    if any(low > high for low, high in zip(corners[:dim], corners[dim:])):
        raise ProtocolError(f.name("bounds"), "lower corner above upper corner")
    return dequantize(bounds, stream, count, dim, f.prefix, support)


# --- scan message


def _encode_scan(message: ScanMessage, encoding: str) -> dict:
    model = message.model
    if not (np.isfinite(model.max_range) and model.max_range > 0):
        raise ProtocolError("max_range", f"must be finite and > 0, got {model.max_range}")
    return {
        "e": encoding,
        "f": message.fleet,
        "r": message.robot,
        "n": message.node,
        "s": message.stamp + 0.0,  # + 0.0: a negative zero is sent as 0.0
        "d": message.dim,
        "p": pose_bytes([message.pose], "<f4", "pose"),
        "o": float32_bytes(np.append(model.origin, model.max_range), "origin"),
        "O": _encode_mixture(model.occupied, encoding, "occupied"),
        "F": _encode_mixture(model.free, encoding, "free"),
    }


def _decode_scan(f: Fields, max_components: int) -> ScanMessage:
    encoding = f.get("e", "encoding")
    if encoding not in ENCODINGS:
        raise ProtocolError("encoding", f"unknown encoding {encoding!r:.80}, expected one of {ENCODINGS}")
    fleet, robot = check_id(f.get("f", "fleet"), "fleet"), check_id(f.get("r", "robot"), "robot")
    node, stamp = f.int("n", "node"), f.float("s", "stamp")
    dim = f.int("d", "dimension", 2, 3)
    pose = pose_from_vector(f.array("p", "pose", "<f4", pose_width(dim)), "pose")
    sensor = f.array("o", "origin", "<f4", dim + 1)  # origin, then max_range
    origin, max_range = sensor[:dim], float(sensor[dim])
    if max_range <= 0:
        raise ProtocolError("max_range", f"must be > 0, got {max_range}")
    parts = [Fields(f.get(key, name), name) for key, name in (("O", "occupied"), ("F", "free"))]
    streams = [part.array("c", "components", "u1") for part in parts]
    counts = [_component_count(stream, dim, encoding, part.name("components")) for part, stream in zip(parts, streams)]
    if sum(counts) > max_components:
        raise ProtocolError("components", f"{sum(counts)} components exceed the maximum of {max_components}")
    occupied, free = (
        _decode_mixture(part, stream, count, dim, encoding) for part, stream, count in zip(parts, streams, counts)
    )
    return ScanMessage(fleet, robot, node, stamp, ScanModel(occupied, free, origin, max_range), pose)


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


# An encoder takes the message class that TYPE_CODES gives its code.
_ENCODERS: dict[int, Callable[[Any, str], dict]] = {
    1: _encode_scan,
    2: _encode_poses,
    3: _encode_ack,
    4: _encode_map_query,
    5: _encode_map_reply,
    6: _encode_rejection,
    7: _encode_inventory,
    8: _encode_point_query,
    9: _encode_point_reply,
}
_DECODERS: dict[int, Callable[[Fields, int], Message]] = {
    1: _decode_scan,
    2: _decode_poses,
    3: _decode_ack,
    4: _decode_map_query,
    5: _decode_map_reply,
    6: _decode_rejection,
    7: _decode_inventory,
    8: _decode_point_query,
    9: _decode_point_reply,
}
_DECODERS_V2 = _DECODERS | {2: _decode_poses_v2}
