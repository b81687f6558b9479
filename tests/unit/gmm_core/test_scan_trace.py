"""The fused sample-and-trace kernel against its plain reference: every sample drawn (scan_rays),
moved by the pose in numpy and traced by trace_rays; and the sampler's own properties."""

import numpy as np
import pytest
from numba import njit
from scipy.special import ndtri

from gmm_core import Grid, Mixture, Pose, ScanModel
from gmm_core.raytrace import trace_rays
from gmm_core.sampling import Z_MAX, draw, mixture_samples, normal_quantile, sample_bounds, scan_rays, scan_samples
from gmm_core.scan_trace import GridCounts


def random_mixture(rng, dim, k, spread, support):
    a = rng.normal(size=(k, dim, dim)) * rng.uniform(0.02, 0.5, (k, 1, 1))
    covariances = a @ a.transpose(0, 2, 1) + 1e-4 * np.eye(dim)
    weights = rng.dirichlet(np.ones(k))
    return Mixture(weights, rng.uniform(-spread, spread, (k, dim)), covariances, support)


def random_pose(rng, dim):
    if dim == 2:
        return Pose.from_xytheta(*rng.uniform(-2, 2, 2), rng.uniform(-np.pi, np.pi))
    return Pose.from_quaternion(rng.uniform(-2, 2, 3), rng.normal(size=4))


def reference(grid, model, pose, seed, samples_per_cell):
    """Every sample drawn, moved as the kernel moves it (R p + t summed in index order), traced."""
    ends, weights, is_hit = scan_rays(model, grid.resolution, seed, samples_per_cell)
    R, t = pose.R, pose.t

    def moved(p):
        return np.column_stack([sum(R[a, b] * p[:, b] for b in range(len(t))) + t[a] for a in range(len(t))])

    origin = moved(model.origin[None])
    return trace_rays(grid, origin, np.zeros(len(ends), int), moved(ends), weights, is_hit, threads=1)


@pytest.mark.parametrize("dim", [2, 3])
def test_fused_trace_equals_tracing_every_sample(dim):
    """Bit for bit, on random mixtures, poses and grids that the scans reach in part: components
    skipped because their rays miss the grid add nothing that tracing them would have added."""
    rng = np.random.default_rng(10 + dim)
    skipped = 0
    for trial in range(6):
        model = ScanModel(
            random_mixture(rng, dim, 12, 6.0, 400),
            random_mixture(rng, dim, 3, 8.0, 50) if trial % 2 else Mixture.empty(dim),
            rng.uniform(-1, 1, dim),
            10.0,
        )
        pose = random_pose(rng, dim)
        shape = (17, 13) if dim == 2 else (11, 9, 7)
        grid = Grid(rng.uniform(-4, 1, dim), rng.uniform(0.15, 0.4), shape)
        counts = GridCounts(grid)
        samples = scan_samples(model, grid.resolution, seed=trial, samples_per_cell=2.0)
        counts.add(samples, pose)
        skipped += samples.n_samples - counts.samples_traced
        hits, misses = reference(grid, model, pose, trial, 2.0)
        fused_hits, fused_misses = counts.arrays()
        assert np.array_equal(fused_hits, hits) and np.array_equal(fused_misses, misses), f"trial {trial}"
        assert hits.sum() > 0 or misses.sum() > 0
    assert skipped > 0  # the test exercises the skipping


