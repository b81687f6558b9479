"""Simulated worlds, sensors, paths and odometry: ground truth consistent with the beams, and offline maps."""

import heapq

import numpy as np
import pytest

from gmm_core import FitConfig, Grid, fit_scan
from gmm_core.metrics import auroc
from gmm_core.occupancy import map_estimate
from gmm_core.reconstruct import count_beams, reconstruct
from gmm_core.sampling import scan_seed
from services.sim.sensor import Laser2D, Lidar3D, beam_directions, sensor_for, simulate_scan
from services.sim.trajectory import (
    ClosureSchedule,
    Motion,
    OdometryNoise,
    _astar,
    _offsets,
    odometry,
    path_pose,
    plan_paths,
    robot_events,
)
from services.sim.worlds import World, _carve_capsule, make_world


@pytest.fixture(scope="module")
def worlds():
    return {name: make_world(name, seed=0) for name in ("office", "warehouse", "mine")}


def random_world(dim: int, seed: int) -> World:
    rng = np.random.default_rng(seed)
    raster = Grid(rng.uniform(-1, 1, dim), 0.25, (13, 11) if dim == 2 else (9, 8, 7))
    return World("random", raster, rng.random(raster.array_shape) < 0.15)


# --- references ----------------------------------------------------------------------------------


def cast_reference(world: World, origin, directions, max_range):
    """Slab test of every ray against every solid cell box; the raster's boundary counts as solid."""
    res = world.raster.resolution
    lo = world.raster.cell_centers()[world.solid.ravel()] - res / 2
    hi = lo + res
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo[None] - origin) / directions[:, None], (hi[None] - origin) / directions[:, None]
        enter = np.where(directions[:, None] != 0, np.minimum(ta, tb), -np.inf).max(axis=2)
        leave = np.where(directions[:, None] != 0, np.maximum(ta, tb), np.inf).min(axis=2)
        exit_raster = np.where(
            directions != 0,
            np.maximum((world.raster.origin - origin) / directions, (world.raster.upper - origin) / directions),
            np.inf,
        )
    first = np.where((leave > enter) & (leave > 0), np.maximum(enter, 0), np.inf).min(axis=1)
    ranges = np.minimum(first, exit_raster.min(axis=1))
    return np.where(ranges <= max_range, ranges, np.inf)


def solid_near_reference(world: World, grid: Grid, margin: float):
    """A query box overlaps a solid cell with positive area/volume, or reaches outside the raster."""
    res = world.raster.resolution
    lo = world.raster.cell_centers()[world.solid.ravel()] - res / 2
    box_lo = grid.cell_centers() - grid.resolution / 2 - margin
    box_hi = box_lo + grid.resolution + 2 * margin
    overlaps = ((box_lo[:, None] < lo[None] + res - 1e-9) & (lo[None] < box_hi[:, None] - 1e-9)).all(axis=2).any(axis=1)
    outside = ((box_lo < world.raster.origin - 1e-9) | (box_hi > world.raster.upper + 1e-9)).any(axis=1)
    return (overlaps | outside).reshape(grid.array_shape)


def carve_capsule_reference(solid, raster: Grid, p, q, radius: float, octaves) -> None:
    """The rough capsule in whole numpy arrays over its box (the noise of every voxel at once)."""

    def value_noise(lattice, spacing, x, y, z):
        u = [np.asarray(c) / spacing for c in (x, y, z)]
        i = [np.floor(c).astype(np.int64) for c in u]
        f = [(c - k) * (c - k) * (3 - 2 * (c - k)) for c, k in zip(u, i)]
        out = 0.0
        for cx in (0, 1):
            for cy in (0, 1):
                for cz in (0, 1):
                    w = (f[0] if cx else 1 - f[0]) * (f[1] if cy else 1 - f[1]) * (f[2] if cz else 1 - f[2])
                    out = out + w * lattice[i[0] + cx, i[1] + cy, i[2] + cz]
        return out

    reach = radius + sum(amplitude for _, amplitude, _ in octaves)
    lo = np.maximum(np.floor((np.minimum(p, q) - reach) / raster.resolution).astype(int), 0)
    hi = np.minimum(np.ceil((np.maximum(p, q) + reach) / raster.resolution).astype(int), raster.shape)
    x, y, z = (raster.origin[a] + (np.arange(lo[a], hi[a]) + 0.5) * raster.resolution for a in range(3))
    x, y, z = x[None, None, :], y[None, :, None], z[:, None, None]
    axis = q - p
    t = np.clip(((x - p[0]) * axis[0] + (y - p[1]) * axis[1] + (z - p[2]) * axis[2]) / axis.dot(axis), 0, 1)
    dx, dy, dz = x - (p[0] + t * axis[0]), y - (p[1] + t * axis[1]), z - (p[2] + t * axis[2])
    rough = sum(amplitude * value_noise(lattice, spacing, x, y, z) for spacing, amplitude, lattice in octaves)
    free = (dx * dx + dy * dy + dz * dz < (radius + rough) ** 2) & (dz > -0.7 * radius + 0.3 * rough)
    solid[lo[2] : hi[2], lo[1] : hi[1], lo[0] : hi[0]] &= ~free


