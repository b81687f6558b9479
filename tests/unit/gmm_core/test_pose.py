"""Poses: interpolation between two poses (2D and 3D) against closed forms and scipy."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from gmm_core.pose import Pose, slerp


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
