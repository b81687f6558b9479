"""The canonical form of docs/PROTOCOL.md: one byte string per message, whatever eigh's signs,
the frame of equal axes, the sign of a zero or of a quaternion; ties rounded half to even;
and the decoder rules the page states (limits in bytes, required keys, ext types)."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest

from gmm_core.mixture import Mixture
from gmm_core.pose import Pose
from gmm_core.scan import ScanModel
from protocol import Ack, MapQuery, PoseGraphUpdate, ProtocolError, Rejection, ScanMessage, decode, encode
from protocol import quantize as qz
from support.fuzz import random_rotations, scan_message
from support.golden import record_codes

pytestmark = pytest.mark.filterwarnings("error")


def scan_of(occupied: Mixture, pose: Pose | None = None, stamp: float = 5.0) -> ScanMessage:
    d = occupied.dim
    model = ScanModel(occupied, Mixture.empty(d), np.zeros(d), 30.0)
    return ScanMessage("f", "r", 1, stamp, model, pose or Pose.identity(d))


def codes(message: ScanMessage) -> list[dict]:
    return record_codes(msgpack.unpackb(encode(message), raw=False)["O"], message.dim)


def mixture(covs, means=None) -> Mixture:
    covs = np.asarray(covs, dtype=float)
    k, d = covs.shape[:2]
    means = np.zeros((k, d)) if means is None else means
    return Mixture(np.full(k, 1 / k), means, covs, 10)


def sandwich(rotations, variances) -> np.ndarray:
    covs = np.einsum("kij,kj,klj->kil", rotations, variances, rotations)
    return 0.5 * (covs + np.swapaxes(covs, 1, 2))


# --- principal axes: signs and equal axes


def test_3d_codes_ignore_the_signs_of_eigh_axes():
    rng = np.random.default_rng(1)
    axes = random_rotations(rng, 200, 3)
    std_codes = np.tile([100.0, 200.0, 300.0], (200, 1))
    want = qz._quantize_quaternion(qz._principal_quaternion(axes, std_codes))
    for signs in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3):
        got = qz._quantize_quaternion(qz._principal_quaternion(axes * signs, std_codes))
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)


def test_2d_codes_ignore_the_signs_of_eigh_axes():
    axes = random_rotations(np.random.default_rng(2), 200, 2)
    isotropic = np.zeros(200, dtype=bool)
    want_codes, want_swap = qz._quantize_angle(axes, isotropic)
    for signs in ([-1, 1], [1, -1], [-1, -1]):
        got_codes, got_swap = qz._quantize_angle(axes * signs, isotropic)
        np.testing.assert_array_equal(got_codes[0], want_codes[0])
        np.testing.assert_array_equal(got_swap, want_swap)


@pytest.mark.parametrize("variances, turned_axis", [([0.02, 0.02, 0.8], 2), ([0.02, 0.8, 0.8], 0)])
def test_3d_equal_axes_code_alike_in_any_frame_of_their_plane(variances, turned_axis):
    """A needle (two equal small axes) or a disc (two equal large ones) is one covariance however
    its equal axes turn about the other: the bytes do not depend on that turn."""
    rng = np.random.default_rng(3)
    base = random_rotations(rng, 50, 3)
    frames = []
    for phi in (0.0, 0.4, 1.3, 2.9):
        c, s = math.cos(phi), math.sin(phi)
        about = np.roll(np.roll(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), turned_axis - 2, 0), turned_axis - 2, 1)
        frames.append(encode(scan_of(mixture(sandwich(base @ about, np.tile(variances, (50, 1)))))))
    assert len(set(frames)) == 1
    decoded = decode(frames[0]).model.occupied.covariances
    want = sandwich(base, np.tile(variances, (50, 1)))
    assert np.abs(decoded - want).max() < 0.04 * max(variances)  # the one axis within ~1 deg, stds within 1.4 %


def test_spheres_and_circles_send_the_identity():
    rng = np.random.default_rng(4)
    sphere = codes(scan_of(mixture(sandwich(random_rotations(rng, 20, 3), np.full((20, 3), 0.09)))))
    assert {(c["quat_index"], c["quat0"], c["quat1"], c["quat2"]) for c in sphere} == {(0, 256, 256, 256)}
    circle = codes(scan_of(mixture(sandwich(random_rotations(rng, 20, 2), np.full((20, 2), 0.09)))))
    assert {c["angle"] for c in circle} == {0}


# --- ties: half to even


def test_mean_ties_round_half_to_even():
    # box [0, 8191]: the code of a coordinate is the coordinate itself
    means = np.array([[0.0, 0.0], [8191.0, 8191.0], [0.5, 1.5], [2.5, 3.5], [4095.5, 8190.5]])
    records = codes(scan_of(mixture(np.tile(np.diag([0.04, 0.01]), (5, 1, 1)), means)))
    assert [(c["mean0"], c["mean1"]) for c in records[2:]] == [(0, 2), (2, 4), (4096, 8190)]


def test_a_zero_quaternion_component_is_a_tie_coded_256():
    assert ((0.0 + qz.QUAT_HALF_RANGE) / (2 * qz.QUAT_HALF_RANGE)) * qz.QUAT_MAX == 255.5
    records = codes(scan_of(mixture([np.diag([0.0004, 0.09, 2.25])])))  # principal axes = coordinate axes
    assert (records[0]["quat_index"], records[0]["quat0"], records[0]["quat1"], records[0]["quat2"]) == (
        0,
        256,
        256,
        256,
    )


# --- zeros and the sign of a quaternion


def test_negative_zero_is_sent_as_zero():
    means = np.array([[-0.0, 1.0], [2.0, -0.0]])
    plus = scan_of(mixture(np.tile(np.eye(2) * 0.04, (2, 1, 1)), np.abs(means)), Pose.from_xytheta(0.0, 1.0, 0.0), 0.0)
    minus = scan_of(mixture(np.tile(np.eye(2) * 0.04, (2, 1, 1)), means), Pose.from_xytheta(-0.0, 1.0, -0.0), -0.0)
    for encoding in ("q", "f32"):
        assert encode(minus, encoding) == encode(plus, encoding)
    assert encode(MapQuery("f", [-0.0, 0.0], [1.0, 1.0], 0.5)) == encode(MapQuery("f", [0.0, 0.0], [1.0, 1.0], 0.5))


def raw_poses(update: PoseGraphUpdate) -> np.ndarray:
    raw = msgpack.unpackb(encode(update), raw=False)
    return np.frombuffer(raw["poses"], "<i4").reshape(len(update.poses), -1)


def test_a_half_turn_sends_the_first_non_zero_quaternion_component_positive():
    c, s = math.cos(-math.pi), math.sin(-math.pi)  # as_quaternion gives (0, -1, 0, 0) for this one
    minus_pi_about_x = Pose(np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]]), np.zeros(3))
    assert minus_pi_about_x.as_quaternion()[1] == -1.0
    about_y = Pose.from_quaternion(np.zeros(3), [0.0, 0.0, -1.0, 0.0])
    sent = raw_poses(PoseGraphUpdate("f", "r", 1, ((1, minus_pi_about_x), (2, about_y))))
    one = 2**31 - 1
    np.testing.assert_array_equal(sent[:, 3:], [[0, one, 0, 0], [0, 0, one, 0]])


def test_2d_theta_pi_and_minus_pi_are_one_code():
    minus_pi = Pose(np.array([[-1.0, 0.0], [-0.0, -1.0]]), np.zeros(2))
    assert minus_pi.as_xytheta()[2] == -math.pi
    pi = Pose.from_xytheta(0.0, 0.0, math.pi)
    assert pi.as_xytheta()[2] == math.pi
    assert raw_poses(PoseGraphUpdate("f", "r", 1, ((1, minus_pi), (2, pi))))[:, 2].tolist() == [-(2**31)] * 2


def test_pose_codes_round_half_to_even():
    """x = 0.00025 m is 2.5 steps of 0.1 mm (in float64, 0.00025 * 10000 is 2.5 exactly): code 2;
    0.00035 is 3.5 steps: code 4."""
    assert 0.00025 * 10000 == 2.5 and 0.00035 * 10000 == 3.5
    poses = ((1, Pose.from_xytheta(0.00025, 0.00035, 0.0)), (2, Pose.from_xytheta(-0.00025, -0.00035, 0.0)))
    assert raw_poses(PoseGraphUpdate("f", "r", 1, poses))[:, :2].tolist() == [[2, 4], [-2, -4]]


def test_2d_pose_updates_are_fixed_points_of_decode_and_encode_and_3d_ones_nearly():
    """A 2D code decodes to a value half a step from every rounding boundary. A 3D quaternion is
    normalised by the decoder, which moves a large component's code by at most one step."""
    rng = np.random.default_rng(8)
    for _ in range(20):
        poses = tuple((node, Pose.from_xytheta(*rng.normal(0, 300, 2), rng.uniform(-4, 4))) for node in range(50))
        data = encode(PoseGraphUpdate("f", "r", 1, poses))
        assert encode(decode(data)) == data
    poses = tuple((node, Pose.from_quaternion(rng.normal(0, 300, 3), rng.normal(size=4))) for node in range(500))
    sent = raw_poses(PoseGraphUpdate("f", "r", 1, poses))
    again = raw_poses(decode(encode(PoseGraphUpdate("f", "r", 1, poses))))
    np.testing.assert_array_equal(again[:, :3], sent[:, :3])
    assert np.abs(again[:, 3:] - sent[:, 3:]).max() <= 1


