"""Procedural worlds with exact ground truth: a solid raster (2D floor plans) or voxel grid (3D mine).

A world *is* its raster: each cell is solid or free, and everything outside the raster is solid.
Ray casting, `occupied` and `ground_truth` all read that one array, so a simulated beam ends
exactly where the ground truth says it does. Generators are seeded: the same seed, the same world.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from gmm_core.grid import Grid

RASTER_2D = 0.02  # m: walls of 0.1-0.2 m are 5-10 cells thick
VOXEL_3D = 0.1  # m
_EDGE_TOLERANCE = 1e-9  # in cells: a query box touching a raster cell at its edge does not overlap it


@njit(cache=True, inline="always")
def _axis_start(o, d, lo, resolution, i):
    """Step, t of the first cell boundary and t between boundaries along one axis."""
    if d > 0.0:
        return 1, (lo + (i + 1) * resolution - o) / d, resolution / d
    if d < 0.0:
        return -1, (lo + i * resolution - o) / d, -resolution / d
    return 0, np.inf, np.inf


@njit(cache=True, parallel=True)
def _cast(solid, lo, resolution, origin, directions, max_range):
    """Distance from `origin` along each unit direction to the first solid cell (Amanatides-Woo).

    `solid` is (nz, ny, nx); leaving the raster counts as a hit at its boundary. inf: nothing
    within `max_range`. An origin inside solid gives 0.
    """
    nz, ny, nx = solid.shape
    ranges = np.empty(directions.shape[0])
    x0 = int(np.floor((origin[0] - lo[0]) / resolution))
    y0 = int(np.floor((origin[1] - lo[1]) / resolution))
    z0 = int(np.floor((origin[2] - lo[2]) / resolution))
    if not (0 <= x0 < nx and 0 <= y0 < ny and 0 <= z0 < nz) or solid[z0, y0, x0]:
        ranges[:] = 0.0
        return ranges
    for r in prange(directions.shape[0]):
        x, y, z = x0, y0, z0
        sx, tx, dtx = _axis_start(origin[0], directions[r, 0], lo[0], resolution, x)
        sy, ty, dty = _axis_start(origin[1], directions[r, 1], lo[1], resolution, y)
        sz, tz, dtz = _axis_start(origin[2], directions[r, 2], lo[2], resolution, z)
        ranges[r] = np.inf
        while True:
            if tx <= ty and tx <= tz:
                t, x, tx = tx, x + sx, tx + dtx
            elif ty <= tz:
                t, y, ty = ty, y + sy, ty + dty
            else:
                t, z, tz = tz, z + sz, tz + dtz
            if t > max_range:
                break
            if not (0 <= x < nx and 0 <= y < ny and 0 <= z < nz) or solid[z, y, x]:
                ranges[r] = t
                break
    return ranges


@njit(cache=True, parallel=True)
def _solid_in_boxes(solid, first_z, last_z, first_y, last_y, first_x, last_x):
    """Whether any solid cell lies in each box of raster index ranges; first = -1: outside, solid."""
    nz, ny, nx = len(first_z), len(first_y), len(first_x)
    out = np.zeros((nz, ny, nx), np.bool_)
    for zy in prange(nz * ny):
        bz, by = zy // ny, zy % ny
        for bx in range(nx):
            if first_z[bz] < 0 or first_y[by] < 0 or first_x[bx] < 0:
                out[bz, by, bx] = True
                continue
            found = False
            for z in range(first_z[bz], last_z[bz] + 1):
                for y in range(first_y[by], last_y[by] + 1):
                    for x in range(first_x[bx], last_x[bx] + 1):
                        if solid[z, y, x]:
                            found = True
                            break
                    if found:
                        break
                if found:
                    break
            out[bz, by, bx] = found
    return out


@dataclass(frozen=True, eq=False)
class World:
    """A solid/free raster over `raster` (array index [iy, ix] or [iz, iy, ix]); outside is solid."""

    name: str
    raster: Grid
    solid: np.ndarray  # bool, raster.array_shape

    @property
    def dim(self) -> int:
        return self.raster.dim

    def _solid_zyx(self) -> np.ndarray:
        return self.solid if self.dim == 3 else self.solid[None]

    def _as_3d(self, vectors: np.ndarray, z: float) -> np.ndarray:
        """(n, 3) copies of (n, d) vectors; 2D ones get z (the raster is one cell thick)."""
        vectors = np.asarray(vectors, dtype=np.float64).reshape(-1, self.dim)
        if self.dim == 3:
            return np.ascontiguousarray(vectors)
        return np.column_stack([vectors, np.full(len(vectors), z)])

    def occupied(self, points: np.ndarray) -> np.ndarray:
        """(n,) bool: whether each (n, d) point lies in a solid cell (or outside the raster)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, self.dim)
        index = np.floor((points - self.raster.origin) / self.raster.resolution).astype(np.int64)
        inside = ((index >= 0) & (index < np.asarray(self.raster.shape))).all(axis=1)
        out = np.ones(len(points), dtype=bool)
        out[inside] = self.solid[tuple(index[inside, ::-1].T)]
        return out

    def cast(self, origin: np.ndarray, directions: np.ndarray, max_range: float) -> np.ndarray:
        """(n,) distances along unit `directions` from `origin` to the first solid cell; inf past max_range."""
        mid_plane = 0.5 * self.raster.resolution  # 2D rays run along the middle of the one-cell layer
        return _cast(
            self._solid_zyx(),
            self._as_3d(self.raster.origin, 0.0)[0],
            self.raster.resolution,
            self._as_3d(origin, mid_plane)[0],
            self._as_3d(directions, 0.0),
            float(max_range),
        )

    def solid_near(self, grid: Grid, margin: float = 0.0) -> np.ndarray:
        """Bool over `grid.array_shape`: whether the cell, grown by `margin`, overlaps a solid cell."""
        if grid.dim != self.dim:
            raise ValueError(f"grid: a {self.dim}D world needs a {self.dim}D grid, got {grid.dim}D")
        ranges = []
        for a in reversed(range(self.dim)):
            edges = grid.origin[a] + np.arange(grid.shape[a] + 1) * grid.resolution
            lo = (edges[:-1] - margin - self.raster.origin[a]) / self.raster.resolution
            hi = (edges[1:] + margin - self.raster.origin[a]) / self.raster.resolution
            first = np.floor(lo + _EDGE_TOLERANCE).astype(np.int64)
            last = np.ceil(hi - _EDGE_TOLERANCE).astype(np.int64) - 1
            outside = (first < 0) | (last >= self.raster.shape[a])
            ranges += [np.where(outside, -1, first), last]
        if self.dim == 2:
            ranges = [np.zeros(1, np.int64), np.zeros(1, np.int64)] + ranges
        out = _solid_in_boxes(self._solid_zyx(), *ranges)
        return out if self.dim == 3 else out[0]

    def ground_truth(self, grid: Grid) -> np.ndarray:
        """Bool over `grid.array_shape`: occupied where the cell's area/volume overlaps a solid cell."""
        return self.solid_near(grid)

    def free_cells(self, cell: float, clearance: float) -> tuple[Grid, np.ndarray]:
        """A coarse grid over the world and where its cells lie at least `clearance` from any solid."""
        grid = Grid.from_bbox(self.raster.origin, self.raster.upper, cell)
        return grid, ~self.solid_near(grid, clearance)

    def sample_free(self, rng: np.random.Generator, n: int, clearance: float, cell: float | None = None) -> np.ndarray:
        """(n, d) points uniformly spread over cells at least `clearance` from any solid."""
        grid, free = self.free_cells(cell or planning_cell(self.dim), clearance)
        index = np.flatnonzero(free.ravel())
        if len(index) == 0:
            raise ValueError(f"{self.name}: no free space with clearance {clearance} m")
        cells = np.stack(np.unravel_index(rng.choice(index, n), free.shape)[::-1], axis=1)
        return grid.origin + (cells + rng.random((n, self.dim))) * grid.resolution


