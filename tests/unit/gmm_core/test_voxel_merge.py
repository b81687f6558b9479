"""The bottom-up merge of a scan's voxels (gmm_core.voxel_merge) against plain references: the
neighbours by brute force, the pieces by scipy, the rounds of merges recomputed from scratch with
numpy's determinants."""

import functools
from collections import defaultdict

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from gmm_core.voxel_merge import _MERGE_SHARE, _merge, _pieces, _voxel_edges, merge_voxels
from gmm_core.voxels import _KEY_BITS, _KEY_OFFSET, _LEVEL_SHIFT, _voxel_statistics

NO_TIERS = np.empty(0)  # one size of voxel


def voxel_coordinates(keys):
    """(x, y, z) of each key in its own voxel size, and its level (its size 2^level the finest's)."""
    mask = (1 << _KEY_BITS) - 1
    coords = np.column_stack([(keys >> (_KEY_BITS * (2 - a))) & mask for a in range(3)]) - _KEY_OFFSET
    return coords, keys >> _LEVEL_SHIFT


@pytest.mark.parametrize("tiers", [[4.0], [2.0, 3.0, 5.0]])
def test_voxel_edges_are_the_neighbouring_voxels(tiers):
    # Voxels of 0.5 m within the first range of `tiers`, doubling at each: neighbours among each
    # size are the 18 around a voxel (a face or an edge in common), two with an edge in common only
    # where no voxel has a face in common with both; a voxel within 2 sqrt(3) voxels of its tier's
    # outer range also touches the voxels of the next tier that hold one of its 26 neighbours' cells;
    # a voxel without any of these, its nearest within two voxels.
    rng = np.random.default_rng(3)
    points = rng.uniform(-7, 7, (700, 3))
    size, ranges = 0.5, np.array(tiers)
    _, keys = _voxel_statistics(points, size, np.zeros(3), ranges)
    eu, ev = _voxel_edges(keys, size, ranges)
    found = {tuple(sorted(pair)) for pair in zip(eu.tolist(), ev.tolist())}
    assert len(found) == len(eu)  # each pair once
    coords, level = voxel_coordinates(keys)
    occupied = {(tuple(c), f) for c, f in zip(coords.tolist(), level.tolist())}
    expected = set()
    for i in range(len(keys)):
        for j in range(i + 1, len(keys)):
            if level[i] == level[j]:
                step = coords[j] - coords[i]
                # a voxel sharing a face with both: i moved along one of the step's two axes
                between = [coords[i] + np.where(np.arange(3) == a, step, 0) for a in np.flatnonzero(step)]
                face_path = step.dot(step) == 2 and any((tuple(b.tolist()), level[i]) in occupied for b in between)
                if np.abs(step).max() == 1 and np.abs(step).sum() < 3 and not face_path:
                    expected.add((i, j))
                continue
            n, f = (i, j) if level[j] > level[i] else (j, i)
            if level[f] != level[n] + 1:
                continue
            own = size * 2 ** level[n]
            centre = np.linalg.norm((coords[n] + 0.5) * own)
            touches = ((2 * coords[f] - 1 <= coords[n]) & (coords[n] <= 2 * coords[f] + 2)).all()
            if touches and centre >= ranges[level[n]] - 2 * np.sqrt(3) * own:
                expected.add((min(i, j), max(i, j)))
    # a voxel still without an edge, in order: one to the nearest of its size within two voxels
    # (ties in the order of (squared distance, dx, dy, dz))
    alone = 0
    for i in range(len(keys)):
        if any(i in pair for pair in expected):
            continue
        offsets = sorted(
            (int(d @ d), *d.tolist(), j)
            for j in range(len(keys))
            if level[j] == level[i] and np.abs(d := coords[j] - coords[i]).max() <= 2 and j != i
        )
        if offsets:
            expected.add((min(i, offsets[0][-1]), max(i, offsets[0][-1])))
            alone += 1
    assert found == expected, (sorted(found - expected)[:5], sorted(expected - found)[:5])
    assert set(level.tolist()) == set(range(len(tiers) + 1)) and alone > 0


