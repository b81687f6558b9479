"""The fused counting-grid update of the beam replay equals the plain numpy steps it replaces."""

import numpy as np
import pytest

from services.sim.byte_models import OCTOMAP_SAMPLES, add_scan_counts, grid_state, octomap_stride


def numpy_reference(hits, misses, first_seen, h, m, count, unseen):
    """The replay's update as numpy does it: the touched cells' states before and after."""
    touched = (h + m) > 0  # the only cells whose state the scan may change
    before = grid_state(hits[touched], misses[touched])
    hits += h
    misses += m
    changed = grid_state(hits[touched], misses[touched]) != before
    first_seen[touched & (first_seen == unseen)] = count
    return int(np.count_nonzero(changed))


@pytest.mark.parametrize("seed", range(4))
def test_add_scan_counts_equals_numpy_on_random_windows(seed):
    rng = np.random.default_rng(seed)
    shape = (9, 23, 31)
    counts = lambda: np.where(rng.random(shape) < 0.6, 0, rng.integers(1, 4, shape)).astype(np.float32)  # noqa: E731
    unseen = np.uint16(65535)
    grid = [counts(), counts(), np.where(rng.random(shape) < 0.5, unseen, 3).astype(np.uint16)]
    expected = [a.copy() for a in grid]
    window = (slice(2, 8), slice(5, 20), slice(1, 30, 2))  # a strided view, as a scan's window of the grid
    for count in (4, 5, 6):
        h, m = counts()[window], counts()[window]
        want = numpy_reference(*(a[window] for a in expected), h, m, count, unseen)
        got = add_scan_counts(
            *(a[window] for a in grid), np.ascontiguousarray(h), np.ascontiguousarray(m), count, unseen
        )
        assert got == want > 0
        for a, b in zip(grid, expected, strict=True):
            assert np.array_equal(a, b)
    # A 2D grid passes its window as one layer
    plane, expected_plane = [a[0].copy() for a in grid], [a[0].copy() for a in grid]
    h, m = counts()[0], counts()[0]
    want = numpy_reference(*expected_plane, h, m, 7, unseen)
    assert add_scan_counts(*(a[None] for a in plane), h[None], m[None], 7, unseen) == want > 0
    for a, b in zip(plane, expected_plane, strict=True):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("dim", [2, 3])
def test_octomap_stride_builds_at_most_the_samples_of_the_dimension(dim):
    for scans in (1, 100, 300, 2000, 4001, 180_000):
        stride = octomap_stride(scans, dim)
        built = -(-scans // stride)  # scans k with k % stride == 0
        assert built <= OCTOMAP_SAMPLES[dim]
        assert stride == 1 or -(-scans // (stride - 1)) > OCTOMAP_SAMPLES[dim]  # no sparser than needed
