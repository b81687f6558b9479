"""The .bt and .ot writers against OctoMap itself (octomap-python): its own writeBinary and write for
the same leaves, and its readBinary and read on what we write."""

import numpy as np
import pytest

from gmm_core import Grid
from gmm_core.occupancy import FREE, OCCUPIED, classify
from services.export.octomap_tree import (
    BT_HEADER,
    KEY_OFFSET,
    OT_HEADER,
    bt_bytes,
    bt_data,
    cell_keys,
    lattice_offset,
    ot_bytes,
    ot_data,
)
from support.octomap_trees import node_log_odds

octomap = pytest.importorskip("octomap", reason="octomap-python is in the [bench] and [dev] extras")


def random_leaves(rng, n_scattered: int) -> dict[tuple[int, int, int], bool]:
    """Voxel keys (relative to the origin's voxel) -> occupied: scattered ones, and solid blocks of one
    class aligned on 2, 4 and 8 voxels, which OctoMap prunes one, two and three levels up."""
    leaves = {tuple(k): bool(o) for k, o in zip(rng.integers(-12, 12, (n_scattered, 3)), rng.random(n_scattered) < 0.3)}
    for size in (2, 4, 8):
        for corner in rng.integers(-3, 3, (2, 3)) * 8:
            occupied = bool(rng.random() < 0.5)
            for offset in np.ndindex(size, size, size):
                leaves[tuple(int(c) for c in corner + offset)] = occupied
    return leaves


@pytest.mark.parametrize("seed", range(6))
def test_same_bytes_as_octomaps_own_writer(seed):
    rng = np.random.default_rng(seed)
    resolution = [0.1, 0.05, 0.25][seed % 3]
    leaves = random_leaves(rng, int(rng.integers(1, 300)))
    reference = octomap.OcTree(resolution)
    for key, occupied in leaves.items():
        reference.updateNode((np.array(key) + 0.5) * resolution, occupied)
    keys = np.array(list(leaves)) + KEY_OFFSET
    size, data = bt_data(keys, np.array(list(leaves.values())))
    ours = f"{BT_HEADER}id OcTree\nsize {size}\nres {resolution!r}\ndata\n".encode() + data
    assert ours == reference.writeBinary()  # toMaxLikelihood, prune, then the same depth-first bytes


@pytest.mark.parametrize("seed", range(4))
def test_ot_same_bytes_as_octomaps_own_writer(seed):
    rng = np.random.default_rng(100 + seed)
    resolution = [0.1, 0.2][seed % 2]
    leaves = random_leaves(rng, int(rng.integers(1, 300)))
    log_odds = rng.uniform(-5, 5, len(leaves)).astype(np.float32)
    reference = octomap.OcTree(resolution)
    reference.setClampingThresMin(0.001)  # log-odds -6.9 .. 6.9: updateNode keeps these values
    reference.setClampingThresMax(0.999)
    for key, value in zip(leaves, log_odds):
        reference.updateNode((np.array(key) + 0.5) * resolution, float(value), True)  # lazy: no pruning
    reference.updateInnerOccupancy()  # inner nodes: the largest child's log-odds
    size, data = ot_data(np.array(list(leaves)) + KEY_OFFSET, log_odds)
    assert f"{OT_HEADER}id OcTree\nsize {size}\nres {resolution!r}\ndata\n".encode() + data == reference.write()


def test_ot_keeps_each_cells_map_log_odds(tmp_path):
    rng = np.random.default_rng(8)
    grid = Grid([0.4, -2.0, 1.2], 0.2, (6, 5, 4))
    prob = rng.random(grid.array_shape).astype(np.float32)
    prob[0, 0, :3] = [0.5, 1.0, 0.6]  # unseen; 1 as float32 rounds it; the dead band
    path = tmp_path / "map.ot"
    path.write_bytes(ot_bytes(prob, grid, 0.21))
    tree = octomap.OcTree.read(str(path).encode())  # OctoMap's AbstractOcTree::read
    classes = classify(prob, 0.21)
    for centre, p, cls in zip(grid.cell_centers(), prob.ravel(), classes.ravel()):
        log_odds = node_log_odds(tree, centre)
        if cls == -1:
            assert log_odds is None
        else:
            expected = np.log(p / (1 - p)) if p < 1 else np.log(np.float32(1 - 2**-24) / 2**-24)
            assert log_odds == pytest.approx(expected, rel=1e-5)
    assert node_log_odds(tree, grid.cell_centers()[1]) > 16  # p = 1: finite, the largest float32 below 1


