"""The plain numpy reading and writing of encoding "q" (protocol/quantize.py before its numba
kernels): the reference that tests/unit/protocol/test_quantize_kernels.py holds them to, bit
for bit."""

from __future__ import annotations

import numpy as np

from gmm_core.mixture import Mixture
from protocol.errors import ProtocolError
from protocol.quantize import (
    ANGLE_STEPS,
    LOG_STD_MIN,
    LOG_STD_STEP,
    MEAN_BITS,
    QUARTER_TURN,
    QUAT_HALF_RANGE,
    QUAT_MAX,
    WEIGHT_STEPS_PER_OCTAVE,
    record_fields,
)

# --- bit packing: K records of fixed-width unsigned fields, LSB-first, one continuous stream


def pack_records(columns: list[np.ndarray], widths: list[int]) -> bytes:
    bits = [
        (col.astype(np.uint64)[:, None] >> np.arange(w, dtype=np.uint64)) & np.uint64(1)
        for col, w in zip(columns, widths)
    ]
    return np.packbits(np.concatenate(bits, axis=1).astype(np.uint8).reshape(-1), bitorder="little").tobytes()


def unpack_records(data: bytes, n_records: int, widths: list[int], field: str) -> list[np.ndarray]:
    total = sum(widths)
    expected = (n_records * total + 7) // 8
    if len(data) != expected:
        raise ProtocolError(field, f"expected {expected} bytes for {n_records} components, got {len(data)}")
    bits = np.unpackbits(np.frombuffer(data, dtype=np.uint8), bitorder="little")
    if bits[n_records * total :].any():  # the pad up to a whole byte is zero, so a stream is canonical
        raise ProtocolError(field, "padding bits after the last component must be zero")
    records = bits[: n_records * total].reshape(n_records, total).astype(np.int64)
    offsets = np.cumsum([0] + list(widths))
    return [
        records[:, lo : lo + w] @ (np.int64(1) << np.arange(w, dtype=np.int64)) for lo, w in zip(offsets[:-1], widths)
    ]


# --- the decoding


def dequantize(bounds: np.ndarray, stream: bytes, n_components: int, dim: int, field: str) -> Mixture:
    """(bounds, stream) -> Mixture with `support` 0 (the caller sets it); raises ProtocolError."""
    columns = unpack_records(stream, n_components, [bits for _, bits in record_fields(dim)], f"{field}.components")
    if n_components == 0:
        return Mixture.empty(dim)
    lo, hi = bounds[:dim].astype(np.float64), bounds[dim:].astype(np.float64)
    mean_codes = np.stack(columns[:dim], axis=1)
    means = lo + mean_codes * ((hi - lo) / (2 ** MEAN_BITS[dim] - 1))
    log_std = LOG_STD_MIN + np.stack(columns[dim : 2 * dim], axis=1) * LOG_STD_STEP
    if dim == 2:
        theta = columns[2 * dim] * (QUARTER_TURN / ANGLE_STEPS)
        c, s = np.cos(theta), np.sin(theta)
        rotations = np.stack([np.stack([c, -s], axis=1), np.stack([s, c], axis=1)], axis=1)
    else:
        rotations = _dequantize_rotation(columns[2 * dim], np.stack(columns[2 * dim + 1 : 2 * dim + 4], axis=1))
    variances = np.exp(2 * log_std)
    covs = np.einsum("kij,kj,klj->kil", rotations, variances, rotations)
    covs = 0.5 * (covs + np.swapaxes(covs, 1, 2))
    weights = np.exp2(columns[-1] / WEIGHT_STEPS_PER_OCTAVE)
    return Mixture(weights / weights.sum(), means, covs, 0)


def _dequantize_rotation(largest: np.ndarray, codes: np.ndarray) -> np.ndarray:
    rest = codes * (2 * QUAT_HALF_RANGE / QUAT_MAX) - QUAT_HALF_RANGE
    # Corrupt codes can make the three exceed a unit vector; clamping keeps R a rotation.
    big = np.sqrt(np.maximum(0.0, 1.0 - np.sum(rest**2, axis=1)))
    q = np.empty((len(largest), 4))
    keep = np.array([[j for j in range(4) if j != i] for i in range(4)])[largest]
    np.put_along_axis(q, keep, rest, axis=1)
    q[np.arange(len(q)), largest] = big
    return _matrix_from_quaternion(q / np.linalg.norm(q, axis=1, keepdims=True))


def _matrix_from_quaternion(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1),
        ],
        axis=1,
    )
