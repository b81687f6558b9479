"""Sampling and reconstruction: evidence counts, determinism, re-posing (Eq. 2)."""

from decimal import Decimal, localcontext
from functools import cache

import numpy as np
from scipy.special import ndtri

from gmm_core import FitConfig, Grid, Mixture, Pose, ScanModel, fit_scan
from gmm_core.reconstruct import ReconstructionConfig, count_beams, reconstruct
from gmm_core.sampling import Z_MAX, draw, mixture_samples, samples_per_component, scan_rays, scan_seed


def wall_scan():
    """A 2D scan of a wall at x = 3 with a gap of no-return beams."""
    angles = np.linspace(-0.6, 0.6, 61)
    rays = np.column_stack([np.cos(angles), np.sin(angles)])
    hit = np.abs(angles) > 0.1
    hits = rays[hit] * (3.0 / rays[hit, 0])[:, None]
    return hits, rays[~hit]


def test_sample_weights_sum_to_the_support_whatever_the_resolution():
    hits, no_return = wall_scan()
    model = fit_scan(hits, no_return)
    for resolution in (0.2, 0.05, 0.01):
        ends, weights, is_hit = scan_rays(model, resolution, seed=3, samples_per_cell=2.0)
        assert np.isclose(weights[is_hit].sum(), len(hits))  # Eq. 10: N evidence in all
        assert np.isclose(weights[~is_hit].sum(), len(no_return))
    coarse = samples_per_component(model.occupied, 0.2, 1.0).sum()
    fine = samples_per_component(model.occupied, 0.01, 1.0).sum()
    assert fine > 5 * coarse


def test_same_seed_same_rays_and_stable_seeds():
    model = fit_scan(*wall_scan())
    a = scan_rays(model, 0.05, seed=scan_seed("robot1", 7), samples_per_cell=1.0)
    b = scan_rays(model, 0.05, seed=scan_seed("robot1", 7), samples_per_cell=1.0)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert scan_seed("robot1", 7) == scan_seed("robot1", 7) != scan_seed("robot1", 8)


def test_reconstruction_sees_the_wall_and_the_free_space():
    hits, no_return = wall_scan()
    model = fit_scan(hits, no_return, FitConfig(max_range=6.0))
    grid = Grid.from_bbox([-1.0, -3.0], [7.0, 3.0], 0.1)
    h, m = reconstruct(grid, [(model, Pose.identity(2), 0)], samples_per_cell=4)
    wall = h[:, 39:41].sum()  # columns x in [2.9, 3.1); arrays are [iy, ix]
    assert wall > 0.7 * len(hits)
    assert h[:, :38].sum() == 0 and m[:, 10:38].sum() > 0  # in front of the wall: misses only
    assert m[30, 45:55].sum() > 0  # through the gap, out to the no-return end points


def test_reposing_moves_the_map_exactly():
    # A pose correction re-poses the same samples: the map of a shifted scan is the shifted map.
    model = fit_scan(*wall_scan())
    grid = Grid.from_bbox([-2.0, -4.0], [8.0, 4.0], 0.1)
    h0, m0 = reconstruct(grid, [(model, Pose.identity(2), 5)])
    h1, m1 = reconstruct(grid, [(model, Pose.from_xytheta(1.0, 0.0, 0.0), 5)])
    assert np.allclose(h1[:, 10:], h0[:, :-10], atol=1e-4)
    assert np.allclose(m1[:, 12:-1], m0[:, 2:-11], atol=1e-4)


def test_the_default_samples_per_cell_is_the_reconstruction_sections():
    model = fit_scan(*wall_scan())
    grid = Grid.from_bbox([-1.0, -3.0], [7.0, 3.0], 0.1)
    scans = [(model, Pose.identity(2), 5)]
    configured = reconstruct(grid, scans, samples_per_cell=ReconstructionConfig().samples_per_cell)
    for default, expected in zip(reconstruct(grid, scans), configured):
        assert np.array_equal(default, expected)


def test_raw_counting_grid():
    hits, no_return = wall_scan()
    grid = Grid.from_bbox([-1.0, -3.0], [7.0, 3.0], 0.1)
    h, m = count_beams(grid, [(hits, no_return, Pose.identity(2))], max_range=5.0)
    assert h.sum() == len(hits)
    assert m[30, :].sum() > 0 and m[30, 61:].sum() == 0  # no-return beams stop at x = 5 m


def test_empty_model_and_far_scans_add_nothing():
    empty = ScanModel(Mixture.empty(2), Mixture.empty(2), np.zeros(2), 10.0)
    model = fit_scan(*wall_scan())
    grid = Grid.from_bbox([100.0, 100.0], [101.0, 101.0], 0.1)
    h, m = reconstruct(grid, [(empty, Pose.identity(2), 0), (model, Pose.identity(2), 1)])
    assert h.sum() == 0 and m.sum() == 0


@cache
def kronecker_alphas(dim: int) -> list[int]:
    """alpha_a = phi^-(a+1) of R_dim in 64-bit fixed point, phi the positive root of x^(dim+1) = x + 1
    solved here to 40 digits."""
    with localcontext() as context:
        context.prec = 40
        phi = Decimal(1.3)
        for _ in range(60):  # Newton on x^(dim+1) - x - 1
            phi -= (phi ** (dim + 1) - phi - 1) / ((dim + 1) * phi**dim - 1)
        return [int((1 / phi ** (a + 1)) % 1 * 2**64) for a in range(dim)]


def kronecker_normals(key: int, j: int, dim: int) -> np.ndarray:
    """The normals of sample j of stream `key`, in plain Python: point j of the Kronecker sequence
    R_dim (kronecker_alphas), shifted by splitmix64 output a of the stream; through scipy's normal
    quantile, clipped to +-Z_MAX."""
    mask = (1 << 64) - 1
    alphas = kronecker_alphas(dim)

    def splitmix(counter):
        x = (key + counter * 0x9E3779B97F4A7C15) & mask
        x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & mask
        x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & mask
        return x ^ (x >> 31)

    uniforms = [(((splitmix(a) + j * alphas[a]) & mask) >> 11) * 2.0**-53 + 2.0**-54 for a in range(dim)]
    return np.clip(ndtri(uniforms), -Z_MAX, Z_MAX)


def test_sample_placement_kernel_matches_numpy():
    """means[k] + chol[k] z from the numba kernel equals numpy's, with z from a plain-Python twin of
    the shifted Kronecker sequence (Acklam's quantile is within 1.2e-9 of scipy's), 2D and 3D."""
    rng = np.random.default_rng(4)
    for dim in (2, 3):
        k = 7
        a = rng.normal(size=(k, dim, dim))
        mixture = Mixture(np.full(k, 1 / k), rng.normal(size=(k, dim)), a @ a.transpose(0, 2, 1) + np.eye(dim), 50)
        counts = rng.integers(0, 9, k)
        key = np.uint64(0xDEADBEEF12345678)
        points, weights = draw(mixture_samples(mixture, counts, key))
        component = np.repeat(np.arange(k), counts)
        z = np.array([kronecker_normals(int(key), j, dim) for j in range(counts.sum())])
        chol = np.linalg.cholesky(mixture.covariances)
        assert np.allclose(
            points, mixture.means[component] + np.einsum("nij,nj->ni", chol[component], z), rtol=0, atol=1e-8
        )
        assert np.allclose(weights, (50 / k / np.maximum(counts, 1))[component], rtol=1e-6)
