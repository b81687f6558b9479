"""What the alternatives to the GMM messages would have sent for the same scans: raw scans,
occupancy-grid deltas and OctoMap deltas, per scan (render.MEASUREMENT_NOTES, "Bytes", says why
these and how each is counted). Replaying the beams also gives the cells each map snapshot had
observed, on which the maps are graded."""

from __future__ import annotations

import importlib.util
import itertools

import numpy as np
from numba import njit

from gmm_core import FitConfig, Grid
from gmm_core.reconstruct import count_beams
from services.datasets.common import RangeScan
from services.sim.fleet import SimulatedFleet

GRID_DELTA_CELL_BYTES = 5  # 4 B cell index + 1 B state
# Scans of a run whose OctoMap delta is built, by dimension (a 2D scan's tree takes about 12 ms, a
# 3D one of the mine's 28,800 beams 180-260 ms); the others repeat the last one built.
OCTOMAP_SAMPLES = {2: 2000, 3: 100}


def grid_state(hits: np.ndarray, misses: np.ndarray) -> np.ndarray:
    """0 unknown, 1 free, 2 occupied, as a counting grid decides."""
    return np.where(hits + misses == 0, 0, np.where(hits > misses, 2, 1)).astype(np.int8)


@njit(cache=True, inline="always")
def _cell_state(hits, misses):
    """grid_state of one cell."""
    return 0 if hits + misses == 0 else (2 if hits > misses else 1)


@njit(cache=True, nogil=True)
def add_scan_counts(hits, misses, first_seen, h, m, count, unseen) -> int:
    """Adds one scan's counts `h`, `m` to the counting grid `hits`, `misses` (all float32, of one
    window's shape), marks the cells it is the first to reach with `count` in `first_seen` (those
    still `unseen`), and returns how many cells changed state (grid_state): one pass over the window
    where numpy made a dozen (tests/unit/services/sim/test_byte_models.py compares them)."""
    changed = 0
    nz, ny, nx = h.shape
    for z in range(nz):
        for y in range(ny):
            for x in range(nx):
                dh, dm = h[z, y, x], m[z, y, x]
                if dh + dm > 0:
                    h0, m0 = hits[z, y, x], misses[z, y, x]
                    h1, m1 = h0 + dh, m0 + dm
                    hits[z, y, x], misses[z, y, x] = h1, m1
                    changed += _cell_state(h0, m0) != _cell_state(h1, m1)
                    if first_seen[z, y, x] == unseen:
                        first_seen[z, y, x] = count
    return changed


def scan_window(grid: Grid, scan: RangeScan, max_range: float):
    """(array slices, sub-grid) of `grid` around the scan's rays, or None when it misses the grid."""
    ends = scan.pose.apply(np.concatenate([scan.hits, scan.no_return * max_range]))
    points = np.vstack([ends, scan.pose.t[None]])
    first = np.clip(np.floor((points.min(axis=0) - grid.origin) / grid.resolution).astype(int), 0, grid.shape)
    last = np.clip(np.floor((points.max(axis=0) - grid.origin) / grid.resolution).astype(int) + 1, 0, grid.shape)
    if np.any(last <= first):
        return None
    window = tuple(slice(a, b) for a, b in zip(first[::-1], last[::-1]))
    return window, Grid(grid.origin + first * grid.resolution, grid.resolution, tuple(last - first))


def octomap_delta_bytes(scan: RangeScan, resolution: float) -> int:
    """Size of the `.bt` of a fresh OcTree holding this one scan's returns (2D: one layer)."""
    import octomap

    tree = octomap.OcTree(resolution)
    origin, points = scan.pose.t, scan.pose.apply(scan.hits)
    if len(origin) == 2:  # the mid-plane of the voxel layer above z = 0
        z = resolution / 2
        origin, points = np.append(origin, z), np.column_stack([points, np.full(len(points), z)])
    tree.insertPointCloud(np.ascontiguousarray(points), np.ascontiguousarray(origin))
    return len(tree.writeBinary())


def octomap_stride(scans: int, dim: int) -> int:
    """Every how many scans of a robot an OctoMap delta is built, in a run of `scans` scans in all
    in `dim` dimensions: a long run's are sampled, so that grading takes minutes however long the
    mission (render.MEASUREMENT_NOTES says so)."""
    return max(1, -(-scans // OCTOMAP_SAMPLES[dim]))


def replay_robot(
    fleet: SimulatedFleet, grid: Grid, update_every: int, index: int, scans: int, stride: int
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Robot `index`'s first `scans` scans, replayed: raw, grid-delta and OctoMap bytes per scan
    (OctoMap every `stride`-th scan, the last one repeated between; none without the [bench]
    extra), and per cell of `grid` how many of its scans had observed it when its beams first
    reached it (`never(scans)` where they never did): the cells observed after n scans are those
    at most n (observed_masks)."""
    with_octomap = importlib.util.find_spec("octomap") is not None
    dim, max_range = grid.dim, FitConfig().max_range
    hits, misses = np.zeros(grid.array_shape, np.float32), np.zeros(grid.array_shape, np.float32)
    unseen = never(scans)
    first_seen = np.full(grid.array_shape, unseen)
    sizes = {key: np.zeros(scans, np.int64) for key in ("raw", "grid", "octomap")}
    for k, scan in enumerate(itertools.islice(fleet.scans(index, update_every), scans)):
        beams = len(scan.hits) + len(scan.no_return)
        sizes["raw"][k] = 4 * beams * (1 if dim == 2 else 3)
        found = scan_window(grid, scan, max_range)
        if found is not None:
            window, sub = found
            h, m = count_beams(sub, [(scan.hits, scan.no_return, scan.pose)], max_range, threads=1)
            cells = [hits[window], misses[window], first_seen[window], h, m]  # views of the window
            changed = add_scan_counts(*(a[None] if dim == 2 else a for a in cells), k + 1, unseen)  # 2D: one layer
            sizes["grid"][k] = GRID_DELTA_CELL_BYTES * changed
        if with_octomap:
            sampled = k % stride == 0
            sizes["octomap"][k] = octomap_delta_bytes(scan, grid.resolution) if sampled else sizes["octomap"][k - 1]
    return (sizes if with_octomap else {key: v for key, v in sizes.items() if key != "octomap"}), first_seen


def never(scans: int) -> np.unsignedinteger:
    """replay_robot's first-seen count of a cell no beam of `scans` scans reached: the largest of
    the smallest unsigned type that holds it (2 bytes a cell up to 65,534 scans)."""
    dtype = np.uint16 if scans < np.iinfo(np.uint16).max else np.uint32
    return dtype(np.iinfo(dtype).max)


def observed_masks(grid: Grid, first_seen: dict[str, np.ndarray], stored_at: list[dict[str, int]]) -> list[np.ndarray]:
    """Per snapshot, the cells of `grid` the beams of the scans stored by then had observed: each
    robot's first `stored[robot]` scans (first_seen: replay_robot's, per robot)."""
    out = []
    for stored in stored_at:
        mask = np.zeros(grid.array_shape, bool)
        for robot, first in first_seen.items():
            if stored.get(robot, 0):
                mask |= first <= stored[robot]
        out.append(mask)
    return out
