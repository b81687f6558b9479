"""Encoding "q": a mixture as fixed-width integers, bit-packed (docs/PROTOCOL.md, "q").

Per component: the mean relative to the mixture's bounding box, the log standard deviations
along the principal axes, the orientation of those axes (2D: one angle; 3D: a quaternion as
its smallest three components) and the weight on a log scale. A covariance is rebuilt as
R diag(exp(2 s)) R^T, so every decoded covariance is symmetric positive definite whatever
the bits say.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from gmm_core.mixture import Mixture
from protocol.bitstream import READ, as_stream, check_status, pack_records, read_codes

MEAN_BITS = {2: 13, 3: 14}  # per axis, over the mixture's box of means
LOG_STD_BITS = 9
LOG_STD_MIN = math.log(1e-4)  # std 0.1 mm; smaller standard deviations are clamped up
LOG_STD_MAX = math.log(1e2)  # std 100 m; larger ones are clamped down
LOG_STD_STEP = (LOG_STD_MAX - LOG_STD_MIN) / (2**LOG_STD_BITS - 1)  # 2.7 % per step
VARIANCE_FLOOR = 1e-8  # eigenvalues are raised to it before the log: any value at or below (1e-4)^2 codes as 0
ANGLE_BITS = 7  # 2D: angle of the first principal axis in [0, pi/2), 0.70 deg per step
QUARTER_TURN = 0.5 * math.pi
QUAT_BITS = 9  # 3D: each of the smallest three quaternion components in [-1/sqrt2, 1/sqrt2]
QUAT_HALF_RANGE = 1 / math.sqrt(2)
WEIGHT_BITS = 7
WEIGHT_STEPS_PER_OCTAVE = 8  # weight proportional to 2^(q/8): 9 % per step, 16 octaves of range

ANGLE_STEPS = 2**ANGLE_BITS  # angles are k * (pi/2) / ANGLE_STEPS, k < ANGLE_STEPS
QUAT_MAX = 2**QUAT_BITS - 1
WEIGHT_MAX = 2**WEIGHT_BITS - 1
LOG_STD_CODE_MAX = 2**LOG_STD_BITS - 1


def record_fields(dim: int) -> tuple[tuple[str, int], ...]:
    """(name, bits) of one component's record, in stream order (least significant first)."""
    means = tuple((f"mean{axis}", MEAN_BITS[dim]) for axis in range(dim))
    stds = tuple((f"log_std{axis}", LOG_STD_BITS) for axis in range(dim))
    rotation: tuple[tuple[str, int], ...]
    if dim == 2:
        rotation = (("angle", ANGLE_BITS),)
    else:
        rotation = (("quat_index", 2),) + tuple((f"quat{i}", QUAT_BITS) for i in range(3))
    return means + stds + rotation + (("weight", WEIGHT_BITS),)


FIELD_WIDTHS = {dim: np.array([bits for _, bits in record_fields(dim)], dtype=np.int64) for dim in (2, 3)}


RECORD_BITS = {dim: int(widths.sum()) for dim, widths in FIELD_WIDTHS.items()}


def record_bits(dim: int) -> int:
    return RECORD_BITS[dim]


def stream_bytes(n_components: int, dim: int) -> int:
    return (n_components * record_bits(dim) + 7) // 8


# What each code decodes to, by the numpy expressions of the reference decoder
# (tests/support/quantize_reference.py), so that the kernel's look-ups give numpy's exp, cos and sin.
VARIANCE_OF_CODE = np.exp(2 * (LOG_STD_MIN + np.arange(LOG_STD_CODE_MAX + 1) * LOG_STD_STEP))
_ANGLE_OF_CODE = np.arange(ANGLE_STEPS) * (QUARTER_TURN / ANGLE_STEPS)
COS_OF_CODE, SIN_OF_CODE = np.cos(_ANGLE_OF_CODE), np.sin(_ANGLE_OF_CODE)
QUAT_OF_CODE = np.arange(QUAT_MAX + 1) * (2 * QUAT_HALF_RANGE / QUAT_MAX) - QUAT_HALF_RANGE
WEIGHT_OF_CODE = np.exp2(np.arange(WEIGHT_MAX + 1) / WEIGHT_STEPS_PER_OCTAVE)

