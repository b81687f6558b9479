"""Transform buffer against plain references: 4x4 matrices composed by hand, scipy's Slerp."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from gmm_core.pose import Pose
from services.datasets import DatasetError
from services.datasets.tf import Extrapolation, TimedPoses, TransformBuffer


def random_pose(rng) -> Pose:
    return Pose(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3) * 3)


def matrix(pose: Pose) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = pose.R, pose.t
    return M


def test_static_chains_against_matrices():
    rng = np.random.default_rng(0)
    # map -> odom -> base -> laser, base -> camera -> optical; world -> other (a second tree)
    edges = [("map", "odom"), ("odom", "base"), ("base", "laser"), ("base", "camera"), ("camera", "optical")]
    edges.append(("world", "other"))
    buf, M = TransformBuffer(), {}
    for parent, child in edges:
        p = random_pose(rng)
        buf.add_static(parent, child, p)
        M[child] = (parent, matrix(p))

    def to_root(frame):
        out = np.eye(4)
        while frame in M:
            parent, m = M[frame]
            out, frame = m @ out, parent
        return out

    for target, source in [("map", "optical"), ("laser", "optical"), ("optical", "laser"), ("odom", "base")]:
        got = matrix(buf.lookup(target, source, 0.0))
        np.testing.assert_allclose(got, np.linalg.inv(to_root(target)) @ to_root(source), atol=1e-12)
    np.testing.assert_allclose(matrix(buf.lookup("laser", "laser", 5.0)), np.eye(4))
    assert buf.root("optical") == "map" and buf.root("other") == "world"
    with pytest.raises(DatasetError, match="between frames 'world' and 'laser'"):
        buf.lookup("world", "laser", 0.0)
    with pytest.raises(DatasetError, match="between frames 'map' and 'nowhere'"):
        buf.lookup("map", "nowhere", 0.0)


def test_timed_transforms_interpolate_like_scipy():
    rng = np.random.default_rng(1)
    stamps = np.sort(rng.uniform(0, 10, 12))
    rotations = Rotation.random(12, random_state=rng)
    translations = rng.normal(size=(12, 3))
    buf = TransformBuffer()
    offset = random_pose(rng)
    buf.add_static("base", "laser", offset)
    for k in rng.permutation(12):  # out of order, as messages from several publishers arrive
        buf.add("odom", "base", stamps[k], Pose(rotations[k].as_matrix(), translations[k]))
    queries = np.concatenate([rng.uniform(stamps[0], stamps[-1], 50), stamps])
    reference = Slerp(stamps, rotations)(queries)
    for q, r in zip(queries, reference):
        t = np.array([np.interp(q, stamps, translations[:, i]) for i in range(3)])
        want = matrix(Pose(r.as_matrix(), t)) @ matrix(offset)
        np.testing.assert_allclose(matrix(buf.lookup("odom", "laser", q)), want, atol=1e-9)
    for outside in (stamps[0] - 1e-6, stamps[-1] + 0.5):
        with pytest.raises(Extrapolation, match="transform 'odom' -> 'base'"):
            buf.lookup("odom", "laser", outside)
    np.testing.assert_allclose(buf.lookup("laser", "base", 3.0).t, offset.inverse().t)  # static only: any stamp


def test_sample_stamps_return_the_sample_and_duplicates_keep_the_first():
    p0, p1, p2 = (Pose.from_quaternion([k, 0, 0], [1, 0, 0, 0]) for k in range(3))
    series = TimedPoses.from_samples([(2.0, p1), (1.0, p0), (2.0, p2), (3.0, p2)], "/odom")
    assert series.span == (1.0, 3.0)
    np.testing.assert_array_equal(series.at(2.0).t, [1, 0, 0])
    np.testing.assert_allclose(series.at(1.5).t, [0.5, 0, 0])


def test_inconsistent_trees_are_named():
    buf = TransformBuffer()
    buf.add_static("base", "laser", Pose.identity(3))
    with pytest.raises(DatasetError, match="frame 'laser' has two parents, 'base' and 'arm'"):
        buf.add_static("arm", "laser", Pose.identity(3))
    with pytest.raises(DatasetError, match="frame 'laser': a timed transform, but a static one too"):
        buf.add("base", "laser", 1.0, Pose.identity(3))
    buf.add_static("laser", "arm", Pose.identity(3))
    buf.add_static("arm", "base", Pose.identity(3))
    with pytest.raises(DatasetError, match="loop"):
        buf.root("laser")


def test_forgetting_old_samples_keeps_every_later_lookup():
    rng = np.random.default_rng(5)
    buffer, full = TransformBuffer(), TransformBuffer()
    for stamp in np.sort(rng.uniform(0, 10, 40)):
        pose = random_pose(rng)
        for b in (buffer, full):
            b.add("odom", "base", float(stamp), pose)
    buffer.forget_before(6.0)
    for stamp in np.linspace(6.0, full._samples["base"][-1][0], 17):
        assert np.array_equal(matrix(buffer.lookup("odom", "base", stamp)), matrix(full.lookup("odom", "base", stamp)))
    assert len(buffer._samples["base"]) < len(full._samples["base"])
    with pytest.raises(Extrapolation):
        buffer.lookup("odom", "base", 1.0)