def dijkstra_cost(free, start, goal, offsets):
    shape = free.shape
    best = {start: 0.0}
    heap = [(0.0, start)]
    while heap:
        c, cell = heapq.heappop(heap)
        if cell == goal:
            return c
        if c > best[cell]:
            continue
        for off in offsets:
            n = tuple(np.add(np.unravel_index(cell, shape), off))
            if all(0 <= n[a] < shape[a] for a in range(3)) and free[n]:
                flat = int(np.ravel_multi_index(n, shape))
                g = c + float(np.linalg.norm(off))
                if g < best.get(flat, np.inf):
                    best[flat] = g
                    heapq.heappush(heap, (g, flat))
    return np.inf


# --- kernels against their twins ------------------------------------------------------------------


@pytest.mark.parametrize("dim", [2, 3])
def test_cast_matches_the_slab_reference(dim):
    world = random_world(dim, dim)
    rng = np.random.default_rng(7)
    for origin in world.sample_free(rng, 5, clearance=0.0, cell=0.05):
        directions = rng.normal(size=(200, dim))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        fast = world.cast(origin, directions, max_range=2.0)
        slow = cast_reference(world, origin, directions, 2.0)
        assert np.array_equal(np.isinf(fast), np.isinf(slow))
        assert np.allclose(fast[np.isfinite(fast)], slow[np.isfinite(slow)], atol=1e-9)


def test_carved_capsules_match_the_numpy_reference_voxel_for_voxel():
    """The mine's tunnels, carved voxel by voxel, are the ones numpy's arrays carved (bit for bit:
    the same operations in the same order), also where a capsule reaches past the raster."""
    rng = np.random.default_rng(3)
    raster = Grid(np.zeros(3), 0.1, (40, 30, 20))
    size = np.array(raster.shape) * raster.resolution
    octaves = [
        (1.0, 0.25, rng.uniform(-1, 1, size=tuple((size / 1.0).astype(int) + 2))),
        (0.35, 0.08, rng.uniform(-1, 1, size=tuple((size / 0.35).astype(int) + 2))),
    ]
    fast, slow = np.ones(raster.array_shape, dtype=bool), np.ones(raster.array_shape, dtype=bool)
    for _ in range(6):
        p, q = rng.uniform(-0.5, 1.0, 3) * size, rng.uniform(0.0, 1.2, 3) * size
        radius = rng.uniform(0.3, 1.0)
        _carve_capsule(fast, raster, p, q, radius, octaves)
        carve_capsule_reference(slow, raster, p, q, radius, octaves)
    assert 0 < (~fast).sum() < fast.size
    assert np.array_equal(fast, slow)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("margin", [0.0, 0.3])