# --- rotations, vectorised over components


def quaternion_from_matrix(R: np.ndarray) -> np.ndarray:
    """(K, 3, 3) rotations -> (K, 4) unit quaternions (w, x, y, z), branch on the largest
    diagonal term so no component is found by dividing by a tiny number (Shepperd)."""
    m = R
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    candidates = np.stack(
        [
            np.stack([1 + trace, m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]], axis=1),
            np.stack(
                [
                    m[:, 2, 1] - m[:, 1, 2],
                    1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
                    m[:, 0, 1] + m[:, 1, 0],
                    m[:, 0, 2] + m[:, 2, 0],
                ],
                axis=1,
            ),
            np.stack(
                [
                    m[:, 0, 2] - m[:, 2, 0],
                    m[:, 0, 1] + m[:, 1, 0],
                    1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2],
                    m[:, 1, 2] + m[:, 2, 1],
                ],
                axis=1,
            ),
            np.stack(
                [
                    m[:, 1, 0] - m[:, 0, 1],
                    m[:, 0, 2] + m[:, 2, 0],
                    m[:, 1, 2] + m[:, 2, 1],
                    1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2],
                ],
                axis=1,
            ),
        ],
        axis=1,
    )  # (K, 4 branches, 4): branch b is 4 q_b * q, whose entry b is 4 q_b^2
    diag = np.stack(
        [
            1 + trace,
            1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
            1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2],
            1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2],
        ],
        axis=1,
    )
    return _unit(candidates[np.arange(len(R)), np.argmax(diag, axis=1)])


# --- the encoding


def quantize(mixture: Mixture) -> tuple[np.ndarray, bytes]:
    """Mixture -> (bounds, stream): bounds is float32 [lo_0..lo_d-1, hi_0..hi_d-1] of the means.

    Means must fit float32, covariances be symmetric positive definite and weights be
    non-negative with a positive sum (the codec checks before calling). The stream is canonical:
    where several records would decode alike (the sign of an axis, the frame of equal axes) the
    encoder picks the one docs/PROTOCOL.md names.
    """
    d, k = mixture.dim, mixture.n_components
    if k == 0:
        return np.zeros(2 * d, dtype=np.float32), b""
    lo = mixture.means.min(axis=0).astype(np.float32)
    hi = mixture.means.max(axis=0).astype(np.float32)
    mean_codes = _quantize_means(mixture.means, lo, hi, MEAN_BITS[d])

    covs = 0.5 * (mixture.covariances + np.swapaxes(mixture.covariances, 1, 2))
    eigenvalues, axes = np.linalg.eigh(covs)  # ascending; columns of `axes` are the principal axes
    # eigh can return a tiny negative eigenvalue for a thin component that Cholesky accepts
    log_std = 0.5 * np.log(np.maximum(eigenvalues, VARIANCE_FLOOR))
    std_codes = _round_clamp((log_std - LOG_STD_MIN) / LOG_STD_STEP, LOG_STD_CODE_MAX)  # ascending too
    if d == 2:
        rotation_codes, swap = _quantize_angle(axes, std_codes[:, 0] == std_codes[:, 1])
        std_codes = np.where(swap[:, None], std_codes[:, ::-1], std_codes)
    else:
        rotation_codes = _quantize_quaternion(_principal_quaternion(axes, std_codes))

    with np.errstate(divide="ignore"):  # a zero weight goes to the smallest code
        octaves = np.log2(mixture.weights / mixture.weights.max())
    weight_codes = np.clip(WEIGHT_MAX + np.rint(octaves * WEIGHT_STEPS_PER_OCTAVE), 0, WEIGHT_MAX)

    codes = np.column_stack([mean_codes, std_codes, *rotation_codes, weight_codes])
    return np.concatenate([lo, hi]), pack_records(codes, FIELD_WIDTHS[d])


