"""OctoMap trees: binary (`.bt`, what `OcTree::readBinary` loads) and full (`.ot`, what
`AbstractOcTree::read` loads), of the cells that Eq. 12 calls occupied or free.

Both files start with header lines (`id OcTree`, `size` = every node of the tree, which the
readers check, `res`, `data`) and then hold the tree depth first from the root. The tree has 16
levels; a voxel's key is floor(coordinate / resolution) + 2^15 on each axis, and child i of a
node at depth d (the root at 0) holds the keys whose bit 15 - d is i & 1 in x, (i >> 1) & 1 in
y, (i >> 2) & 1 in z. So voxels lie on multiples of the resolution from the world origin.

`.bt` (AbstractOccupancyOcTree.cpp, OccupancyOcTreeBase.hxx readBinaryNode): each inner node as
two bytes of 2 bits per child, children 0-3 in the first, 4-7 in the second, child i at bits 2i
and 2i + 1 (from the least significant): 00 absent (unknown), 01 free leaf, 10 occupied leaf,
11 an inner node, whose own two bytes follow later. It holds classes, not probabilities:
readBinary gives every occupied leaf the tree's upper clamping log-odds and every free leaf the
lower one (3.5 and -2 by default), as for any `.bt` (OctoMap's writeBinary first turns a tree to
its maximum likelihood). Eight leaves of one class merge into their parent (OctoMap's prune,
never at the root), so these are the bytes OctoMap's writeBinary writes for the same leaves.

`.ot` (OcTreeBaseImpl.hxx writeNodesRecurs, OcTreeDataNode::writeData): every node as its
log-odds (float32) and one byte with a bit per existing child, so a leaf keeps the MAP estimate
of Eq. 11 as log(p / (1 - p)); an inner node holds the largest of its children's, as OctoMap's
updateInnerOccupancy sets it. Nothing is pruned (leaves rarely share a value).
"""

from __future__ import annotations

import numpy as np

from gmm_core import Grid
from gmm_core.occupancy import OCCUPIED, UNKNOWN, classify

TREE_DEPTH = 16
KEY_OFFSET = 1 << (TREE_DEPTH - 1)  # OctoMap's tree_max_val: the key of the voxel at [0, resolution)
COMMENT = "\n# (feel free to add / change comments, but leave the first line as it is!)\n#\n"
BT_HEADER = "# Octomap OcTree binary file" + COMMENT  # its first line is what readBinary checks
OT_HEADER = "# Octomap OcTree file" + COMMENT  # and what read checks
OT_NODE = np.dtype([("log_odds", "<f4"), ("children", "u1")])  # 5 bytes, packed
P_MIN = float(np.nextafter(np.float32(0), np.float32(1)))  # the float32 probabilities inside (0, 1)
P_MAX = float(np.nextafter(np.float32(1), np.float32(0)))
FREE_LEAF, OCCUPIED_LEAF, INNER = 1, 2, 3  # a child's 2 bits
ALL_FREE = sum(FREE_LEAF << (2 * i) for i in range(8))  # 0x5555: eight free leaves, pruned to one
ALL_OCCUPIED = sum(OCCUPIED_LEAF << (2 * i) for i in range(8))  # 0xAAAA
NOT_3D = "{fmt}: OctoMap trees are 3D and this map is {dim}D; export it as pgm or ply"


def cell_keys(grid: Grid, index: tuple[np.ndarray, ...]) -> np.ndarray:
    """(n, 3) OctoMap keys (x, y, z) of the voxels holding the centres of the cells at array `index`
    ((iz, iy, ix), as np.nonzero gives it): OctoMap's coordToKey. On a grid whose min corner is a
    multiple of the resolution each cell is a voxel; otherwise each moves by under half a cell onto
    OctoMap's lattice (`lattice_offset`)."""
    return np.stack([_axis_keys(grid, axis)[index[2 - axis]] for axis in range(3)], axis=1)