@pytest.mark.parametrize("dim", [2, 3])
def test_many_scans_in_one_call_equal_adding_them_one_by_one(dim):
    """add_many (one kernel call for a batch of nodes) against add node by node, bit for bit:
    random scans, poses, signs and samples per cell, some with no free mixture."""
    rng = np.random.default_rng(20 + dim)
    shape = (23, 19) if dim == 2 else (13, 11, 9)
    grid = Grid(rng.uniform(-4, 0, dim), 0.3, shape)
    scans = []
    for i in range(9):
        free = random_mixture(rng, dim, 3, 8.0, 50) if i % 3 else Mixture.empty(dim)
        model = ScanModel(random_mixture(rng, dim, 10, 6.0, 400), free, rng.uniform(-1, 1, dim), 10.0)
        samples = scan_samples(model, grid.resolution, seed=i, samples_per_cell=float(rng.choice([1.0, 4.0])))
        scans.append((samples, random_pose(rng, dim), float(rng.choice([1.0, -1.0]))))
    one_by_one, batched = GridCounts(grid), GridCounts(grid)
    for scan in scans:
        one_by_one.add(*scan)
    batched.add_many(scans)
    assert batched.samples_traced == one_by_one.samples_traced > 0
    for a, b in zip(batched.arrays(), one_by_one.arrays()):
        assert np.array_equal(a, b) and np.abs(a).sum() > 0


def test_a_scan_taken_out_again_leaves_the_counts_bit_for_bit():
    """Counts are sums of quantised weights: adding a scan at one pose and subtracting it there
    again gives back exactly the counts without it (a cached tile updated for a moved node)."""
    rng = np.random.default_rng(3)
    model = ScanModel(random_mixture(rng, 3, 8, 3.0, 300), random_mixture(rng, 3, 2, 5.0, 40), np.zeros(3), 10.0)
    grid = Grid(np.full(3, -3.0), 0.2, (30, 30, 30))
    samples = scan_samples(model, grid.resolution, seed=1, samples_per_cell=3.0)
    kept, moved = random_pose(rng, 3), random_pose(rng, 3)
    updated, fresh = GridCounts(grid), GridCounts(grid)
    updated.add(samples, kept)
    updated.add(samples, moved)
    updated.add(samples, moved, sign=-1.0)
    fresh.add(samples, kept)
    assert fresh.hits.sum() > 0
    assert np.array_equal(updated.hits, fresh.hits) and np.array_equal(updated.misses, fresh.misses)


def test_counts_on_a_grid_beyond_32_bit_cell_numbers_are_refused_before_allocating():
    with pytest.raises(ValueError, match="grid: 2147483648 cells"):
        GridCounts(Grid(np.zeros(3), 0.1, (2048, 2048, 512)))


@pytest.mark.parametrize("dim", [2, 3])
def test_samples_are_normal_within_the_clipped_box(dim):
    """Mean and covariance of many samples of one component match it, and each stays in its box."""
    rng = np.random.default_rng(dim)
    mixture = random_mixture(rng, dim, 1, 1.0, 100)
    samples = mixture_samples(mixture, np.array([200_000]), np.uint64(12345))
    points, weights = draw(samples)
    assert np.allclose(points.mean(axis=0), mixture.means[0], atol=4 * np.sqrt(mixture.covariances[0].max() / 2e5))
    assert np.allclose(np.cov(points.T), mixture.covariances[0], rtol=0.02, atol=1e-3 * mixture.covariances[0].max())
    lo, hi = sample_bounds(mixture)
    assert np.all(points >= lo) and np.all(points <= hi)
    assert np.isclose(weights.sum(), 100, rtol=1e-4)  # weights quantised to 2^-26
    z = np.linalg.solve(np.linalg.cholesky(mixture.covariances[0]), (points - mixture.means[0]).T)
    assert np.abs(z).max() <= Z_MAX + 1e-9 and (np.abs(z) > 3.5).mean() > 1e-4  # clipped, not truncated early


@njit
def quantile(p):
    return normal_quantile(p)


def test_normal_quantile_matches_scipy():
    """Acklam's approximation against scipy's ndtri on random p, tails included."""
    p = np.concatenate([np.random.default_rng(0).random(20_000), 10.0 ** -np.linspace(1, 15, 200)])
    p = np.concatenate([p, 1 - p[-200:]])
    ours = np.array([quantile(x) for x in p])
    assert np.allclose(ours, ndtri(p), rtol=2e-9, atol=1e-12)
