"""A scan message's map (docs/PROTOCOL.md, "Scan message"): the pose, the sensor and two mixtures,
each as a float32 table ("f32") or as quantised records ("q", protocol.quantize), and what a
mixture must be to be sent or accepted either way. protocol.codec frames it.
"""

from __future__ import annotations

import numpy as np

from gmm_core.mixture import Mixture
from gmm_core.scan import ScanModel
from protocol.errors import ProtocolError
from protocol.keys import check_id
from protocol.messages import ScanMessage
from protocol.quantize import dequantize, quantize, record_bits, stream_bytes
from protocol.wire import Fields, float32_bytes, pose_bytes, pose_from_vector, pose_width

ENCODINGS = ("q", "f32")
WEIGHT_SUM_TOLERANCE = 1e-3
SYMMETRY_TOLERANCE = 1e-6  # relative to the component's largest covariance entry


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