def _axis_keys(grid: Grid, axis: int) -> np.ndarray:
    centre = grid.origin[axis] / grid.resolution + np.arange(grid.shape[axis]) + 0.5  # in cells
    return np.floor(centre).astype(np.int64) + KEY_OFFSET


def reach_problem(grid: Grid) -> str | None:
    """Why a 3D grid does not fit in an OctoMap tree (keys of 16 bits), or None when it does."""
    for axis in range(3):
        first = np.floor(grid.origin[axis] / grid.resolution + 0.5) + KEY_OFFSET
        last = first + grid.shape[axis] - 1
        if first < 0 or last >= 2 * KEY_OFFSET:
            return (
                f"an OctoMap tree at {grid.resolution} m reaches +-{KEY_OFFSET * grid.resolution:g} m from the "
                f"origin; this map spans {'xyz'[axis]} {float(grid.origin[axis]):g} .. {float(grid.upper[axis]):g} m"
            )
    return None


def lattice_offset(grid: Grid) -> np.ndarray:
    """(3,) metres each cell centre lies from the centre of its OctoMap voxel (0 on OctoMap's lattice)."""
    centre = grid.origin / grid.resolution + 0.5
    return (centre - (np.floor(centre) + 0.5)) * grid.resolution


def _morton(keys: np.ndarray) -> np.ndarray:
    """Interleaved key bits, x lowest: ordering by it walks the tree depth first, children 0 to 7."""
    code = np.zeros(len(keys), dtype=np.int64)
    for bit in range(TREE_DEPTH):
        for axis in range(3):
            code |= ((keys[:, axis] >> bit) & 1) << (3 * bit + axis)
    return code


def _parents(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nodes (n, 3 keys at one depth) under their parents: the parents' keys, the order that sorts
    the nodes by parent, where each parent's run starts in that order, and the sorted nodes' child
    indices."""
    parent = keys >> 1
    child = (keys[:, 0] & 1) | (keys[:, 1] & 1) << 1 | (keys[:, 2] & 1) << 2
    packed = parent[:, 0] | parent[:, 1] << 16 | parent[:, 2] << 32
    order = np.argsort(packed, kind="stable")
    _, first = np.unique(packed[order], return_index=True)
    return parent[order[first]], order, first, child[order]


def _depth_first(depth: np.ndarray, prefix: np.ndarray) -> np.ndarray:
    """The order that walks nodes (their depth, and their keys at that depth) depth first, children
    0 to 7: a node's keys padded with zero bits sort it before its descendants (which share that
    code only along child 0, deeper) and after every earlier sibling's subtree."""
    return np.lexsort((depth, _morton(prefix << (TREE_DEPTH - depth)[:, None])))


def bt_data(keys: np.ndarray, occupied: np.ndarray) -> tuple[int, bytes]:
    """The node count and the `.bt` data bytes of the tree whose leaves are voxels `keys` (n, 3) at
    the deepest level, occupied where `occupied` and free elsewhere; every other voxel unknown."""
    keys = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
    if len(keys) == 0:
        return 0, b""
    state = np.where(np.asarray(occupied, dtype=bool).ravel(), OCCUPIED_LEAF, FREE_LEAF).astype(np.int64)
    depths, prefixes, words = [], [], []  # the inner nodes
    nodes = 1  # the root
    for depth in range(TREE_DEPTH, 0, -1):  # the nodes at `depth` join their parents at depth - 1
        parent, order, first, child = _parents(keys)
        word = np.add.reduceat(state[order] << (2 * child), first)  # each child once: + is |
        pruned = (word == ALL_FREE) | (word == ALL_OCCUPIED) if depth > 1 else np.zeros(len(word), bool)
        inner = ~pruned
        depths.append(np.full(int(inner.sum()), depth - 1))
        prefixes.append(parent[inner])
        words.append(word[inner])
        nodes += int(np.diff(np.append(first, len(order)))[inner].sum())
        keys = parent
        state = np.where(pruned, np.where(word == ALL_OCCUPIED, OCCUPIED_LEAF, FREE_LEAF), INNER)
    word = np.concatenate(words)[_depth_first(np.concatenate(depths), np.concatenate(prefixes))]
    data = np.empty(2 * len(word), dtype=np.uint8)
    data[0::2] = word & 0xFF
    data[1::2] = word >> 8
    return nodes, data.tobytes()


