"""The fused sample-and-trace kernel against its plain reference: every sample drawn (scan_rays),
moved by the pose in numpy and traced by trace_rays; and the sampler's own properties."""

import numpy as np
import pytest
from numba import njit
from scipy.special import ndtri

from gmm_core import Grid, Mixture, Pose, ScanModel
from gmm_core.raytrace import trace_rays
from gmm_core.sampling import (
    WEIGHT_QUANTUM,
    Z_MAX,
    draw,
    mixture_samples,
    normal_quantile,
    sample_bounds,
    scan_rays,
    scan_samples,
)
from gmm_core.scan_trace import HIT_STOP_CELLS, GridCounts, _trace_hit
from support.evidence import hit_stop


def random_mixture(rng, dim, k, spread, support):
    a = rng.normal(size=(k, dim, dim)) * rng.uniform(0.02, 0.5, (k, 1, 1))
    covariances = a @ a.transpose(0, 2, 1) + 1e-4 * np.eye(dim)
    weights = rng.dirichlet(np.ones(k))
    return Mixture(weights, rng.uniform(-spread, spread, (k, dim)), covariances, support)


def random_pose(rng, dim):
    if dim == 2:
        return Pose.from_xytheta(*rng.uniform(-2, 2, 2), rng.uniform(-np.pi, np.pi))
    return Pose.from_quaternion(rng.uniform(-2, 2, 3), rng.normal(size=4))


def moved_rays(grid, model, pose, seed, samples_per_cell):
    """Every sample drawn and moved as the kernel moves it (R p + t summed in index order): the moved
    origin, ends, weights, is_hit, each sample's index in its component and that component's count,
    and how far short of each sample its misses stop (m; an occupied sample's, see stopped_short)."""
    ends, weights, is_hit = scan_rays(model, grid.resolution, seed, samples_per_cell)
    samples = scan_samples(model, grid.resolution, seed, samples_per_cell)
    counts = np.concatenate([samples.occupied.counts, samples.free.counts])
    index = np.concatenate([np.arange(n) for n in counts]).astype(int) if len(counts) else np.zeros(0, int)
    stops = [hit_stop(c, grid.resolution) for m in (model.occupied, model.free) for c in m.covariances]
    stop = np.repeat(np.array(stops, dtype=float), counts)
    R, t = pose.R, pose.t

    def moved(p):
        return np.column_stack([sum(R[a, b] * p[:, b] for b in range(len(t))) + t[a] for a in range(len(t))])

    return moved(model.origin[None])[0], moved(ends), weights, is_hit, index, np.repeat(counts, counts), stop


def stopped_short(origin, ends, stop):
    """Each end moved `stop` (m) toward the origin, and whether the ray is longer than that (the
    misses of an occupied sample's ray end there: HIT_STOP_CELLS cells, or HIT_STOP_SIGMAS of its
    component's thinnest standard deviation where that is farther, gmm_core.scan_trace)."""
    delta = ends - origin
    length = np.linalg.norm(delta, axis=1)
    kept = 1.0 - stop / length
    return origin + kept[:, None] * delta, kept > 0.0