def test_2d_f32_scans_and_messages_without_poses_are_fixed_points_of_decode_and_encode():
    """A float32 theta survives the rotation matrix the decoder makes of it (its float64 error is
    far below half a float32 step); a 3D quaternion is normalised on the way and may not."""
    rng = np.random.default_rng(5)
    for _ in range(40):
        data = encode(scan_message(rng, 2, 12, 2), "f32")
        assert encode(decode(data), "f32") == data
    for message in (
        Ack("f", "r", "s", "scan", (1, 2), (3,)),
        Rejection("f", "r", "s", "poses", (9,), "quota", "voll"),
        MapQuery("f", [0.1, 0.2], [1.0, 2.5], 0.1, ("a",)),
    ):
        assert encode(decode(encode(message))) == encode(message)


# --- decoder rules that docs/PROTOCOL.md states


def packed(raw: dict) -> bytes:
    return msgpack.packb(raw, use_bin_type=True)


def ack_wire(**extra) -> dict:
    return msgpack.unpackb(encode(Ack("f", "r", "s", "scan", (1,))), raw=False) | extra


def test_string_limits_count_utf8_bytes():
    assert decode(packed(ack_wire(note="é" * 512)))  # 512 characters, 1024 bytes: the msgpack limit
    with pytest.raises(ProtocolError, match="^message: malformed"):
        decode(packed(ack_wire(note="é" * 513)))
    assert Rejection("f", "r", "s", "scan", (1,), "quota", "é" * 500).detail == "é" * 500  # 1000 bytes
    with pytest.raises(ProtocolError, match="^detail:"):
        Rejection("f", "r", "s", "scan", (1,), "quota", "é" * 500 + "x")