def ot_data(keys: np.ndarray, log_odds: np.ndarray) -> tuple[int, bytes]:
    """The node count and the `.ot` data bytes of the tree whose leaves are voxels `keys` (n, 3) at
    the deepest level with `log_odds` (n,); every other voxel unknown."""
    keys = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
    if len(keys) == 0:
        return 0, b""
    value = np.asarray(log_odds, dtype=np.float32).ravel()
    depths, prefixes, values = [np.full(len(keys), TREE_DEPTH)], [keys], [value]
    masks = [np.zeros(len(keys), np.int64)]
    for depth in range(TREE_DEPTH, 0, -1):
        keys, order, first, child = _parents(keys)
        value = np.maximum.reduceat(value[order], first)  # updateInnerOccupancy: the largest child
        depths.append(np.full(len(keys), depth - 1))
        prefixes.append(keys)
        values.append(value)
        masks.append(np.add.reduceat(1 << child, first))  # each child once: + is |
    walk = _depth_first(np.concatenate(depths), np.concatenate(prefixes))
    nodes = np.empty(len(walk), dtype=OT_NODE)
    nodes["log_odds"] = np.concatenate(values)[walk]
    nodes["children"] = np.concatenate(masks)[walk]
    return len(nodes), nodes.tobytes()


def _known_cells(
    prob: np.ndarray, grid: Grid, variance: float, fmt: str
) -> tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray]:
    """The keys, array index and classes of the cells that Eq. 12 at sigma^2 = `variance` calls
    occupied or free, after the checks that the grid fits a tree (of format `fmt`)."""
    if grid.dim != 3:
        raise ValueError("format: " + NOT_3D.format(fmt=fmt, dim=grid.dim))
    problem = reach_problem(grid)
    if problem:
        raise ValueError(f"bbox: {problem}")
    classes = classify(prob, variance)
    known = np.nonzero(classes != UNKNOWN)
    return cell_keys(grid, known), known, classes[known]


def _file(header: str, size: int, resolution: float, data: bytes) -> bytes:
    return f"{header}id OcTree\nsize {size}\nres {resolution!r}\ndata\n".encode("ascii") + data


def bt_bytes(prob: np.ndarray, grid: Grid, variance: float) -> bytes:
    """The `.bt` of a 3D probability map [iz, iy, ix]: cells occupied or free by Eq. 12 at sigma^2 =
    `variance` become leaves of that class; cells in the dead band, and p = 0.5, stay unknown."""
    keys, _, classes = _known_cells(prob, grid, variance, "bt")
    size, data = bt_data(keys, classes == OCCUPIED)
    return _file(BT_HEADER, size, grid.resolution, data)


def ot_bytes(prob: np.ndarray, grid: Grid, variance: float) -> bytes:
    """The `.ot` of a 3D probability map [iz, iy, ix]: cells occupied or free by Eq. 12 at sigma^2 =
    `variance` become leaves with log-odds log(p / (1 - p)); the rest stay unknown."""
    keys, known, _ = _known_cells(prob, grid, variance, "ot")
    # p = 1 or 0 only where float32 rounded it there (Eq. 11 with N_p > 0 is strictly inside): the
    # nearest float32 inside keeps the log-odds finite.
    p = np.clip(prob[known].astype(np.float64), P_MIN, P_MAX)
    size, data = ot_data(keys, np.log(p / (1.0 - p)))
    return _file(OT_HEADER, size, grid.resolution, data)