def reference(grid, model, pose, seed, samples_per_cell):
    """2D: `whole` (2D rays are not thinned). 3D: every cell a sample's ray crosses, found by brute
    force, with the weight of the level (module docstring of gmm_core.scan_trace) at which the ray
    enters it: the first ceil(n / 4^l) samples on t in [2^-(l+1), 2^-l) with weight n / that; an
    occupied sample's ray stopped short of it, and its own cell, where it has the hit, gains no miss."""
    if grid.dim == 2:
        return whole(grid, model, pose, seed, samples_per_cell)
    origin, ends, weights, is_hit, index, n, stop = moved_rays(grid, model, pose, seed, samples_per_cell)
    centres = grid.cell_centers()
    lo_c, hi_c = centres - grid.resolution / 2, centres + grid.resolution / 2
    short, kept = stopped_short(origin, ends, stop)
    hits, misses = np.zeros(grid.n_cells), np.zeros(grid.n_cells)
    for e, e_short, has_misses, w, hit, s, count in zip(ends, short, kept, weights, is_hit, index, n):
        end_cell = np.all((e >= lo_c) & (e < hi_c), axis=1)
        if hit:
            hits[end_cell] += w
            if not has_misses:
                continue
            e = e_short
        delta = e - origin
        with np.errstate(divide="ignore", invalid="ignore"):
            ta, tb = (lo_c - origin) / delta, (hi_c - origin) / delta
        enters = np.maximum(np.max(np.where(delta != 0, np.minimum(ta, tb), -np.inf), axis=1), 0.0)
        leaves = np.minimum(np.min(np.where(delta != 0, np.maximum(ta, tb), np.inf), axis=1), 1.0)
        cell_weight = np.zeros(grid.n_cells)
        level, m = 0, count
        while s < m:  # the levels sample s takes part in, from the sample inward
            inner = -(-count // 4 ** (level + 1))
            on_level = enters >= (0.5 ** (level + 1) if inner < m else -1.0)
            on_level &= enters < 0.5**level if level else enters <= 1.0
            cell_weight[on_level] = np.rint(w * count / m / WEIGHT_QUANTUM) * WEIGHT_QUANTUM
            if inner == m:
                break
            level, m = level + 1, inner
        crossed = enters < leaves
        if hit:
            crossed &= ~end_cell
        misses[crossed] += cell_weight[crossed]
    return hits.reshape(grid.array_shape), misses.reshape(grid.array_shape)


@pytest.mark.parametrize("dim", [2, 3])
def test_fused_trace_equals_tracing_every_sample(dim):
    """On random mixtures, poses and grids that the scans reach in part, against every sample traced
    (in 3D thinned toward the sensor): components skipped because their rays miss the grid add
    nothing that tracing them would have added."""
    rng = np.random.default_rng(10 + dim)
    skipped = thinned = 0
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
        if dim == 2:  # the same traversal: bit for bit
            assert np.array_equal(fused_hits, hits) and np.array_equal(fused_misses, misses), f"trial {trial}"
        else:  # brute force: sums of the same quantised weights, so equal but for a cell crossed at a corner
            assert np.allclose(fused_hits, hits, rtol=0, atol=1e-9), f"trial {trial}"
            assert np.allclose(fused_misses, misses, rtol=0, atol=1e-9), f"trial {trial}"
            thinned += not np.array_equal(misses, whole(grid, model, pose, trial, 2.0)[1])
        assert hits.sum() > 0 or misses.sum() > 0
    assert skipped > 0  # the test exercises the skipping
    assert thinned > 0 or dim == 2  # and the thinning


def whole(grid, model, pose, seed, samples_per_cell):
    """Every sample's ray traced whole (trace_rays), none thinned; an occupied sample's misses
    stopped short of it, none in its own cell."""
    origin, ends, weights, is_hit, _, _, stop = moved_rays(grid, model, pose, seed, samples_per_cell)
    hits, misses = trace_rays(grid, origin[None], np.zeros(len(ends), int), ends, weights, is_hit, threads=1)
    short, kept = stopped_short(origin, ends, stop)
    miss_ends = np.where(is_hit[:, None], short, ends)
    traced = ~is_hit | kept
    n = int(traced.sum())
    _, misses = trace_rays(
        grid, origin[None], np.zeros(n, int), miss_ends[traced], weights[traced], np.zeros(n, bool), threads=1
    )
    stop_cell = cell_of(grid, miss_ends)
    own_cell = is_hit & kept & (stop_cell >= 0) & (stop_cell == cell_of(grid, ends))
    np.subtract.at(misses.reshape(-1), stop_cell[own_cell], weights[own_cell])
    return hits, misses


def cell_of(grid, points):
    """The flat cell number of each point on `grid` (as hits.ravel() numbers them), -1 outside."""
    index = np.floor((points - grid.origin) / grid.resolution).astype(np.int64)
    inside = np.all((index >= 0) & (index < np.asarray(grid.shape)), axis=1)
    flat = np.ravel_multi_index(tuple(np.where(inside[:, None], index, 0)[:, ::-1].T), grid.array_shape)
    return np.where(inside, flat, -1)


def test_thinned_misses_keep_their_expectation_and_every_hit():
    """3D misses are thinned toward the sensor without bias: over 40 seeds, the mean difference from
    tracing every ray whole (the same samples) is within 5 standard errors of 0, summed over each
    shell of cells around the sensor; the hits are those of every ray, and thinning does act."""
    rng = np.random.default_rng(7)
    model = ScanModel(random_mixture(rng, 3, 6, 2.5, 300), random_mixture(rng, 3, 2, 2.5, 40), np.zeros(3), 10.0)
    grid = Grid(np.full(3, -3.0), 0.25, (24, 24, 24))  # the sensor at its centre
    shell = np.minimum(np.linalg.norm(grid.cell_centers(), axis=1) // 0.5, 6).astype(int)
    differences = []
    for seed in range(40):
        counts = GridCounts(grid)
        counts.add(scan_samples(model, grid.resolution, seed, 1.0), Pose.identity(3))
        hits, misses = whole(grid, model, Pose.identity(3), seed, 1.0)
        assert np.array_equal(counts.hits, hits.ravel())
        differences.append(np.bincount(shell, counts.misses - misses.ravel(), minlength=7))
    differences = np.array(differences)
    mean, standard_error = differences.mean(axis=0), differences.std(axis=0, ddof=1) / np.sqrt(len(differences))
    assert (standard_error > 0).sum() >= 4  # shells the thinning reaches
    assert np.all(np.abs(mean) <= 5 * standard_error + 1e-9), (mean, standard_error)


def test_an_occupied_sample_claims_free_only_the_cells_a_stop_short_of_it():
    """One sample of one component (n = 1: no thinning) from the corner of a 0.1 m grid: its hit in its
    own cell, misses up to the cell of the point HIT_STOP_CELLS before it; where that point is in the
    sample's own cell (a diagonal ray ending in a far corner), the cell gains the hit alone."""
    dims = np.array([8, 8, 8])

    def trace(q, o=(0.0, 0.0, 0.0)):
        hits, misses = np.zeros(512), np.zeros(512)
        cells, lo, hi = np.empty(28, np.uint32), np.zeros(3), dims - 1.0
        args = (np.array(o), np.array(q), 1.0, 0, 1, True, 0.1 * HIT_STOP_CELLS, np.zeros(3), 10.0, dims, lo, hi)
        _trace_hit(*args, cells, hits, misses, np.empty(3))
        return hits.reshape(8, 8, 8), misses.reshape(8, 8, 8)  # [z, y, x]

    hits, misses = trace([0.55, 0.05, 0.05])  # along x, in cell x = 5 of the row y = z = 0
    stop = int(np.floor(10 * (0.55 - 0.1 * HIT_STOP_CELLS)))  # the cell of the stop point, before the sample's
    assert hits[0, 0, 5] == 1.0 and hits.sum() == 1.0 and stop < 5
    assert np.array_equal(np.flatnonzero(misses[0, 0]), np.arange(stop + 1)) and misses.sum() == stop + 1
    hits, misses = trace([0.599, 0.598, 0.597], (0.013, 0.007, 0.001))  # diagonal: its stop point ~0.06 m back
    assert hits[5, 5, 5] == 1.0 and misses[5, 5, 5] == 0.0 and misses[4, 4, 4] > 0.0
    hits, misses = trace([0.05, 0.0, 0.0])  # nearer than the stop: the hit alone
    assert hits.sum() == 1.0 and misses.sum() == 0.0


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