def test_ext_types_are_refused_even_when_empty_and_unknown():
    with pytest.raises(ProtocolError, match="^message: malformed msgpack: ValueError: ext type"):
        decode(packed(ack_wire(x=msgpack.ExtType(3, b""))))


@pytest.mark.parametrize(
    "message, key",
    [
        (PoseGraphUpdate("f", "r", 1, ((1, Pose.identity(2)),)), "anchor"),
        (MapQuery("f", [0, 0], [1, 1], 0.1), "robots"),
        (Ack("f", "r", "s", "scan", (1,)), "queued"),
        (Rejection("f", "r", "s", "scan", (1,), "quota"), "detail"),
    ],
)
def test_keys_that_may_be_nil_or_empty_are_still_required(message, key):
    raw = msgpack.unpackb(encode(message), raw=False)
    del raw[key]
    with pytest.raises(ProtocolError, match="missing"):
        decode(packed(raw))


def test_2d_theta_may_be_any_finite_number_and_bounds_of_an_empty_mixture_are_ignored():
    raw = msgpack.unpackb(encode(scan_of(Mixture.empty(2))), raw=False)
    raw["p"] = np.array([0.0, 0.0, 100.0], "<f4").tobytes()
    raw["O"]["b"] = b"anything"
    message = decode(packed(raw))
    assert message.pose.R[1, 0] == pytest.approx(math.sin(np.float32(100.0)))
