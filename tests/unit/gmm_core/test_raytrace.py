"""The Amanatides-Woo kernel against a brute-force twin: every cell a segment crosses."""

import numpy as np
import pytest

from gmm_core import Grid, raytrace
from gmm_core.raytrace import trace_rays


def brute_force(grid, origins, ray_origin, ends, weights, is_hit):
    """Test every cell box against every segment (slab test); the end point's cell takes the hit."""
    centres = grid.cell_centers()
    lo_c, hi_c = centres - grid.resolution / 2, centres + grid.resolution / 2
    hits = np.zeros(grid.n_cells)
    misses = np.zeros(grid.n_cells)
    for r in range(len(ends)):
        o, e = origins[ray_origin[r]], ends[r]
        delta = e - o
        with np.errstate(divide="ignore", invalid="ignore"):
            ta, tb = (lo_c - o) / delta, (hi_c - o) / delta
        t0 = np.max(np.where(delta != 0, np.minimum(ta, tb), -np.inf), axis=1)
        t1 = np.min(np.where(delta != 0, np.maximum(ta, tb), np.inf), axis=1)
        crossed = np.maximum(t0, 0) < np.minimum(t1, 1)
        end_cell = np.all((e >= lo_c) & (e < hi_c), axis=1)
        if is_hit[r]:
            hits[end_cell] += weights[r]
            crossed &= ~end_cell
        misses[crossed] += weights[r]
    return hits.reshape(grid.array_shape), misses.reshape(grid.array_shape)


def random_rays(rng, dim, n_origins, n_rays, origin_span, end_span):
    """Weighted rays from origins in [-origin_span, origin_span]^dim to ends in [-end_span, end_span]^dim,
    70 % of them ending in a hit."""
    origins = rng.uniform(-origin_span, origin_span, (n_origins, dim))
    ray_origin = rng.integers(0, n_origins, n_rays)
    ends = rng.uniform(-end_span, end_span, (n_rays, dim))
    weights = rng.uniform(0.5, 2, n_rays)
    is_hit = rng.random(n_rays) < 0.7
    return origins, ray_origin, ends, weights, is_hit


@pytest.mark.parametrize("dim", [2, 3])
def test_matches_brute_force_on_random_rays(dim):
    rng = np.random.default_rng(dim)
    grid = Grid(np.full(dim, -2.0), 0.37, (11,) * dim if dim == 2 else (9, 8, 7))
    # Origins inside and outside the grid; ends inside, outside and beyond it.
    origins, ray_origin, ends, weights, is_hit = random_rays(rng, dim, 6, 400, 4, 5)
    fast = trace_rays(grid, origins, ray_origin, ends, weights, is_hit)
    slow = brute_force(grid, origins, ray_origin, ends, weights, is_hit)
    assert np.allclose(fast[0], slow[0], atol=1e-4)
    assert np.allclose(fast[1], slow[1], atol=1e-4)


def test_ray_inside_one_cell_and_axis_aligned_rays():
    grid = Grid(np.zeros(2), 1.0, (4, 3))
    origins = np.array([[0.5, 0.5]])
    ends = np.array([[0.7, 0.6], [3.5, 0.5], [0.5, 2.5]])
    hits, misses = trace_rays(grid, origins, np.zeros(3, int), ends, np.ones(3), np.ones(3, bool))
    assert hits[0, 0] == 1 and hits[0, 3] == 1 and hits[2, 0] == 1
    assert misses[0, 0] == 2 and misses[0, 1] == 1 and misses[0, 2] == 1 and misses[1, 0] == 1
    assert hits.sum() == 3 and misses.sum() == 5


