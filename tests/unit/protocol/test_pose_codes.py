"""protocol/pose_codes.py: the vectorised int32 pose codes against a plain pose-by-pose reference
(Pose.as_xytheta, Pose.as_quaternion, Pose.from_xytheta, Pose.from_quaternion), on random poses,
and rotations on the axes (half turns, zero components) that must come back as they were sent."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gmm_core.pose import Pose
from protocol import ProtocolError
from protocol.pose_codes import QUATERNION_SCALE, pose_codes, poses_of_codes
from support.fuzz import random_rotations


def reference_codes(pose: Pose) -> list[int]:
    """docs/PROTOCOL.md, "Pose-graph update", one pose at a time in Python floats."""
    translation = [round(value * 10000.0) for value in pose.t.tolist()]  # Python round: half to even
    if pose.dim == 2:
        theta = round(pose.as_xytheta()[2] / math.pi * 2**31)
        return translation + [-(2**31) if theta == 2**31 else theta]
    q = [round(value * QUATERNION_SCALE) for value in pose.as_quaternion().tolist()]
    first = next((value for value in q if value != 0), 0)
    return translation + ([-value for value in q] if first < 0 else q)


def random_poses(rng, dim: int, count: int, on_axes: int = 0) -> list[Pose]:
    """Random poses, the first `on_axes` of them turned onto the axes (zero quaternion components,
    half turns about oblique axes, ties of the largest |q_j|)."""
    t = rng.normal(0.0, 500.0, (count, dim))
    R = random_rotations(rng, count, dim)
    for k in range(on_axes):
        R[k] = np.eye(dim)[rng.permutation(dim)] * rng.choice([-1.0, 1.0], dim)
        R[k, :, 0] *= np.linalg.det(R[k])
    return [Pose(rotation, translation) for rotation, translation in zip(R, t)]


@pytest.mark.parametrize("dim", [2, 3])
def test_codes_match_the_pose_by_pose_reference(dim):
    rng = np.random.default_rng(dim)
    poses = random_poses(rng, dim, 400)
    codes = pose_codes(poses, dim, "poses.poses")
    assert codes.dtype == np.dtype("<i4") and codes.shape == (400, 3 if dim == 2 else 7)
    assert codes.tolist() == [reference_codes(pose) for pose in poses]


@pytest.mark.parametrize("dim", [2, 3])
def test_decoded_poses_match_the_pose_by_pose_reference_within_a_step(dim):
    rng = np.random.default_rng(20 + dim)
    poses = random_poses(rng, dim, 300, on_axes=60)
    all_codes = pose_codes(poses, dim, "poses.poses")
    decoded = poses_of_codes(all_codes, dim, "poses.poses")
    for sent, got, codes in zip(poses, decoded, all_codes.tolist()):
        assert np.abs(got.t - sent.t).max() <= 0.5e-4 + 1e-12  # half a step of 0.1 mm
        assert np.abs(got.R - sent.R).max() <= 4e-9  # 2pi / 2^32 in 2D, 2^-31 per quaternion component in 3D
        if dim == 2:
            x, y, theta = codes[0] / 1e4, codes[1] / 1e4, codes[2] / 2**31 * math.pi
            reference = Pose.from_xytheta(x, y, theta)
        else:
            reference = Pose.from_quaternion(np.array(codes[:3]) / 1e4, np.array(codes[3:]) / QUATERNION_SCALE)
        np.testing.assert_allclose(got.R, reference.R, rtol=0, atol=4e-15)  # norms summed in another order
        np.testing.assert_allclose(got.t, reference.t, rtol=0, atol=0)


def test_a_3d_code_off_the_unit_sphere_is_refused_and_every_2d_code_is_a_pose():
    codes = np.array([[0, 0, 0, 2**31 - 1, 0, 0, 2**21]], "<i4")  # norm 1 + 5e-7: normalised
    assert poses_of_codes(codes, 3, "poses.poses")[0].R[0, 0] == pytest.approx(1.0, abs=1e-5)
    with pytest.raises(ProtocolError, match="^anchor: quaternion norm 0.99"):
        poses_of_codes(np.array([[0, 0, 0, 2**31 - 1 - 2**22, 0, 0, 0]], "<i4"), 3, "anchor")
    extremes = np.array([[-(2**31), 2**31 - 1, -(2**31)], [2**31 - 1, 0, 2**31 - 1]], "<i4")
    decoded = poses_of_codes(extremes, 2, "poses.poses")
    assert decoded[0].as_xytheta() == pytest.approx((-214748.3648, 214748.3647, -math.pi))