def test_an_edge_neighbour_is_joined_only_where_no_face_path_is():
    # Voxels (0, 0, 0) and (1, 1, 0) share an edge: joined alone, not once (1, 0, 0) is there,
    # whose faces join them both.
    size = 1.0
    corner = np.array([[0.5, 0.5, 0.5], [1.5, 1.5, 0.5]])
    _, keys = _voxel_statistics(corner, size, np.zeros(3), NO_TIERS)
    assert len(_voxel_edges(keys, size, NO_TIERS)[0]) == 1
    _, keys = _voxel_statistics(np.vstack([corner, [1.5, 0.5, 0.5]]), size, np.zeros(3), NO_TIERS)
    eu, ev = _voxel_edges(keys, size, NO_TIERS)
    assert sorted(map(sorted, zip(eu.tolist(), ev.tolist()))) == [[0, 2], [1, 2]]


def test_pieces_are_scipys_connected_components():
    rng = np.random.default_rng(5)
    m = 300
    eu, ev = rng.integers(0, m, (2, 200)).astype(np.int32)
    piece, count = _pieces(m, eu, ev)
    n_expected, expected = connected_components(coo_matrix((np.ones(len(eu)), (eu, ev)), shape=(m, m)), directed=False)
    assert count == n_expected
    # the same partition, numbered in the order of each piece's first node
    assert (piece[np.unique(piece, return_index=True)[1]] == np.arange(count)).all()
    assert (np.unique(np.column_stack([piece, expected]), axis=0).shape[0]) == count


@functools.cache
def log_likelihood(s: tuple[float, ...], reg: float) -> float:
    """n log n - n/2 log det(Sigma + reg I) of a group's sums [n, sum x, upper sum x x^T] (a tuple:
    the rounds ask for the same group's again and again)."""
    n, mean = s[0], np.array(s[1:4]) / s[0]
    second = np.zeros((3, 3))
    second[np.triu_indices(3)] = s[4:]
    second = second + np.triu(second, 1).T
    cov = second / n - np.outer(mean, mean) + reg * np.eye(3)
    return n * np.log(n) - 0.5 * n * np.log(np.linalg.det(cov))


def reference_merge(sums, edges, n_groups, reg):
    """_merge's rounds with every cost and every cheapest neighbour recomputed from the groups."""
    groups = {v: sums[v].copy() for v in range(len(sums))}
    owner = np.arange(len(sums))
    neighbours = defaultdict(set)  # of each voxel
    for u, v in edges:
        neighbours[u].add(v)
        neighbours[v].add(u)

    def cost(a, b):
        return (
            log_likelihood(tuple(groups[a]), reg)
            + log_likelihood(tuple(groups[b]), reg)
            - log_likelihood(tuple(groups[a] + groups[b]), reg)
        )

    def cheapest(a):
        others = {owner[w] for v in np.flatnonzero(owner == a) for w in neighbours[v]} - {a}
        return min(((cost(a, b), b) for b in others), default=(np.inf, -1))

    while len(groups) > n_groups:
        best = {a: cheapest(a) for a in sorted(groups)}
        pairs = [(best[a][0], a, b) for a, (c, b) in best.items() if b > a and best[b][1] == a]
        if not pairs:
            break
        take = min(len(pairs), max(1, int(_MERGE_SHARE * (len(groups) - n_groups))))
        limit = np.inf if take == len(pairs) else sorted(c for c, _, _ in pairs)[take - 1]
        for c, a, b in pairs:
            if len(groups) <= n_groups or c > limit or cheapest(a) != (c, b) or cheapest(b)[1] != a:
                continue
            groups[a] = groups[a] + groups.pop(b)
            owner[owner == b] = a
    return np.array([groups[a] for a in sorted(groups)])