def planning_cell(dim: int) -> float:
    """Coarse cell for free-space sampling and path planning: 0.1 m in 2D, 0.3 m in 3D."""
    return 0.1 if dim == 2 else 0.3


# --- generators ------------------------------------------------------------------------------


def _box(solid: np.ndarray, raster: Grid, lo, hi, value: bool) -> None:
    """Set the raster cells whose centres lie in the box [lo, hi] (x, y[, z] order)."""
    first = np.round((np.asarray(lo) - raster.origin) / raster.resolution).astype(np.int64)
    last = np.round((np.asarray(hi) - raster.origin) / raster.resolution).astype(np.int64)
    first = np.clip(first, 0, raster.shape)
    last = np.clip(last, 0, raster.shape)
    solid[tuple(slice(f, l) for f, l in zip(first[::-1], last[::-1]))] = value


def _spans(
    rng: np.random.Generator, x0: float, x1: float, width: tuple[float, float], gap: tuple[float, float]
) -> list[tuple[float, float]]:
    """Split [x0, x1] into pieces of `width` separated by gaps of `gap`; the last piece takes the rest."""
    spans, x = [], x0
    while x1 - x > 2 * width[0] + gap[1]:
        w = min(rng.uniform(*width), x1 - x - width[0] - gap[1])
        spans.append((x, x + w))
        x += w + rng.uniform(*gap)
    spans.append((x, x1))
    return spans


