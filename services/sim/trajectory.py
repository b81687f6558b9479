"""Robot paths through free space, drifting odometry, and the scan / loop-closure event stream.

Paths: each robot repeatedly picks, among random reachable cells, the one farthest from where
the fleet has already been, and drives there along an A* path (8- or 26-connected) on a coarse
grid of cells at least `clearance` from any solid, shortened by line-of-sight shortcuts that
stay in such cells. So every point of a path keeps the clearance. Poses are sampled at
`speed / rate` spacing; heading follows the direction of travel.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numba import njit

from gmm_core.pose import Pose
from services.sim.sensor import Sensor, simulate_scan
from services.sim.worlds import World, planning_cell


@dataclass(frozen=True)
class Motion:
    speed: float = 1.0  # m/s
    rate: float = 5.0  # scans per second
    clearance: float = 0.3  # m between the sensor and any solid
    candidates: int = 64  # random cells considered for each next goal

    def __post_init__(self):
        if not (self.speed > 0 and self.rate > 0 and self.clearance >= 0 and self.candidates >= 1):
            raise ValueError(f"motion: speed and rate must be positive, clearance non-negative, got {self}")


@dataclass(frozen=True)
class OdometryNoise:
    """Odometry error: a per-robot distance scale error plus a random walk in position and heading.

    The walk's std grows as the square root of the distance travelled: after D metres the heading
    is off by about heading_walk * sqrt(D), which bends the integrated path by roughly
    D * heading_walk * sqrt(D / 3); the scale error adds scale_bias * D along the way.
    """

    scale_bias: float = 0.01  # std of the distance scale error (fraction of distance)
    translation_walk: float = 0.01  # m per sqrt(m), per axis
    heading_walk: float = float(np.radians(0.25))  # rad per sqrt(m)


# --- grid search kernels (grids are (nz, ny, nx); a 2D grid has nz = 1) ------------------------


@njit(cache=True)
def _label_components(free, offsets):
    """Connected components of free cells (breadth-first search); 0 on solid, 1.. on free."""
    nz, ny, nx = free.shape
    labels = np.zeros(free.size, np.int32)
    flat_free = free.ravel()
    queue = np.empty(free.size, np.int64)
    label = 0
    for seed in range(free.size):
        if not flat_free[seed] or labels[seed]:
            continue
        label += 1
        labels[seed] = label
        head, tail = 0, 1
        queue[0] = seed
        while head < tail:
            c = queue[head]
            head += 1
            z, y, x = c // (ny * nx), (c // nx) % ny, c % nx
            for k in range(offsets.shape[0]):
                zz, yy, xx = z + offsets[k, 0], y + offsets[k, 1], x + offsets[k, 2]
                if 0 <= zz < nz and 0 <= yy < ny and 0 <= xx < nx:
                    n = (zz * ny + yy) * nx + xx
                    if flat_free[n] and not labels[n]:
                        labels[n] = label
                        queue[tail] = n
                        tail += 1
    return labels.reshape(free.shape)


@njit(cache=True)
def _astar(free, start, goal, offsets):
    """Shortest path of free cells (flat indices) from start to goal; empty when unreachable."""
    nz, ny, nx = free.shape
    flat_free = free.ravel()
    cost = np.full(free.size, np.inf)
    parent = np.full(free.size, -1, np.int64)
    done = np.zeros(free.size, np.bool_)
    step = np.sqrt((offsets * offsets).sum(axis=1).astype(np.float64))
    gz, gy, gx = goal // (ny * nx), (goal // nx) % ny, goal % nx
    cost[start] = 0.0
    heap = [(0.0, start)]
    while heap:
        _, c = heapq.heappop(heap)
        if done[c]:
            continue
        if c == goal:
            break
        done[c] = True
        z, y, x = c // (ny * nx), (c // nx) % ny, c % nx
        for k in range(offsets.shape[0]):
            zz, yy, xx = z + offsets[k, 0], y + offsets[k, 1], x + offsets[k, 2]
            if 0 <= zz < nz and 0 <= yy < ny and 0 <= xx < nx:
                n = (zz * ny + yy) * nx + xx
                g = cost[c] + step[k]
                if flat_free[n] and g < cost[n]:
                    cost[n] = g
                    parent[n] = c
                    h = np.sqrt(float((zz - gz) ** 2 + (yy - gy) ** 2 + (xx - gx) ** 2))
                    heapq.heappush(heap, (g + h, n))
    if cost[goal] == np.inf:
        return np.empty(0, np.int64)
    path = [goal]
    while path[-1] != start:
        path.append(parent[path[-1]])
    return np.array(path[::-1], dtype=np.int64)


@njit(cache=True)
def _segment_free(free, a, b):
    """Whether every cell the segment between cell centres a and b (z, y, x) passes through is free."""
    nz, ny, nx = free.shape
    cell = a.copy()
    sign = np.zeros(3, np.int64)
    t_next = np.full(3, np.inf)
    t_delta = np.full(3, np.inf)
    for i in range(3):
        d = b[i] - a[i]
        if d != 0:
            sign[i] = 1 if d > 0 else -1
            t_delta[i] = 1.0 / abs(d)
            t_next[i] = 0.5 * t_delta[i]
    while True:
        if not free[cell[0], cell[1], cell[2]]:
            return False
        i = np.argmin(t_next)
        if t_next[i] >= 1.0:
            return True
        cell[i] += sign[i]
        t_next[i] += t_delta[i]


@njit(cache=True)
def _shortcut(free, cells):
    """Indices of the cells of a path kept as corners: each reaches as far ahead as it sees."""
    keep = [0]
    i = 0
    while i < cells.shape[0] - 1:
        j = i + 1
        while j + 1 < cells.shape[0] and _segment_free(free, cells[i], cells[j + 1]):
            j += 1
        keep.append(j)
        i = j
    return np.array(keep, dtype=np.int64)


def _offsets(dim: int) -> np.ndarray:
    """Neighbour steps (dz, dy, dx): 8 in 2D, 26 in 3D."""
    dz = (-1, 0, 1) if dim == 3 else (0,)
    steps = [(z, y, x) for z in dz for y in (-1, 0, 1) for x in (-1, 0, 1) if (z, y, x) != (0, 0, 0)]
    return np.array(steps, dtype=np.int64)


# --- paths -------------------------------------------------------------------------------------


def plan_paths(world: World, robots: int, scans: int, seed: int = 0, motion: Motion = Motion()) -> list[np.ndarray]:
    """True poses of each robot: (scans, 3) rows x, y, yaw in 2D; (scans, 4) x, y, z, yaw in 3D.

    All robots share the largest connected region of free space, and each goes where the
    robots before it have not been.
    """
    if robots < 1 or scans < 1:
        raise ValueError(f"robots and scans must be at least 1, got {robots}, {scans}")
    grid, free = world.free_cells(planning_cell(world.dim), motion.clearance)
    free = free if world.dim == 3 else free[None]
    offsets = _offsets(world.dim)
    labels = _label_components(free, offsets)
    if labels.max() == 0:
        raise ValueError(f"{world.name}: no free space with clearance {motion.clearance} m")
    region = np.flatnonzero(labels.ravel() == np.argmax(np.bincount(labels.ravel())[1:]) + 1)
    if len(region) < 2:
        raise ValueError(f"{world.name}: free space with clearance {motion.clearance} m is a single cell")
    rng = np.random.default_rng([seed, 5])
    visited = np.empty((0, world.dim))
    paths = []
    for _ in range(robots):
        path = _explore(free, grid.origin, grid.resolution, region, offsets, rng, scans, motion, visited)
        visited = np.concatenate([visited, path[:, : world.dim]])
        paths.append(path)
    return paths


def _explore(free, origin, cell, region, offsets, rng, scans, motion, visited) -> np.ndarray:
    """One robot's poses: legs to the candidate cell farthest from everything seen so far."""
    dim = len(origin)

    def centre(flat):
        zyx = np.stack(np.unravel_index(flat, free.shape), axis=-1)
        return origin + (zyx[..., ::-1][..., :dim] + 0.5) * cell

    def farthest(seen):
        options = rng.choice(region, motion.candidates)
        if len(seen) == 0:
            return options[0]
        pts = centre(options)
        gap = np.min(np.linalg.norm(pts[:, None] - seen[None, :: max(1, len(seen) // 500)], axis=-1), axis=1)
        return options[np.argmax(gap)]

    here = farthest(visited)
    rows, offset, yaw = [], 0.0, rng.uniform(-np.pi, np.pi)
    while sum(len(r) for r in rows) < scans:
        goal = farthest(np.concatenate([visited] + [r[:, :dim] for r in rows]))
        cells = _astar(free, here, goal, offsets)
        if len(cells) < 2:
            continue
        zyx = np.stack(np.unravel_index(cells, free.shape), axis=1)
        corners = centre(cells[_shortcut(free, zyx)])
        leg, offset, yaw = _sample_polyline(corners, motion.speed / motion.rate, offset, yaw)
        rows.append(leg)
        here = goal
    return np.concatenate(rows)[:scans]


def _sample_polyline(corners: np.ndarray, spacing: float, offset: float, yaw: float):
    """Poses every `spacing` metres from `offset` along the polyline; the next leg's offset; last yaw."""
    segment = np.diff(corners, axis=0)
    length = np.linalg.norm(segment, axis=1)
    ends = np.cumsum(length)
    s = np.arange(offset, ends[-1] + 1e-12, spacing)
    k = np.minimum(np.searchsorted(ends, s, side="right"), len(segment) - 1)
    points = corners[k] + segment[k] * ((s - (ends[k] - length[k])) / length[k])[:, None]
    heading = np.arctan2(segment[:, 1], segment[:, 0])
    for i in range(len(heading)):  # a vertical segment (3D) keeps the heading it had
        if np.hypot(segment[i, 0], segment[i, 1]) < 1e-9:
            heading[i] = heading[i - 1] if i else yaw
    yaws = heading[k]
    next_offset = (s[-1] + spacing - ends[-1]) if len(s) else offset - ends[-1]
    return np.column_stack([points, yaws]), next_offset, float(yaws[-1]) if len(s) else yaw


# --- odometry and events -----------------------------------------------------------------------


def _rotate(xy: np.ndarray, angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.column_stack([c * xy[:, 0] - s * xy[:, 1], s * xy[:, 0] + c * xy[:, 1]])


def odometry(path: np.ndarray, noise: OdometryNoise, rng: np.random.Generator) -> np.ndarray:
    """The path as the robot's odometry integrates it, from the true first pose (same layout)."""
    position, yaw = path[:, :-1], path[:, -1]
    step = np.diff(position, axis=0)
    distance = np.linalg.norm(step, axis=1)
    local = step.copy()
    local[:, :2] = _rotate(step[:, :2], -yaw[:-1])
    turn = np.angle(np.exp(1j * np.diff(yaw)))
    scale = 1.0 + rng.normal(0.0, noise.scale_bias)
    root = np.sqrt(distance)
    local = local * scale + rng.normal(0.0, noise.translation_walk, local.shape) * root[:, None]
    turn = turn + rng.normal(0.0, noise.heading_walk, len(turn)) * root
    odo_yaw = yaw[0] + np.concatenate([[0.0], np.cumsum(turn)])
    moved = local.copy()
    moved[:, :2] = _rotate(local[:, :2], odo_yaw[:-1])
    odo_position = position[0] + np.concatenate([np.zeros((1, position.shape[1])), np.cumsum(moved, axis=0)])
    return np.column_stack([odo_position, odo_yaw])


def path_pose(row: np.ndarray) -> Pose:
    """A path row (x, y, yaw) or (x, y, z, yaw) as a Pose; 3D poses turn about z only."""
    if len(row) == 3:
        return Pose.from_xytheta(*row)
    c, s = np.cos(row[3]), np.sin(row[3])
    return Pose(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), row[:3])


@dataclass(frozen=True)
class ClosureSchedule:
    """When a simulated robot's SLAM back end closes a loop: after every `every` scans (0: never),
    `offset` scans early. The robots' back ends run independently, so robot i of n closes i/n of an
    interval before robot 0 and a fleet's closures spread over the interval rather than landing at
    one instant (the worst case, one optimiser for the whole fleet: SimulatedFleet.spread_closures)."""

    every: int
    offset: int = 0

    @staticmethod
    def of_robot(index: int, robots: int, every: int, spread: bool = True) -> ClosureSchedule:
        return ClosureSchedule(every, (index * every) // robots if spread and every else 0)

    def closes_after(self, scans: int) -> bool:
        """Whether a closure follows the robot's first `scans` scans."""
        return self.every > 0 and (scans + self.offset) % self.every == 0

    def revision(self, scans: int) -> int:
        """The closures in the robot's first `scans` scans."""
        return (scans + self.offset) // self.every if self.every else 0


def robot_events(
    world: World,
    sensor: Sensor,
    path: np.ndarray,
    odom: np.ndarray,
    *,
    rate: float,
    closures: ClosureSchedule,
    seed: int,
) -> Iterator[tuple]:
    """A robot's run as events, in order:

    ("scan", RangeScan): node = scan.index, `pose` the true pose, `odom_pose` the robot's own
        estimate when it publishes the scan: its odometry chained onto the latest corrected pose.
    ("correction", revision, [(node, Pose), ...]): after the scans `closures` says, a pose-graph
        update setting every node so far to its true pose, as a SLAM back end would.
    """
    rng = np.random.default_rng([seed, 13])
    true = [path_pose(row) for row in path]
    odo = [path_pose(row) for row in odom]
    to_estimate = Pose.identity(world.dim)  # maps odometry onto the estimate; reset by corrections
    for k in range(len(path)):
        yield (
            "scan",
            simulate_scan(world, sensor, true[k], rng, index=k, stamp=k / rate, odom_pose=to_estimate.compose(odo[k])),
        )
        if closures.closes_after(k + 1):
            yield "correction", closures.revision(k + 1), [(j, true[j]) for j in range(k + 1)]
            to_estimate = true[k].compose(odo[k].inverse())