def test_solid_near_matches_the_overlap_reference(dim, margin):
    world = random_world(dim, 10 + dim)
    for resolution, shift in ((0.25, 0.0), (0.37, 0.113), (0.1, -0.05)):
        grid = Grid(
            world.raster.origin + shift - 0.2,
            resolution,
            tuple(np.asarray(world.raster.shape) * 0.25 // resolution + 3),
        )
        assert np.array_equal(world.solid_near(grid, margin), solid_near_reference(world, grid, margin))


@pytest.mark.parametrize("dim", [2, 3])
def test_astar_finds_a_shortest_path(dim):
    rng = np.random.default_rng(dim)
    free = rng.random((1, 30, 30) if dim == 2 else (8, 10, 12)) > 0.25
    offsets = _offsets(dim)
    cells = np.flatnonzero(free.ravel())
    for start, goal in rng.choice(cells, (10, 2)):
        path = _astar(free, start, goal, offsets)
        expected = dijkstra_cost(free, int(start), int(goal), offsets)
        if np.isinf(expected):
            assert len(path) == 0
            continue
        zyx = np.stack(np.unravel_index(path, free.shape), axis=1)
        assert path[0] == start and path[-1] == goal and free.ravel()[path].all()
        assert np.abs(np.diff(zyx, axis=0)).max() <= 1
        assert np.linalg.norm(np.diff(zyx, axis=0), axis=1).sum() == pytest.approx(expected)


# --- worlds and sensors ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["office", "warehouse", "mine"])
def test_a_beam_ends_where_the_world_says(worlds, name):
    world = worlds[name]
    sensor = sensor_for(world)
    rng = np.random.default_rng(1)
    directions = beam_directions(sensor)
    for origin in world.sample_free(rng, 3, clearance=0.3):
        ranges = world.cast(origin, directions, sensor.max_range)
        hit = np.isfinite(ranges)
        assert hit.mean() > 0.95  # closed worlds: only beams longer than the sensor's range miss
        r, d = ranges[hit, None], directions[hit]
        assert not world.occupied(origin + (r - 0.01) * d).any()
        assert world.occupied(origin + (r + 1e-6) * d).all()
        # 2 cm into the wall, except where a beam clips a corner and leaves the solid again: rare
        # on straight walls, 1-2 % of lidar beams on the mine's rough voxel walls (staircases)
        assert world.occupied(origin + (r + 0.02) * d).mean() > (0.99 if world.dim == 2 else 0.97)
        # ground truth on a fine grid, not aligned with the raster, marks every hit cell occupied
        inside = origin + (r + 1e-6) * d
        grid = Grid.from_bbox(inside.min(axis=0) - 0.013, inside.max(axis=0) + 0.1, 0.05 if world.dim == 2 else 0.07)
        cell = np.floor((inside - grid.origin) / grid.resolution).astype(int)
        assert world.ground_truth(grid)[tuple(cell[:, ::-1].T)].all()


def test_ground_truth_at_the_raster_resolution_is_the_raster(worlds):
    world = worlds["office"]
    assert np.array_equal(world.ground_truth(world.raster), world.solid)


def test_scans_have_the_sensors_shape(worlds):
    rng = np.random.default_rng(2)
    office, mine = worlds["office"], worlds["mine"]
    pose2 = path_pose(np.r_[office.sample_free(rng, 1, 0.3)[0], 0.3])
    scan2 = simulate_scan(office, Laser2D(), pose2, rng, index=4, stamp=0.8)
    assert len(scan2.hits) + len(scan2.no_return) == 360 and scan2.index == 4
    pose3 = path_pose(np.r_[mine.sample_free(rng, 1, 0.5)[0], 1.0])
    scan3 = simulate_scan(mine, Lidar3D(), pose3, rng)
    assert len(scan3.hits) + len(scan3.no_return) == 16 * 1800
    assert len(scan3.hits) > 0.95 * 16 * 1800
    elevation = np.degrees(np.arcsin(scan3.hits[:, 2] / np.linalg.norm(scan3.hits, axis=1)))
    assert np.abs(elevation).max() == pytest.approx(15.0, abs=0.1)
    # Range noise: the hits lie about 2 cm from the exact surface.
    exact = mine.cast(pose3.t, beam_directions(Lidar3D()) @ pose3.R.T, 100.0)
    error = np.linalg.norm(scan3.hits, axis=1) - exact[np.isfinite(exact)]
    assert np.std(error) == pytest.approx(0.02, rel=0.1)


def test_same_seed_same_world_and_paths(worlds):
    again = make_world("office", seed=0)
    assert np.array_equal(again.solid, worlds["office"].solid)
    assert not np.array_equal(make_world("office", seed=1).solid, again.solid)
    a = plan_paths(again, 2, 100, seed=3)
    b = plan_paths(worlds["office"], 2, 100, seed=3)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))


# --- paths, odometry, events ----------------------------------------------------------------------


@pytest.mark.parametrize("name", ["office", "warehouse", "mine"])
def test_paths_keep_their_clearance(worlds, name):
    world = worlds[name]
    motion = Motion(speed=1.0, rate=5.0, clearance=0.3)
    paths = plan_paths(world, 3, 400, seed=0, motion=motion)
    rng = np.random.default_rng(0)
    ring = rng.normal(size=(64, world.dim))
    ring *= motion.clearance / np.linalg.norm(ring, axis=1, keepdims=True)
    for path in paths:
        assert path.shape == (400, world.dim + 1)
        position = path[:, :-1]
        step = np.linalg.norm(np.diff(position, axis=0), axis=1)
        assert step.max() <= 0.2 + 1e-9 and np.median(step) == pytest.approx(0.2)
        between = position[:-1, None] + np.linspace(0, 1, 5)[None, :, None] * np.diff(position, axis=0)[:, None]
        around = between.reshape(-1, 1, world.dim) + np.concatenate([np.zeros((1, world.dim)), ring])[None]
        assert not world.occupied(around.reshape(-1, world.dim)).any()
    assert min(np.linalg.norm(a[0, :-1] - b[0, :-1]) for i, a in enumerate(paths) for b in paths[i + 1 :]) > 1.0


