"""gmm_core.analytic.components: a node's components decomposed once in its frame and posed
(NodeComponents, world_components) against the plain way, each posed covariance decomposed anew."""

import numpy as np
import pytest

from gmm_core import Pose, fit_scan
from gmm_core.analytic.components import NodeComponents, isotropic_maps, world_components


def posed_scans(dim, rng, n=4):
    scans = []
    for _ in range(n):
        hits = rng.normal(0, 2, (300, dim)) * rng.uniform(0.05, 1, dim) + rng.uniform(-5, 5, dim)
        beams = rng.normal(size=(20, dim))
        model = fit_scan(hits, beams / np.linalg.norm(beams, axis=1, keepdims=True))
        if dim == 2:
            pose = Pose.from_xytheta(*rng.uniform(-3, 3, 2), rng.uniform(-np.pi, np.pi))
        else:
            pose = Pose.from_quaternion(rng.uniform(-3, 3, 3), rng.normal(size=4))
        scans.append((model, pose))
    return scans


@pytest.mark.parametrize("dim", [2, 3])
def test_posed_node_components_are_the_posed_mixtures_decomposed(dim):
    rng = np.random.default_rng(dim)
    scans = posed_scans(dim, rng)
    comp = world_components([(NodeComponents.of(m), p) for m, p in scans], dim)
    # plain: every mixture moved to the world (Eq. 2), then its covariances decomposed
    means, covs, sensors, counts, free = [], [], [], [], []
    for model, pose in scans:
        for mixture, is_free in ((model.occupied, False), (model.free, True)):
            world = mixture.transformed(pose)
            means.append(world.means)
            covs.append(world.covariances)
            sensors.append(np.broadcast_to(pose.apply(model.origin[None])[0], world.means.shape))
            counts.append(world.support * world.weights)
            free.append(np.full(world.n_components, is_free))
    plain_covs, evals, _, isos = isotropic_maps(np.concatenate(covs))
    np.testing.assert_allclose(comp.means, np.concatenate(means), atol=1e-12)
    np.testing.assert_allclose(comp.covs, plain_covs, atol=1e-12)
    np.testing.assert_allclose(comp.evals, evals, rtol=1e-9, atol=1e-15)
    # the isotropic map up to the sign of each axis: its Gram matrix is Sigma^-1
    gram = np.swapaxes(comp.isos, 1, 2) @ comp.isos
    inverse = np.swapaxes(isos, 1, 2) @ isos
    np.testing.assert_allclose(gram, inverse, rtol=1e-7, atol=1e-9 * np.abs(inverse).max())
    np.testing.assert_allclose(
        comp.evecs @ np.swapaxes(comp.evecs, 1, 2), np.broadcast_to(np.eye(dim), gram.shape), atol=1e-12
    )
    np.testing.assert_array_equal(comp.sensors, np.concatenate(sensors))
    np.testing.assert_array_equal(comp.counts, np.concatenate(counts))
    np.testing.assert_array_equal(comp.max_range, np.concatenate(free))
    # scan models are decomposed on the way: the same as their NodeComponents
    direct = world_components(scans, dim)
    np.testing.assert_array_equal(direct.covs, comp.covs)
    assert world_components([], dim).means.shape == (0, dim)