def dequantize(
    bounds: np.ndarray, stream: bytes | np.ndarray, n_components: int, dim: int, field: str, support: int = 0
) -> Mixture:
    """(float32 bounds, stream) -> Mixture; raises ProtocolError. `stream` is bytes or a uint8 array."""
    stream = as_stream(stream)
    widths = FIELD_WIDTHS[dim]
    means, covs, weights, status = _decode(stream, n_components, widths, bounds, dim, 2 ** MEAN_BITS[dim] - 1)
    check_status(status, stream, n_components, widths, f"{field}.components")
    if n_components:
        weights /= weights.sum()  # numpy's pairwise sum, as the reference's
    return Mixture(weights, means, covs, support)


@njit(cache=True)
def _decode(stream, n_components, widths, bounds, dim, mean_top):
    codes, status = read_codes(stream, n_components, widths)
    means, covs, weights = _dequantize_codes(codes[: n_components if status == READ else 0], bounds, dim, mean_top)
    return means, covs, weights, status


@njit(cache=True)
def _dequantize_codes(codes, bounds, dim, mean_top):
    """(K, fields) codes, float32 [lo, hi] -> means, covariances R diag(v) R^T and weights not yet
    normalised; each in the reference's order of operations (einsum: a sum over j from 0.0 of
    (R_ij v_j) R_lj), so the bits agree."""
    n = codes.shape[0]
    means, covs, weights = np.empty((n, dim)), np.empty((n, dim, dim)), np.empty(n)
    lo = bounds[:dim].astype(np.float64)
    step = (bounds[dim:].astype(np.float64) - lo) / mean_top
    rotation, full = np.empty((dim, dim)), np.empty((dim, dim))
    for k in range(n):
        for axis in range(dim):
            means[k, axis] = lo[axis] + codes[k, axis] * step[axis]
        if dim == 2:
            _rotation_2d(codes[k, 4], rotation)
        else:
            _rotation_3d(codes[k, 6], codes[k, 7:10], rotation)
        for i in range(dim):
            for m in range(dim):
                total = 0.0
                for j in range(dim):
                    total += (rotation[i, j] * VARIANCE_OF_CODE[codes[k, dim + j]]) * rotation[m, j]
                full[i, m] = total
        for i in range(dim):
            for m in range(dim):
                covs[k, i, m] = 0.5 * (full[i, m] + full[m, i])
        weights[k] = WEIGHT_OF_CODE[codes[k, -1]]
    return means, covs, weights


@njit(cache=True)
def _rotation_2d(code, out):
    c, s = COS_OF_CODE[code], SIN_OF_CODE[code]
    out[0, 0], out[0, 1], out[1, 0], out[1, 1] = c, -s, s, c