def test_odometry_drift_grows_with_distance(worlds):
    path = plan_paths(worlds["office"], 1, 600, seed=1)[0]
    errors = np.array(
        [
            np.linalg.norm(odometry(path, OdometryNoise(), np.random.default_rng(s))[:, :2] - path[:, :2], axis=1)
            for s in range(30)
        ]
    )
    assert np.all(errors[:, 0] == 0)
    rms = np.sqrt((errors**2).mean(axis=0))
    assert 0 < rms[50] < rms[200] < rms[599]
    assert 0.05 < rms[599] < 0.05 * 120  # after 120 m: off, but by less than 5 % of the distance


def test_a_fleets_closures_spread_over_the_interval_unless_asked_to_land_at_once():
    every, robots = 100, 20
    spread = [ClosureSchedule.of_robot(i, robots, every) for i in range(robots)]
    after = [[n for n in range(1, 301) if s.closes_after(n)] for s in spread]
    assert after[0] == [100, 200, 300] and after[1] == [95, 195, 295] and after[19] == [5, 105, 205]
    assert len({a[0] for a in after}) == robots  # no two robots close at the same scan
    assert [spread[1].revision(n) for n in (94, 95, 195)] == [0, 1, 2]
    together = {ClosureSchedule.of_robot(i, robots, every, spread=False) for i in range(robots)}
    assert together == {ClosureSchedule(every)}
    assert not any(ClosureSchedule.of_robot(3, robots, 0).closes_after(n) for n in range(1, 300))


def test_events_publish_estimates_and_corrections(worlds):
    world = worlds["office"]
    path = plan_paths(world, 1, 25, seed=2)[0]
    odom = odometry(path, OdometryNoise(heading_walk=0.05), np.random.default_rng(0))
    events = list(robot_events(world, Laser2D(), path, odom, rate=5.0, closures=ClosureSchedule(10), seed=0))
    kinds = [e[0] for e in events]
    assert kinds.count("scan") == 25 and kinds.count("correction") == 2
    assert kinds.index("correction") == 10
    scans = [e[1] for e in events if e[0] == "scan"]
    assert [s.index for s in scans] == list(range(25)) and scans[5].stamp == pytest.approx(1.0)
    revision, poses = events[10][1], events[10][2]
    assert revision == 1 and [node for node, _ in poses] == list(range(10))
    assert all(np.allclose(pose.t, scans[node].pose.t) for node, pose in poses)
    # Before a correction the estimate drifts; right after it restarts from the corrected pose.
    drift = [np.linalg.norm(s.odom_pose.t - s.pose.t) for s in scans]
    assert drift[0] == 0 and drift[9] > 0 and drift[10] < drift[9]


# --- offline maps against ground truth --------------------------------------------------------------


def map_auroc(world, scans, models, resolution, raw_range):
    """AUROC of the GMM map against ground truth on the cells the raw beams observed."""
    points = np.concatenate([s.pose.apply(s.hits) for s in scans])
    grid = Grid.from_bbox(points.min(axis=0) - 0.5, points.max(axis=0) + 0.5, resolution)
    raw_hits, raw_misses = count_beams(grid, [(s.hits, s.no_return, s.pose) for s in scans], raw_range)
    observed = (raw_hits + raw_misses) > 0
    hits, misses = reconstruct(
        grid, [(m, s.pose, scan_seed(0, s.index)) for m, s in zip(models, scans)], samples_per_cell=4.0
    )
    return auroc(map_estimate(hits, misses)[observed], world.ground_truth(grid)[observed])


@pytest.mark.parametrize("name, n_scans, rate, minimum", [("office", 60, 5.0, 0.9), ("mine", 3, 1.0, 0.85)])
def test_offline_map_from_true_poses_matches_ground_truth(worlds, name, n_scans, rate, minimum):
    world = worlds[name]
    sensor = sensor_for(world)
    path = plan_paths(world, 1, n_scans, seed=0, motion=Motion(rate=rate))[0]
    rng = np.random.default_rng(0)
    scans = [simulate_scan(world, sensor, path_pose(row), rng, index=k) for k, row in enumerate(path)]
    config = FitConfig().for_dimension(world.dim)
    models = [fit_scan(s.hits, s.no_return, config) for s in scans]
    assert map_auroc(world, scans, models, 0.1, config.max_range) >= minimum
