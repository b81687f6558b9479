"""Poses: interpolation between two poses (2D and 3D) against closed forms and scipy; many poses
built at once against Pose one by one."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from gmm_core.pose import Pose, displacements, poses_from_arrays, poses_from_xytheta, slerp
from support.fuzz import random_rotations


def test_slerp_closed_form_and_short_way():
    axis = np.array([0.0, 0.0, 1.0])
    for f in (0.0, 0.25, 0.5, 1.0):
        q = slerp(np.array([1.0, 0, 0, 0]), np.array([np.cos(0.6), *(np.sin(0.6) * axis)]), f)
        np.testing.assert_allclose(q, [np.cos(0.6 * f), 0, 0, np.sin(0.6 * f)], atol=1e-15)
    # -q1 is the same rotation as q1: the half-way point is still a 0.3 rad turn about z
    q = slerp(np.array([1.0, 0, 0, 0]), -np.array([np.cos(0.3), 0, 0, np.sin(0.3)]), 0.5)
    np.testing.assert_allclose(abs(q @ [np.cos(0.15), 0, 0, np.sin(0.15)]), 1, atol=1e-15)
    np.testing.assert_allclose(slerp(np.array([0.0, 1, 0, 0]), np.array([0.0, 1, 0, 0]), 0.3), [0, 1, 0, 0])


def test_between_follows_the_line_and_the_shorter_arc():
    a, b = Pose.from_xytheta(0, 0, np.radians(170)), Pose.from_xytheta(2, 4, np.radians(-170))
    mid = a.between(b, 0.5)
    np.testing.assert_allclose(mid.t, [1, 2])
    assert abs(abs(mid.as_xytheta()[2]) - np.pi) < 1e-12  # through 180 degrees, not through 0
    rng = np.random.default_rng(0)
    for _ in range(20):
        r = Rotation.random(2, random_state=rng)
        a, b = Pose(r[0].as_matrix(), rng.normal(size=3)), Pose(r[1].as_matrix(), rng.normal(size=3))
        f = rng.uniform()
        want = Slerp([0, 1], r)(f).as_matrix()
        np.testing.assert_allclose(a.between(b, f).R, want, atol=1e-9)
        np.testing.assert_allclose(a.between(b, f).t, a.t + f * (b.t - a.t))


@pytest.mark.parametrize("dim", [2, 3])
def test_poses_from_arrays_builds_and_refuses_what_pose_does(dim):
    rng = np.random.default_rng(dim)
    for _ in range(20):
        n = int(rng.integers(0, 50))
        R = Rotation.random(n, random_state=rng).as_matrix() if n else np.zeros((0, 3, 3))
        R = R[:, :dim, :dim] if dim == 3 else np.array([Pose.from_xytheta(0, 0, a).R for a in rng.uniform(-4, 4, n)])
        t = rng.normal(size=(n, dim)) * 100
        R, t = R.reshape(n, dim, dim), t.reshape(n, dim)
        bad = int(rng.integers(n)) if n and rng.random() < 0.5 else None
        if bad is not None:  # a reflection, a scaled rotation or a NaN: refused by both, with one message
            how = rng.integers(3)
            if how == 0:
                R[bad, 0] *= -1
            elif how == 1:
                R[bad] *= 1.001
            else:
                t[bad, -1] = np.nan
        try:
            one_by_one = [Pose(r, v) for r, v in zip(R, t)]
        except ValueError as error:
            with pytest.raises(ValueError, match=str(error)):
                poses_from_arrays(R, t)
            continue
        many = poses_from_arrays(R, t)
        assert [(p.R.tobytes(), p.t.tobytes()) for p in many] == [(p.R.tobytes(), p.t.tobytes()) for p in one_by_one]
    with pytest.raises(ValueError, match="must be"):
        poses_from_arrays(np.zeros((2, 3, 3)), np.zeros((2, 2)))


def test_poses_from_xytheta_are_pose_from_xytheta_of_each_row():
    rows = np.random.default_rng(0).normal(size=(200, 3)) * [50, 50, 4]
    many = poses_from_xytheta(rows)
    one_by_one = [Pose.from_xytheta(*row) for row in rows]
    assert [(p.R.tobytes(), p.t.tobytes()) for p in many] == [(p.R.tobytes(), p.t.tobytes()) for p in one_by_one]
    assert poses_from_xytheta(np.zeros((0, 3))) == []
    with pytest.raises(ValueError, match="non-finite"):
        poses_from_xytheta([[0.0, 0.0, np.nan]])


@pytest.mark.parametrize("dim", [2, 3])
def test_displacement_bounds_how_far_points_within_reach_move_and_is_reached(dim):
    """Against brute force: the largest move of many points within `reach` never exceeds the bound,
    and in 2D (a single rotation plane) points on the reach circle come within 0.1 % of it."""
    rng = np.random.default_rng(dim)
    for _ in range(50):
        if dim == 2:
            a, b = (Pose.from_xytheta(*rng.normal(size=2), rng.uniform(-np.pi, np.pi)) for _ in range(2))
        else:
            a, b = (Pose.from_quaternion(rng.normal(size=3), rng.normal(size=4)) for _ in range(2))
        reach = rng.uniform(0.1, 20.0)
        points = rng.normal(size=(20_000, dim))
        points *= reach / np.linalg.norm(points, axis=1, keepdims=True)  # on the sphere of radius reach
        inside = points * rng.uniform(0, 1, size=(len(points), 1))
        moved = np.linalg.norm(b.apply(np.vstack([points, inside])) - a.apply(np.vstack([points, inside])), axis=1)
        bound = a.displacement(b, reach)
        assert moved.max() <= bound + 1e-9
        if dim == 2:  # every point turns by the same angle: the farthest is the one along the translation
            assert moved.max() >= 0.999 * bound
    same = Pose.from_xytheta(1.0, 2.0, 0.3) if dim == 2 else Pose.from_quaternion([1, 2, 3], [1, 0.2, 0, 0])
    assert same.displacement(same, 100.0) == pytest.approx(0.0, abs=1e-6)


def reference(a: Pose, b: Pose, reach: float) -> float:
    turn = a.R.T @ b.R
    if a.dim == 2:
        turn = np.block([[turn, np.zeros((2, 1))], [np.zeros((1, 2)), np.ones((1, 1))]])
    return float(np.linalg.norm(b.t - a.t)) + reach * 2 * np.sin(float(Rotation.from_matrix(turn).magnitude()) / 2)


@pytest.mark.parametrize("dim", [2, 3])
def test_displacements_match_a_pose_by_pose_reference_by_scipy(dim):
    rng = np.random.default_rng(dim)
    n = 500
    R0 = random_rotations(rng, n, dim)
    small = random_rotations(rng, n, dim)  # turned by up to a few mrad from R0, or anything
    steps = rng.choice([1e-4, 1e-3, 1e-2, 1.0], n)
    if dim == 2:
        theta = rng.normal(0.0, 1.0, n) * steps
        small = np.stack([np.stack([np.cos(theta), -np.sin(theta)], 1), np.stack([np.sin(theta), np.cos(theta)], 1)], 1)
    else:
        axis = rng.normal(size=(n, 3))
        small = np.array([Pose.from_quaternion(np.zeros(3), [1.0, *(a * s)]).R for a, s in zip(axis, steps)])
    R1 = R0 @ small
    t0, t1 = rng.normal(0, 20, (n, dim)), rng.normal(0, 20, (n, dim)) * steps[:, None]
    t1 += t0
    reach = rng.uniform(0, 30, n)
    got = displacements(t0, R0, t1, R1, reach)
    want = [reference(Pose(a, x), Pose(b, y), r) for a, x, b, y, r in zip(R0, t0, R1, t1, reach)]
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)


def test_as_quaternion_gives_back_the_rotation_also_at_half_turns_about_slanted_axes():
    """w >= 0 and from_quaternion(as_quaternion) == R: on random rotations, and on half turns (w = 0),
    where the signs of x, y, z must come from the off-diagonal sums, not the differences (both ~0)."""
    rng = np.random.default_rng(7)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    quaternions = [rng.normal(size=4) for _ in range(200)] + [np.array([0.0, *a]) for a in axes]
    quaternions += [np.array([1e-9, *a]) for a in axes[:50]]  # just short of a half turn
    for q in quaternions:
        pose = Pose.from_quaternion(rng.normal(size=3), q)
        back = pose.as_quaternion()
        assert back[0] >= 0 and abs(np.linalg.norm(back) - 1) < 1e-12
        np.testing.assert_allclose(Pose.from_quaternion(pose.t, back).R, pose.R, atol=1e-12)