def load(body: bytes, tmp_path):
    path = tmp_path / "map.bt"
    path.write_bytes(body)
    tree = octomap.OcTree(1.0)
    assert tree.readBinary(str(path).encode())  # OctoMap's own reader: checks the header and the node count
    return tree


def test_readbinary_loads_every_cell_with_its_class(tmp_path):
    rng = np.random.default_rng(7)
    grid = Grid([-1.2, 0.4, -0.6], 0.2, (9, 7, 5))  # on OctoMap's lattice: every cell is one voxel
    prob = rng.random(grid.array_shape).astype(np.float32)
    prob[1:3, 2:4, 4:6] = 0.05  # a block of free cells
    prob.ravel()[rng.random(prob.size) < 0.1] = 0.5  # unseen
    variance = 0.21
    tree = load(bt_bytes(prob, grid, variance), tmp_path)
    assert tree.getResolution() == 0.2
    classes = classify(prob, variance)
    occupied_log, free_log = tree.getClampingThresMaxLog(), tree.getClampingThresMinLog()
    seen = {OCCUPIED: 0, FREE: 0}
    for centre, cls in zip(grid.cell_centers(), classes.ravel()):
        log_odds = node_log_odds(tree, centre)
        if cls == OCCUPIED:
            assert log_odds == pytest.approx(occupied_log)
        elif cls == FREE:
            assert log_odds == pytest.approx(free_log)
        else:
            assert log_odds is None
        seen[cls] = seen.get(cls, 0) + 1
    assert seen[OCCUPIED] > 20 and seen[FREE] > 50
    # Every leaf volume is a known cell: the tree holds nothing beyond them.
    volume = sum(leaf.getSize() ** 3 for leaf in tree.begin_leafs())
    assert volume == pytest.approx((classes != -1).sum() * 0.2**3)


def test_off_lattice_cells_land_in_the_voxel_holding_their_centre(tmp_path):
    grid = Grid([0.03, -0.13, 1.0], 0.1, (4, 3, 2))
    prob = np.full(grid.array_shape, 0.9, dtype=np.float32)
    np.testing.assert_allclose(lattice_offset(grid), [0.03, -0.03, 0.0], atol=1e-12)
    keys = cell_keys(grid, tuple(i.ravel() for i in np.indices(grid.array_shape)))
    centres = grid.cell_centers()
    np.testing.assert_array_equal(keys, np.floor(centres / 0.1).astype(int) + KEY_OFFSET)
    tree = load(bt_bytes(prob, grid, 0.21), tmp_path)
    for centre in centres:
        assert node_log_odds(tree, centre - lattice_offset(grid)) == pytest.approx(tree.getClampingThresMaxLog())
    assert sum(1 for _ in tree.begin_leafs()) <= grid.n_cells


def test_a_map_with_nothing_known_is_an_empty_tree(tmp_path):
    grid = Grid([0.0, 0.0, 0.0], 0.1, (3, 3, 3))
    body = bt_bytes(np.full(grid.array_shape, 0.5, np.float32), grid, 0.21)
    assert body.endswith(b"size 0\nres 0.1\ndata\n")
    assert load(body, tmp_path).size() == 0


def test_2d_maps_and_maps_beyond_the_tree_are_refused():
    with pytest.raises(ValueError, match="format: bt: OctoMap trees are 3D and this map is 2D"):
        bt_bytes(np.zeros((2, 2), np.float32), Grid([0.0, 0.0], 0.1, (2, 2)), 0.21)
    far = Grid([0.0, 0.0, 3276.7], 0.1, (1, 1, 2))  # keys reach 2^16 at +3276.8 m
    with pytest.raises(ValueError, match=r"bbox: an OctoMap tree at 0.1 m reaches \+-3276.8 m"):
        bt_bytes(np.ones((2, 1, 1), np.float32), far, 0.21)