def office(seed: int = 0, size: tuple[float, float] = (40.0, 30.0)) -> World:
    """Two corridors joined by a third, rooms on both sides with 1 m doors, some furniture."""
    rng = np.random.default_rng([seed, 1])
    width, height = size
    raster = Grid.from_bbox((0.0, 0.0), size, RASTER_2D)
    solid = np.ones(raster.array_shape, dtype=bool)
    outer, wall, corridor = 0.2, (0.1, 0.2), rng.uniform(1.8, 2.4)
    low = rng.uniform(0.26, 0.32) * height
    high = rng.uniform(0.68, 0.74) * height - corridor
    middle = (low + corridor + high) / 2
    cross = rng.uniform(0.3, 0.6) * width
    for y in (low, high):
        _box(solid, raster, (outer, y), (width - outer, y + corridor), False)
    _box(solid, raster, (cross, low), (cross + corridor, high + corridor), False)
    t = rng.uniform(*wall, size=4)
    # Rows of rooms: (y0, y1, y of the corridor edge their doors open onto).
    rows = [
        (outer, low - t[0], low),
        (low + corridor + t[1], middle - 0.06, low + corridor),
        (middle + 0.06, high - t[2], high),
        (high + corridor + t[3], height - outer, high + corridor),
    ]
    for i, (y0, y1, door_y) in enumerate(rows):
        pieces = [(outer, width - outer)]
        if i in (1, 2):  # the cross corridor splits the middle rows
            pieces = [(outer, cross - t[i]), (cross + corridor + t[i], width - outer)]
        for x0, x1 in pieces:
            for r0, r1 in _spans(rng, x0, x1, (3.0, 6.0), wall):
                _room(solid, raster, rng, (r0, y0), (r1, y1), door_y)
    return World("office", raster, solid)


def _room(solid, raster, rng, lo, hi, door_y) -> None:
    """A room [lo, hi] with a 1 m door through the wall to y = door_y, furniture on the far wall."""
    (x0, y0), (x1, y1) = lo, hi
    _box(solid, raster, lo, hi, False)
    door = rng.uniform(x0 + 0.2, max(x0 + 0.2, x1 - 1.2))
    _box(solid, raster, (door, min(door_y, y1)), (door + 1.0, max(door_y, y0)), False)
    against_bottom = door_y > y1  # furniture stands along the wall opposite the door
    for _ in range(rng.integers(0, 3)):
        w, depth = rng.uniform(0.8, 2.0), rng.uniform(0.5, 0.9)
        x = rng.uniform(x0, max(x0, x1 - w))
        if against_bottom:
            _box(solid, raster, (x, y0), (x + w, y0 + depth), True)
        else:
            _box(solid, raster, (x, y1 - depth), (x + w, y1), True)
    if x1 - x0 > 4.5 and y1 - y0 > 4.0:  # a table in the middle of a large room
        cx, cy = (x0 + x1) / 2 + rng.uniform(-0.3, 0.3), (y0 + y1) / 2 + rng.uniform(-0.3, 0.3)
        _box(solid, raster, (cx - 0.7, cy - 0.45), (cx + 0.7, cy + 0.45), True)


