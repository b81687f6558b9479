"""protocol/scan_codec.py: scans round trip in both encodings within the stated bounds of the
quantisation, their sizes, and each rule of a scan's validation, at decode and at encode, naming
its field."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gmm_core.mixture import Mixture
from gmm_core.pose import Pose
from gmm_core.scan import ScanModel
from protocol import PointQuery, ProtocolError, ScanMessage, decode, encode
from protocol import quantize as qz
from support.fuzz import random_rotations, scan_like_mixture, scan_message
from support.wire_maps import pack, set_path, wire, without

pytestmark = pytest.mark.filterwarnings("error")  # a numpy warning means a value slipped through

HYPOTHESIS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# --- generators: mixtures with the awkward cases a scan fit produces


@st.composite
def mixtures(draw, dim: int, max_components: int = 40, stds=(1e-4, 1e2)) -> Mixture:
    """Random mixtures: sizes of boxes from cm to 100 m, stds across `stds` (default: the whole
    coded range), exactly isotropic and axis-aligned components, a single one, repeated means."""
    count = draw(st.integers(0, max_components))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    extent = draw(st.sampled_from([0.01, 1.0, 20.0, 100.0]))
    means = rng.uniform(-extent, extent, size=(count, dim)) + rng.uniform(-50, 50, size=dim)
    if count > 1 and draw(st.booleans()):
        means[1] = means[0]
    log_std = rng.uniform(math.log(stds[0]), math.log(stds[1]), size=(count, dim))
    rotations = random_rotations(rng, count, dim)
    special = draw(st.sampled_from(["none", "isotropic", "axis-aligned"]))
    if special == "isotropic":
        log_std[:] = log_std[:, :1]
    elif special == "axis-aligned":
        rotations[:] = np.eye(dim)
    covs = np.einsum("kij,kj,klj->kil", rotations, np.exp(2 * log_std), rotations)
    covs = 0.5 * (covs + np.swapaxes(covs, 1, 2))  # exactly symmetric, as float32 tables will be
    weights = rng.dirichlet(np.full(count, draw(st.sampled_from([0.2, 1.0, 10.0])))) if count else np.zeros(0)
    return Mixture(weights, means, covs, draw(st.integers(0, 10**6)))


def scan_of(occupied: Mixture, free: Mixture, node: int = 5) -> ScanMessage:
    d = occupied.dim
    pose = Pose.from_xytheta(1.0, -2.0, 0.7) if d == 2 else Pose.from_quaternion([1, 2, 3], [0.9, -0.1, 0.3, 0.2])
    return ScanMessage("fleet-a", "robot_1", node, 1.7e9 + 0.25, ScanModel(occupied, free, np.full(d, 0.1), 30.0), pose)


def principal_axes(covs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """log stds (ascending) and axes (columns) of each covariance."""
    eigenvalues, axes = np.linalg.eigh(covs)
    return 0.5 * np.log(eigenvalues), axes


def axis_angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.abs(np.sum(a * b, axis=-1)), 0, 1)))


# --- round trips


@pytest.mark.parametrize("dim", [2, 3])
@HYPOTHESIS
@given(data=st.data())
def test_f32_round_trip_is_exact_to_float32(dim, data):
    # float32 tables lose positive definiteness beyond a variance ratio of about 1e6 (see
    # test_encode_refuses_what_decode_would_reject), so stay within what scans produce
    occupied, free = data.draw(mixtures(dim, stds=(1e-3, 1.0))), data.draw(mixtures(dim, 5, stds=(1e-3, 1.0)))
    message = scan_of(occupied, free)
    back = decode(encode(message, "f32"))
    assert (back.fleet, back.robot, back.node, back.stamp) == (
        message.fleet,
        message.robot,
        message.node,
        message.stamp,
    )
    for sent, got in ((occupied, back.model.occupied), (free, back.model.free)):
        assert got.support == sent.support
        np.testing.assert_array_equal(got.means, sent.means.astype(np.float32))
        np.testing.assert_array_equal(got.weights, sent.weights.astype(np.float32))
        np.testing.assert_array_equal(got.covariances, sent.covariances.astype(np.float32))
    np.testing.assert_array_equal(back.model.origin, message.model.origin.astype(np.float32))
    assert back.model.max_range == np.float32(30.0)
    np.testing.assert_allclose(back.pose.R, message.pose.R, atol=1e-6)
    np.testing.assert_allclose(back.pose.t, message.pose.t, rtol=1e-6)


@pytest.mark.parametrize("dim", [2, 3])
@HYPOTHESIS
@given(data=st.data())
def test_q_round_trip_within_stated_tolerances(dim, data):
    sent = data.draw(mixtures(dim))
    got = decode(encode(scan_of(sent, Mixture.empty(dim)), "q")).model.occupied
    assert got.n_components == sent.n_components and got.support == sent.support
    if sent.n_components == 0:
        return
    # means: half a step of the box, plus float32 rounding of the box corners
    span = np.ptp(sent.means, axis=0)
    tolerance = span / (2 * (2 ** qz.MEAN_BITS[dim] - 1)) + 1e-6 * (1 + np.abs(sent.means).max())
    assert (np.abs(got.means - sent.means) <= tolerance).all()
    # covariances are symmetric positive definite by construction
    np.testing.assert_array_equal(got.covariances, np.swapaxes(got.covariances, 1, 2))
    np.linalg.cholesky(got.covariances)
    # standard deviations: half a log step (rounding is monotone, so sorted stds pair up), plus
    # what an eigen-decomposition can resolve: an error of ~eps * lambda_max on every eigenvalue
    sent_log_std, sent_axes = principal_axes(sent.covariances)
    got_log_std, got_axes = principal_axes(got.covariances)
    resolution = 1e-14 * np.exp(2 * (sent_log_std[:, -1:] - sent_log_std))
    assert (np.abs(got_log_std - sent_log_std) <= qz.LOG_STD_STEP / 2 + 1e-9 + resolution).all()
    # orientation: compare the axes whose stds stand apart from the others by > 10 %
    angle_limit = 0.36 if dim == 2 else 0.6  # 2D: half of 90/128 deg; 3D: smallest-three bound
    for axis, neighbour in ((-1, -2), (0, 1)):
        apart = np.abs(sent_log_std[:, axis] - sent_log_std[:, neighbour]) > math.log(1.1)
        angles = axis_angle_deg(sent_axes[apart, :, axis], got_axes[apart, :, axis])
        assert (angles <= angle_limit).all(), angles.max()
    # weights: ratios to the largest within a sixteenth of an octave, down to the floor of the scale
    ratio_sent, ratio_got = sent.weights / sent.weights.max(), got.weights / got.weights.max()
    floor = 2.0 ** (-qz.WEIGHT_MAX / qz.WEIGHT_STEPS_PER_OCTAVE)
    coded = ratio_sent >= floor
    assert np.all(np.abs(np.log2(ratio_got[coded] / ratio_sent[coded])) <= 1 / 16 + 1e-9)
    assert np.all(ratio_got[~coded] == pytest.approx(floor))
    assert got.weights.sum() == pytest.approx(1.0)


def test_q_decodes_any_bits_to_positive_definite_covariances():
    rng = np.random.default_rng(3)
    for dim in (2, 3):
        count = 500
        stream = rng.bytes(qz.stream_bytes(count, dim))
        pad = count * qz.record_bits(dim) % 8
        if pad:  # zero the padding bits, as the format requires
            stream = stream[:-1] + bytes([stream[-1] & ((1 << pad) - 1)])
        bounds = np.array([-5.0] * dim + [5.0] * dim, dtype=np.float32)
        mixture = qz.dequantize(bounds, stream, count, dim, "occupied")
        np.linalg.cholesky(mixture.covariances)
        assert np.isfinite(mixture.means).all() and (mixture.weights > 0).all()


def test_q_keeps_the_2d_fold_of_axes_consistent():
    # angles just below pi/2 wrap to 0 with the stds swapped: the covariance stays the same
    theta = np.array([0.0, np.pi / 2 - 1e-4, np.pi / 2, np.pi - 1e-4, -np.pi / 4, 3.0])
    c, s = np.cos(theta), np.sin(theta)
    rotations = np.stack([np.stack([c, -s], 1), np.stack([s, c], 1)], 1)
    covs = np.einsum("kij,j,klj->kil", rotations, np.array([4.0, 0.01]), rotations)
    sent = Mixture(np.full(len(theta), 1 / len(theta)), np.zeros((len(theta), 2)), covs, 10)
    got = decode(encode(scan_of(sent, Mixture.empty(2)))).model.occupied
    np.testing.assert_allclose(got.covariances, covs, atol=0.04 * 4.0)


# --- sizes: the targets of the issue, every byte of the message counted


@pytest.mark.parametrize("dim, occupied, free, limit", [(2, 56, 4, 10.0), (3, 192, 8, 16.0), (3, 96, 4, 16.0)])
def test_q_bytes_per_component_meet_target(dim, occupied, free, limit):
    message = scan_message(np.random.default_rng(dim), dim, occupied, free, node=123456)
    per_component = len(encode(message, "q")) / (occupied + free)
    assert per_component <= limit
    assert len(encode(message, "f32")) / (occupied + free) > 2.5 * per_component


# --- validation: each rule raises ProtocolError naming its field


def scan_wire(dim=2, encoding="q") -> dict:
    return wire(scan_message(np.random.default_rng(11), dim, 10, 2), encoding)


def f32_table(raw: dict, dim: int = 2) -> np.ndarray:
    return np.frombuffer(raw["O"]["c"], "<f4").reshape(-1, dim + dim * (dim + 1) // 2 + 1).copy()


def with_table(raw: dict, edit) -> dict:
    table = f32_table(raw)
    edit(table)
    raw["O"]["c"] = table.astype("<f4").tobytes()
    return raw


def drop_last_byte(raw: dict) -> dict:
    raw["O"]["c"] = raw["O"]["c"][:-1]
    return raw


def set_padding_bit(raw: dict) -> dict:
    stream = bytearray(raw["O"]["c"])
    stream[-1] |= 0x80  # 10 records of 58 bits leave 4 bits of padding in the last byte
    raw["O"]["c"] = bytes(stream)
    return raw


INVALID_SCANS = [
    # (name, encoding, edit of the wire map, field named in the error)
    ("version", "q", lambda r: set_path(r, ("v",), 4), "version"),
    ("version type", "q", lambda r: set_path(r, ("v",), "1"), "version"),
    ("message type", "q", lambda r: set_path(r, ("t",), 42), "type"),
    ("encoding", "q", lambda r: set_path(r, ("e",), "f16"), "encoding"),
    ("fleet id", "q", lambda r: set_path(r, ("f",), "bad fleet"), "fleet"),
    ("robot id long", "q", lambda r: set_path(r, ("r",), "r" * 65), "robot"),
    ("robot id empty", "q", lambda r: set_path(r, ("r",), ""), "robot"),
    ("robot id type", "q", lambda r: set_path(r, ("r",), 5), "robot"),
    ("node negative", "q", lambda r: set_path(r, ("n",), -1), "node"),
    ("node type", "q", lambda r: set_path(r, ("n",), "12"), "node"),
    ("node bool", "q", lambda r: set_path(r, ("n",), True), "node"),
    ("stamp nan", "q", lambda r: set_path(r, ("s",), math.nan), "stamp"),
    ("stamp missing", "q", lambda r: without(r, "s"), "stamp"),
    ("dimension", "q", lambda r: set_path(r, ("d",), 4), "dimension"),
    ("pose length", "q", lambda r: set_path(r, ("p",), r["p"][:-4]), "pose"),
    ("pose type", "q", lambda r: set_path(r, ("p",), [1.0, 2.0, 3.0]), "pose"),
    ("pose inf", "q", lambda r: set_path(r, ("p",), np.array([np.inf, 0, 0], "<f4").tobytes()), "pose"),
    ("origin nan", "q", lambda r: set_path(r, ("o",), np.array([np.nan, 0, 30], "<f4").tobytes()), "origin"),
    ("max range", "q", lambda r: set_path(r, ("o",), np.array([0, 0, -1], "<f4").tobytes()), "max_range"),
    ("mixture type", "q", lambda r: set_path(r, ("O",), [1, 2]), "occupied"),
    ("support", "q", lambda r: set_path(r, ("F", "N"), -3), "free.support"),
    ("q stream length", "q", drop_last_byte, "occupied.components"),
    ("q padding", "q", set_padding_bit, "occupied.components"),
    ("q stream type", "q", lambda r: set_path(r, ("O", "c"), "text"), "occupied.components"),
    ("q bounds length", "q", lambda r: set_path(r, ("O", "b"), r["O"]["b"][:8]), "occupied.bounds"),
    ("q bounds missing", "q", lambda r: without(r, "O", "b"), "occupied.bounds"),
    (
        "q bounds nan",
        "q",
        lambda r: set_path(r, ("O", "b"), np.array([np.nan, 0, 1, 1], "<f4").tobytes()),
        "occupied.bounds",
    ),
    (
        "q bounds order",
        "q",
        lambda r: set_path(r, ("O", "b"), np.array([2, 0, 1, 1], "<f4").tobytes()),
        "occupied.bounds",
    ),
    ("f32 length", "f32", lambda r: set_path(r, ("O", "c"), r["O"]["c"][:-4]), "occupied.components"),
    ("f32 nan", "f32", lambda r: with_table(r, lambda t: t.__setitem__((0, 0), np.nan)), "occupied.components"),
    ("f32 inf", "f32", lambda r: with_table(r, lambda t: t.__setitem__((1, 3), np.inf)), "occupied.components"),
    (
        "f32 not PD",
        "f32",
        lambda r: with_table(r, lambda t: t.__setitem__((2, slice(2, 5)), [1, 2, 1])),
        "occupied.covariances",
    ),
    (
        "f32 zero cov",
        "f32",
        lambda r: with_table(r, lambda t: t.__setitem__((2, slice(2, 5)), 0)),
        "occupied.covariances",
    ),
    (
        "f32 negative weight",
        "f32",
        lambda r: with_table(r, lambda t: t.__setitem__((0, 5), -t[0, 5])),
        "occupied.weights",
    ),
    (
        "f32 weights sum",
        "f32",
        lambda r: with_table(r, lambda t: t.__setitem__((slice(None), 5), t[:, 5] * 1.01)),
        "occupied.weights",
    ),
]


@pytest.mark.parametrize("name, encoding, edit, field", INVALID_SCANS, ids=[case[0] for case in INVALID_SCANS])
def test_invalid_scan_names_field(name, encoding, edit, field):
    with pytest.raises(ProtocolError) as caught:
        decode(pack(edit(scan_wire(encoding=encoding))))
    assert caught.value.field == field
    assert str(caught.value).startswith(f"{field}: ")


def test_3d_pose_quaternion_must_be_unit():
    raw = scan_wire(dim=3)
    raw["p"] = np.array([0, 0, 0, 1.1, 0, 0, 0], "<f4").tobytes()
    with pytest.raises(ProtocolError, match="^pose: quaternion norm"):
        decode(pack(raw))


def test_encode_refuses_what_decode_would_reject():
    rng = np.random.default_rng(5)
    good = scan_like_mixture(rng, 2, 4)
    nan_means = Mixture(good.weights, np.where(np.eye(4, 2, dtype=bool), np.nan, good.means), good.covariances, 9)
    not_pd = Mixture(good.weights, good.means, np.tile([[1.0, 2.0], [2.0, 1.0]], (4, 1, 1)), 9)
    unnormalised = Mixture(good.weights * 2, good.means, good.covariances, 9)
    thin = Mixture([1.0], [[0, 0]], [[[1.0, 1.0 - 1e-12], [1.0 - 1e-12, 1.0]]], 3)  # PD in float64 only
    for mixture, field, encodings in (
        (nan_means, "occupied.means", "q f32"),
        (not_pd, "occupied.covariances", "q f32"),
        (unnormalised, "occupied.weights", "q f32"),
        (thin, "occupied.covariances", "f32"),
    ):
        for encoding in encodings.split():
            with pytest.raises(ProtocolError) as caught:
                encode(scan_of(mixture, Mixture.empty(2)), encoding)
            assert caught.value.field == field
    with pytest.raises(ProtocolError, match="^encoding:"):
        encode(scan_of(good, Mixture.empty(2)), "gzip")
    with pytest.raises(ProtocolError, match="^robot:"):
        ScanMessage("fleet", "robot 1", 0, 0.0, scan_of(good, Mixture.empty(2)).model, Pose.identity(2))
    with pytest.raises(ProtocolError, match="^pose:"):
        ScanMessage("fleet", "robot", 0, 0.0, scan_of(good, Mixture.empty(2)).model, Pose.identity(3))
    with pytest.raises(ProtocolError, match="^message: cannot encode"):
        encode("not a message")
    for points, field in (([[0.0, np.nan]], "points"), (np.zeros((0, 2)), "points"), (np.zeros((10_001, 3)), "points")):
        with pytest.raises(ProtocolError) as caught:
            PointQuery("f", points, 0.1)
        assert caught.value.field == field
    with pytest.raises(ProtocolError, match="^method:"):
        PointQuery("f", [[0.0, 0.0]], 0.1, None, "exact")