@njit(cache=True)
def _rotation_3d(largest, codes, out):
    """The quaternion's three smaller components in index order, the largest one (dropped) from
    the unit norm: clamped at 0, as corrupt codes can make the three exceed a unit vector."""
    q = np.empty(4)
    squares = 0.0
    slot = 0
    for j in range(4):
        if j != largest:
            q[j] = QUAT_OF_CODE[codes[slot]]
            squares += q[j] * q[j]
            slot += 1
    q[largest] = np.sqrt(max(0.0, 1.0 - squares))
    norm = np.sqrt(((q[0] * q[0] + q[1] * q[1]) + q[2] * q[2]) + q[3] * q[3])
    w, x, y, z = q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm
    out[0, 0], out[0, 1], out[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    out[1, 0], out[1, 1], out[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    out[2, 0], out[2, 1], out[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)


def _round_clamp(values: np.ndarray, top: int) -> np.ndarray:
    """Round half to even (IEEE 754 roundTiesToEven, C rint), then clamp to [0, top]."""
    return np.clip(np.rint(values), 0, top)


def _quantize_means(means: np.ndarray, lo: np.ndarray, hi: np.ndarray, bits: int) -> np.ndarray:
    top = 2**bits - 1
    span = hi.astype(np.float64) - lo.astype(np.float64)
    scale = np.divide(top, span, out=np.zeros_like(span), where=span > 0)  # a flat axis codes as 0
    return _round_clamp((means - lo) * scale, top)


def _quantize_angle(axes: np.ndarray, isotropic: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """2D: the first axis' angle folded into [0, pi/2), and whether the stds swap: turning the frame
    by pi/2 swaps the two axes, so a fold by an odd number of quarter turns swaps them. The sign
    of an axis turns it by pi, an even fold, so eigh's signs do not matter. Equal std codes decode
    to a circle whatever the angle: those components send angle 0, unswapped."""
    theta = np.arctan2(axes[:, 1, 0], axes[:, 0, 0])
    quarter_turns = np.floor(theta / QUARTER_TURN)
    code = np.rint((theta - quarter_turns * QUARTER_TURN) / QUARTER_TURN * ANGLE_STEPS)
    swap = (quarter_turns.astype(np.int64) % 2 == 1) ^ (code == ANGLE_STEPS)  # pi/2 wraps to 0
    return [np.where(isotropic, 0, code % ANGLE_STEPS)], swap & ~isotropic


def _lead_sign(vectors: np.ndarray) -> np.ndarray:
    """(K, 3) -> (K,) +1 or -1: the sign of each vector's largest-magnitude entry (the first of equal ones)."""
    lead = np.take_along_axis(vectors, np.argmax(np.abs(vectors), axis=1)[:, None], axis=1)[:, 0]
    return np.where(lead < 0, -1.0, 1.0)


def _unit(q: np.ndarray) -> np.ndarray:
    """Quaternions over their norm, summed in a stated order so that other encoders match bit for bit."""
    w, x, y, z = q.T
    return q / np.sqrt(((w * w + x * x) + y * y) + z * z)[:, None]


def _principal_quaternion(axes: np.ndarray, std_codes: np.ndarray) -> np.ndarray:
    """3D: (K, 3, 3) eigh axes, (K, 3) ascending std codes -> (K, 4) quaternions of one frame each.

    eigh's signs are arbitrary: axes 0 and 1 get their largest-magnitude entry positive and axis 2
    completes a right-handed frame. Axes with equal std codes decode alike in any frame within
    their plane: then only the other axis u counts (its largest entry made positive) and the frame
    is the smallest rotation taking the coordinate axis onto u; with three equal codes, identity.
    """
    axes = axes.copy()
    for column in (0, 1):
        axes[:, :, column] *= _lead_sign(axes[:, :, column])[:, None]
    axes[np.linalg.det(axes) < 0, :, 2] *= -1
    q = quaternion_from_matrix(axes)
    low_pair, high_pair = std_codes[:, 0] == std_codes[:, 1], std_codes[:, 1] == std_codes[:, 2]
    u = axes[:, :, 2] * _lead_sign(axes[:, :, 2])[:, None]  # low pair: z -> u, q = (1 + u.z, z x u)
    z_arc = np.stack([1 + u[:, 2], -u[:, 1], u[:, 0], np.zeros(len(u))], axis=1)
    v = axes[:, :, 0]  # high pair: x -> v, q = (1 + v.x, x x v); v's lead is positive already
    x_arc = np.stack([1 + v[:, 0], np.zeros(len(v)), -v[:, 2], v[:, 1]], axis=1)
    q = np.where(low_pair[:, None], _unit(z_arc), np.where(high_pair[:, None], _unit(x_arc), q))
    return np.where((low_pair & high_pair)[:, None], np.array([1.0, 0.0, 0.0, 0.0]), q)


def _quantize_quaternion(q: np.ndarray) -> list[np.ndarray]:
    """3D: quaternion -> index of its largest-magnitude component (the first of equal ones; dropped,
    made positive since q and -q are one rotation) and codes of the other three in index order."""
    largest = np.argmax(np.abs(q), axis=1)
    q = q * np.sign(q[np.arange(len(q)), largest])[:, None]
    keep = np.array([[j for j in range(4) if j != i] for i in range(4)])[largest]
    rest = np.take_along_axis(q, keep, axis=1)
    return [largest] + list(_round_clamp((rest + QUAT_HALF_RANGE) / (2 * QUAT_HALF_RANGE) * QUAT_MAX, QUAT_MAX).T)