def warehouse(seed: int = 0, size: tuple[float, float] = (60.0, 40.0)) -> World:
    """A hall: rows of racks along x split by cross aisles, an open loading zone with pallets."""
    rng = np.random.default_rng([seed, 2])
    width, height = size
    raster = Grid.from_bbox((0.0, 0.0), size, RASTER_2D)
    solid = np.ones(raster.array_shape, dtype=bool)
    outer = 0.3
    _box(solid, raster, (outer, outer), (width - outer, height - outer), False)
    dock = rng.uniform(6.0, 8.0)
    for _ in range(rng.integers(6, 12)):  # pallets in the loading zone
        x, y = rng.uniform(outer + 1.0, width - 3.0), rng.uniform(outer + 1.0, dock - 2.5)
        _box(solid, raster, (x, y), (x + 1.2, y + 1.0), True)
    depth = rng.uniform(1.0, 1.3)
    aisles = _spans(rng, 2.0, width - 2.0, (12.0, 18.0), (3.0, 4.0))
    y = dock + rng.uniform(1.5, 2.5)
    while y + depth < height - 2.0:
        for x0, x1 in aisles:
            _box(solid, raster, (x0, y), (x1, y + depth), True)
            if rng.random() < 0.3:  # an empty bay
                gap = rng.uniform(x0 + 1.0, x1 - 3.0)
                _box(solid, raster, (gap, y), (gap + 2.0, y + depth), False)
        y += depth + rng.uniform(2.6, 3.4)
    return World("warehouse", raster, solid)


@njit(cache=True, inline="always")
def _value_noise(lattice, spacing, x, y, z):
    """Smooth noise in [-1, 1] at (x, y, z): trilinear interpolation of random lattice values,
    smoothstep weights."""
    u0, u1, u2 = x / spacing, y / spacing, z / spacing
    i0, i1, i2 = int(np.floor(u0)), int(np.floor(u1)), int(np.floor(u2))
    g0, g1, g2 = u0 - i0, u1 - i1, u2 - i2
    f0, f1, f2 = g0 * g0 * (3 - 2 * g0), g1 * g1 * (3 - 2 * g1), g2 * g2 * (3 - 2 * g2)
    out = 0.0
    for cx in (0, 1):
        for cy in (0, 1):
            for cz in (0, 1):
                w = (f0 if cx else 1 - f0) * (f1 if cy else 1 - f1) * (f2 if cz else 1 - f2)
                out = out + w * lattice[i0 + cx, i1 + cy, i2 + cz]
    return out


def mine(seed: int = 0, size: tuple[float, float, float] = (80.0, 80.0, 10.0)) -> World:
    """Tunnels along a random spanning tree (plus two loops) of a jittered 4 x 4 lattice.

    Each edge is three capsule segments with jittered joints, 3-4 m across, with a flattened
    floor; walls are roughened by two octaves of value noise (about 0.25 m and 0.08 m).
    """
    rng = np.random.default_rng([seed, 3])
    size = np.asarray(size)
    raster = Grid.from_bbox(np.zeros(3), size, VOXEL_3D)
    solid = np.ones(raster.array_shape, dtype=bool)
    n = 4
    spacing = (size[:2] - 16.0) / (n - 1)
    nodes = {
        (i, j): np.array(
            [
                8.0 + i * spacing[0] + rng.uniform(-3, 3),
                8.0 + j * spacing[1] + rng.uniform(-3, 3),
                rng.uniform(0.4, 0.6) * size[2],
            ]
        )
        for i in range(n)
        for j in range(n)
    }
    edges = _lattice_tunnels(rng, n, loops=2)
    octaves = [
        (1.0, 0.25, rng.uniform(-1, 1, size=tuple((size / 1.0).astype(int) + 2))),
        (0.35, 0.08, rng.uniform(-1, 1, size=tuple((size / 0.35).astype(int) + 2))),
    ]
    for a, b in edges:
        radius = rng.uniform(1.5, 2.0)
        lateral = np.cross(nodes[b] - nodes[a], [0, 0, 1.0])
        lateral /= np.linalg.norm(lateral)
        joints = (
            [nodes[a]]
            + [nodes[a] + f * (nodes[b] - nodes[a]) + rng.uniform(-1.5, 1.5) * lateral for f in (1 / 3, 2 / 3)]
            + [nodes[b]]
        )
        for p, q in zip(joints[:-1], joints[1:]):
            _carve_capsule(solid, raster, p, q, radius, octaves)
    return World("mine", raster, solid)