def test_merge_is_the_plain_rounds_of_mutual_cheapest_pairs():
    rng = np.random.default_rng(11)
    for trial in range(4):
        # A bent sheet and some clutter, in voxels of 0.2 m: groups of a few voxels each.
        u, w = rng.uniform(0, 2, (2, 600))
        sheet = np.column_stack([u, w, 0.3 * np.sin(3 * u) + rng.normal(0, 0.01, 600)])
        points = np.concatenate([sheet, rng.uniform(0, 2, (60, 3))])
        sums, keys = _voxel_statistics(points, 0.2, points[0].copy(), NO_TIERS)
        eu, ev = _voxel_edges(keys, 0.2, NO_TIERS)
        n_groups = [5, 20, 40, 80][trial]
        expected = reference_merge(sums, list(zip(eu.tolist(), ev.tolist())), n_groups, 1e-4)
        merged = sums.copy()
        group = _merge(merged, eu.copy(), ev.copy(), n_groups, 1e-4)
        roots = np.flatnonzero(group == np.arange(len(group)))
        assert np.allclose(merged[roots], expected, rtol=1e-10, atol=1e-10)
        assert (group[roots] == roots).all() and (group[group] == group).all()


def test_two_planes_meeting_at_a_corner_become_two_groups():
    # The classification likelihood merges the halves of a flat patch almost for free and pays
    # for the thickness a merge across the corner adds: K = 2 gives the two planes.
    rng = np.random.default_rng(2)
    floor = np.column_stack([rng.uniform(0, 3, 4000), rng.uniform(0, 3, 4000), rng.normal(0, 0.01, 4000)])
    wall = floor[:, [2, 1, 0]]
    points = np.concatenate([floor, wall])
    sums, keys = _voxel_statistics(points, 0.25, np.zeros(3), NO_TIERS)
    groups, group = merge_voxels(keys, sums, sums.copy(), 2, 1e-4, 0.25, NO_TIERS, 0)
    assert np.allclose(groups, [sums[group == g].sum(axis=0) for g in range(2)])
    assert len(groups) == 2 and np.allclose(groups.sum(axis=0), sums.sum(axis=0))
    for g in groups:
        mean = g[1:4] / g[0]
        assert g[0] > 3500 and (abs(mean[0]) < 0.2 or abs(mean[2]) < 0.2)  # centred on one plane


def test_sparse_scan_is_bridged_to_k_groups():
    # Rings 1 m apart on a floor (voxels 0.25 m): the neighbours leave one piece a ring, far more
    # than K; edges between pieces in neighbouring cells let the merge go on to K groups.
    rng = np.random.default_rng(9)
    radii = np.repeat(np.arange(2.0, 30.0, 1.0), 150)
    angle = rng.uniform(0, 2 * np.pi, len(radii))
    points = np.column_stack([radii * np.cos(angle), radii * np.sin(angle), rng.normal(-1, 0.01, len(radii))])
    tiers = np.array([12.0])
    sums, keys = _voxel_statistics(points, 0.25, np.zeros(3), tiers)
    eu, ev = _voxel_edges(keys, 0.25, tiers)
    assert _pieces(len(keys), eu, ev)[1] > 200
    groups, _ = merge_voxels(keys, sums, sums.copy(), 20, 1e-4, 0.25, tiers, 0)
    assert len(groups) == 20 and np.allclose(groups.sum(axis=0), sums.sum(axis=0))
    assert (
        len(merge_voxels(keys[:5], sums[:5], sums[:5].copy(), 20, 1e-4, 0.25, tiers, 0)[0]) == 5
    )  # fewer voxels than K


def test_merge_of_a_star_compacts_its_rows_and_stays_the_plain_rounds():
    # A hub with 80 leaves merges one leaf a round, each time writing the hub's row anew: 60 rows
    # of up to 80 edges overflow the pool of 8 edges per edge, which is compacted in place; which
    # leaves the hub takes depends on every cost read from the rows.
    from gmm_core import em

    rng = np.random.default_rng(4)
    sums = np.array([em._features(rng.normal(0, 1, (5, 3)) + rng.uniform(-3, 3, 3)).sum(axis=0) for _ in range(81)])
    eu = np.zeros(80, dtype=np.int32)
    ev = np.arange(1, 81, dtype=np.int32)
    expected = reference_merge(sums, list(zip(eu.tolist(), ev.tolist())), 20, 1e-4)
    merged = sums.copy()
    group = _merge(merged, eu, ev, 20, 1e-4)
    roots = np.flatnonzero(group == np.arange(81))
    assert len(roots) == 20 and np.allclose(merged[roots], expected, rtol=1e-10)