def test_free_rays_add_only_misses_and_counts_are_additive():
    rng = np.random.default_rng(5)
    grid = Grid(np.array([-3.0, -3.0, -1.0]), 0.25, (24, 24, 8))
    ends = rng.uniform(-3, 3, (300, 3))
    args = (np.zeros((1, 3)), np.zeros(300, int), ends, np.ones(300))
    free_hits, free_misses = trace_rays(grid, *args, np.zeros(300, bool))
    assert free_hits.sum() == 0
    a = trace_rays(grid, args[0], args[1][:100], ends[:100], args[3][:100], np.ones(100, bool))
    b = trace_rays(grid, args[0], args[1][100:], ends[100:], args[3][100:], np.ones(200, bool))
    whole = trace_rays(grid, *args, np.ones(300, bool))
    assert np.allclose(a[0] + b[0], whole[0]) and np.allclose(a[1] + b[1], whole[1])


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("n_chunks", [1, 3])
def test_rays_that_miss_the_grid_add_nothing(dim, n_chunks):
    # A ray that misses runs on as a ray of weight 0 into the first cell a chunk holds (one exit
    # for numba's reference counts): neither that cell nor any other may gain anything from it,
    # on a grid small enough to trace in place and on one whose chunks fill slab buffers.
    rng = np.random.default_rng(20 + dim)
    for side in (9, int(raytrace.SORT_MIN_CELLS ** (1 / dim)) + 1):
        grid = Grid(np.zeros(dim), 1.0 / side, (side,) * dim)
        origins = rng.uniform(2.0, 3.0, (3, dim))  # every ray stays in [2, 4]^dim, beside the grid
        ends = rng.uniform(2.0, 4.0, (200, dim))
        is_hit = rng.random(200) < 0.5
        hits, misses = chunked(grid, origins, rng.integers(0, 3, 200), ends, np.ones(200), is_hit, n_chunks)
        assert not hits.any() and not misses.any()


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("big", [False, True], ids=["in-cache", "sorted"])
def test_chunks_match_brute_force_and_each_other(dim, big):
    """Chunked tracing (one per numba thread) on small grids and on grids big enough that rays are
    sorted by end block and chunks fill slab buffers: brute-force counts for any chunk count."""
    rng = np.random.default_rng(10 + dim)
    side = raytrace.SORT_MIN_CELLS ** (1 / dim) + 1 if big else 9
    grid = Grid(np.full(dim, -2.0), 4.0 / side, (int(side),) * dim)
    assert (grid.n_cells >= raytrace.SORT_MIN_CELLS) == big
    origins, ray_origin, ends, weights, is_hit = random_rays(rng, dim, 4, 300, 3, 3)
    slow = brute_force(grid, origins, ray_origin, ends, weights, is_hit)
    counts = [chunked(grid, origins, ray_origin, ends, weights, is_hit, n) for n in (1, 2, 3, 7)]
    for hits, misses in counts:
        assert np.allclose(hits, slow[0], atol=1e-4) and np.allclose(misses, slow[1], atol=1e-4)
        assert np.allclose(hits, counts[0][0], rtol=1e-7) and np.allclose(misses, counts[0][1], rtol=1e-7)
    again = chunked(grid, origins, ray_origin, ends, weights, is_hit, 3)
    assert np.array_equal(again[0], counts[2][0]) and np.array_equal(again[1], counts[2][1])
    serial = trace_rays(grid, origins, ray_origin, ends, weights, is_hit, threads=1)  # no threading layer
    assert np.array_equal(serial[0], counts[0][0]) and np.array_equal(serial[1], counts[0][1])


def test_a_grid_beyond_32_bit_cell_numbers_is_refused():
    grid = Grid(np.zeros(3), 0.1, (2048, 2048, 512))  # 2^31 cells: none is allocated before the check
    assert grid.n_cells == raytrace.MAX_CELLS + 1
    with pytest.raises(ValueError, match="grid: 2147483648 cells"):
        trace_rays(grid, np.zeros((1, 3)), np.zeros(1, int), np.ones((1, 3)), np.ones(1), np.ones(1, bool))


def chunked(grid, origins, ray_origin, ends, weights, is_hit, n_chunks):
    """`trace_rays` with the rays split into n_chunks, whatever the machine's thread count."""
    d = grid.dim
    z = grid.resolution / 2
    dims = np.array(list(grid.shape) + [1] * (3 - d))
    hits, misses = raytrace._counts(
        raytrace._as_3d(origins, d, z),
        ray_origin,
        raytrace._as_3d(ends, d, z),
        weights,
        is_hit,
        raytrace._as_3d(grid.origin, d, 0.0)[0],
        grid.resolution,
        dims,
        n_chunks,
    )
    return hits.reshape(grid.array_shape), misses.reshape(grid.array_shape)