def _lattice_tunnels(rng, n: int, loops: int) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """A random spanning tree of the n x n lattice (Kruskal over shuffled edges) plus `loops` other edges."""
    edges = [((i, j), (i + 1, j)) for i in range(n - 1) for j in range(n)]
    edges += [((i, j), (i, j + 1)) for i in range(n) for j in range(n - 1)]
    edges = [edges[k] for k in rng.permutation(len(edges))]
    parent = {node: node for edge in edges for node in edge}

    def root(node):
        while parent[node] != node:
            node = parent[node]
        return node

    tree, rest = [], []
    for a, b in edges:
        ra, rb = root(a), root(b)
        (tree if ra != rb else rest).append((a, b))
        parent[ra] = rb
    return tree + rest[:loops]


def _carve_capsule(solid, raster: Grid, p, q, radius: float, octaves) -> None:
    """Free the voxels within the rough capsule around segment pq and above its flattened floor."""
    spacings, amplitudes, lattices = zip(*octaves)
    reach = radius + sum(amplitudes)
    lo = np.maximum(np.floor((np.minimum(p, q) - reach) / raster.resolution).astype(int), 0)
    hi = np.minimum(np.ceil((np.maximum(p, q) + reach) / raster.resolution).astype(int), raster.shape)
    axis = q - p
    _carve(
        solid, raster.origin, raster.resolution, lo, hi, p, axis, axis.dot(axis), radius,
        np.array(spacings, dtype=np.float64), np.array(amplitudes, dtype=np.float64), tuple(lattices),
    )  # fmt: skip


@njit(cache=True)
def _carve(solid, origin, resolution, lo, hi, p, axis, length2, radius, spacings, amplitudes, lattices):
    """_carve_capsule's voxels lo .. hi - 1 (x, y, z), voxel by voxel: the roughness of every octave
    summed in order, as numpy's arrays of the whole box did in 2.6 of the mine's 3.5 s."""
    for k in range(lo[2], hi[2]):
        z = origin[2] + (k + 0.5) * resolution
        for j in range(lo[1], hi[1]):
            y = origin[1] + (j + 0.5) * resolution
            for i in range(lo[0], hi[0]):
                x = origin[0] + (i + 0.5) * resolution
                t = ((x - p[0]) * axis[0] + (y - p[1]) * axis[1] + (z - p[2]) * axis[2]) / length2
                t = min(max(t, 0.0), 1.0)
                dx, dy, dz = x - (p[0] + t * axis[0]), y - (p[1] + t * axis[1]), z - (p[2] + t * axis[2])
                rough = 0.0
                for o in range(len(lattices)):
                    rough = rough + amplitudes[o] * _value_noise(lattices[o], spacings[o], x, y, z)
                if dx * dx + dy * dy + dz * dz < (radius + rough) ** 2 and dz > -0.7 * radius + 0.3 * rough:
                    solid[k, j, i] = False


WORLDS = {"office": office, "warehouse": warehouse, "mine": mine}


def make_world(name: str, seed: int = 0) -> World:
    if name not in WORLDS:
        raise ValueError(f"world must be one of {sorted(WORLDS)}, got {name!r}")
    return WORLDS[name](seed)
