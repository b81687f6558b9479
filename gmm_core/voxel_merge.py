"""A scan's voxels grouped bottom-up into the components of its mixture.

Each voxel starts as a group with its summed statistics [n, sum x, sum x x^T] (voxels.py); neighbouring
groups are merged, the cheapest first, until K are left. The cost of a merge is what it takes from the
classification log-likelihood of the points, each point counted under its own group's Gaussian
with its weight n / N (the mixture's Eq. 1 with hard assignments):

    l(A) = n_A log n_A - n_A / 2 log det(Sigma_A),    cost(A, B) = l(A) + l(B) - l(A u B),

less terms linear in n, which cancel (Sigma with the M-step's regulariser). So two halves of one
flat patch merge at almost no cost, while a patch merged across a corner or a gap pays for the
thickness it gains: the K Gaussians go where the surfaces bend, as scikit-learn's EM puts them
after tens of passes (docs/BENCHMARKS.md, twenty-second session), instead of being spread by size.
It is agglomerative clustering with a Gaussian likelihood linkage (Ward's method is its isotropic
form), restricted to the voxel grid's neighbours as in Felzenszwalb & Huttenlocher's graph-based
segmentation.

The merges run in rounds: in each, the groups that are each other's cheapest neighbour (mutual
pairs, which a greedy merge order would merge before anything they touch) are merged, the cheapest
first, at most _MERGE_SHARE of the merges still to make; costs are kept per edge and updated for
the edges of a merged group only. Where the voxels that touch leave more separate pieces than
K / 4 (sparse scans: rings farther apart than a voxel), pieces with voxels in the same or
neighbouring cells of 2, 4 and 8 voxels, and of more while the pieces outnumber K, are joined by an
edge before the merging starts.

The likelihood counts points, not surface: along a lidar ring a group stays thin, so the cheapest
merges would follow the rings. The costs are therefore taken on the voxel sums with their points'
footprint across the rings added (rings.py); the groups' statistics are the points' own.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from gmm_core.selection import kth_smallest
from gmm_core.voxels import _KEY_BITS, _KEY_OFFSET, _LEVEL_SHIFT, _lookup, _numbered, _table_of

# Each round merges at most this share of the merges still to make: 0.1 / 0.25 / 0.5 / 1 gave a
# log-likelihood per point of -1.849 / -1.849 / -1.861 / -1.966 on BALM #0 in 8.4 / 7.1 / 6.6 /
# 6.5 ms (docs/BENCHMARKS.md, twenty-second session).
_MERGE_SHARE = 0.25
# Where the voxels' neighbours leave more separate pieces than this share of K (a sparse scan's
# rings), pieces in neighbouring cells of 2, 4, ... voxels are joined by an edge each before
# merging: the cheapest merges across a gap are then taken in their turn, not after each piece
# has been merged into one group.
_BRIDGED_PIECES = 0.25
# ... in cells of at most 2^this base voxels (2 m at 0.25 m): pieces farther apart are separate
# things, bridged only while they outnumber K. A bridge between two single points is cheap however
# long it is (two points make a line of no width), so a bridge between far pieces could join two
# objects (5 blobs 11-40 m apart, each with a few stray points: two joined at level 8;
# test_voxel_em's well separated clusters).
_BRIDGED_LEVELS = 3
_MASK = (1 << _KEY_BITS) - 1


def _key_changes(offsets) -> np.ndarray:
    """What adding each (dx, dy, dz) to a voxel's (or cell's) coordinates adds to its key: the
    neighbours' keys without decoding (no coordinate is near the ends of its _KEY_BITS)."""
    return np.array([(dx << (2 * _KEY_BITS)) + (dy << _KEY_BITS) + dz for dx, dy, dz in offsets], dtype=np.int64)


_CUBE = [(dx, dy, dz) for dx in range(-2, 3) for dy in range(-2, 3) for dz in range(-2, 3)]  # lexicographic
# The forward half of a voxel's 18 neighbours (each pair of voxels once): those sharing a face or
# an edge. The 8 that share a corner only add a quarter of the edges (BALM #4: 34,344 against
# 26,785) and change the likelihood by less than 0.01 nats a point (docs/BENCHMARKS.md,
# twenty-third session).
_FORWARD_STEPS = [o for o in _CUBE if o > (0, 0, 0) and max(map(abs, o)) == 1 and sum(map(abs, o)) < 3]
_FORWARD = _key_changes(_FORWARD_STEPS)


def _face_steps(step: tuple[int, int, int]) -> list[tuple[int, int, int]]:
    """The two face steps an edge step is the sum of; (0, 0, 0) twice for a face step."""
    dx, dy, dz = step
    parts = [p for p in ((dx, 0, 0), (0, dy, 0), (0, 0, dz)) if p != (0, 0, 0)]
    return parts if len(parts) == 2 else [(0, 0, 0), (0, 0, 0)]


# Two voxels sharing an edge are joined only where neither voxel that shares a face with both is
# there: a surface's voxels are joined through their faces, and an edge joins what nothing else
# does (a thin diagonal structure). A group then grows across a surface face by face instead of
# cutting its corners, and a merge recosts a third fewer edges: the fit 1.21x faster for 0.022
# nats a point on BALM (1.1 %), the maps the same (docs/BENCHMARKS.md, thirty-sixth session).
_FACE_PATHS = np.array([_key_changes(_face_steps(o)) for o in _FORWARD_STEPS], dtype=np.int64)
# ... and the voxels within two that share no face or edge, the nearest first: a voxel with none of
# its 18 neighbours (a stray return, a lone point of a far ring) is joined to the nearest of them,
# else it ends a component of its own (BALM #4: 38 of 1077 were single points).
_NEAREST = _key_changes(
    sorted(
        (o for o in _CUBE if max(map(abs, o)) == 2 or sum(map(abs, o)) == 3),
        key=lambda o: (o[0] ** 2 + o[1] ** 2 + o[2] ** 2, o),
    )
)
# A cell itself and the forward half of its 26 neighbours (_bridges).
_CELL_FORWARD = _key_changes(o for o in _CUBE if o >= (0, 0, 0) and max(map(abs, o)) <= 1)


@njit(cache=True, inline="always")
def _log_likelihood(s0, s1, s2, s3, s4, s5, s6, s7, s8, s9, reg):
    """l = n log n - n/2 log det(Sigma + reg I) of a group from its sums (n, sum x, upper
    triangle of sum x x^T), as -n/2 log(det / n^2)."""
    inv = 1.0 / s0
    m0, m1, m2 = s1 * inv, s2 * inv, s3 * inv
    c00 = s4 * inv - m0 * m0 + reg
    c01 = s5 * inv - m0 * m1
    c02 = s6 * inv - m0 * m2
    c11 = s7 * inv - m1 * m1 + reg
    c12 = s8 * inv - m1 * m2
    c22 = s9 * inv - m2 * m2 + reg
    det = c00 * (c11 * c22 - c12 * c12) - c01 * (c01 * c22 - c12 * c02) + c02 * (c01 * c12 - c11 * c02)
    return -0.5 * s0 * np.log(det * inv * inv)


@njit(cache=True, inline="always")
def _group(sums, a, reg):
    # sums[a, q], not a row view sums[a]: a view in a loop costs numba a reference count (ARCHITECTURE.md)
    return _log_likelihood(
        sums[a, 0], sums[a, 1], sums[a, 2], sums[a, 3], sums[a, 4], sums[a, 5], sums[a, 6], sums[a, 7], sums[a, 8],
        sums[a, 9], reg,
    )  # fmt: skip


@njit(cache=True, inline="always")
def _merged(sums, a, b, reg):
    return _log_likelihood(
        sums[a, 0] + sums[b, 0], sums[a, 1] + sums[b, 1], sums[a, 2] + sums[b, 2], sums[a, 3] + sums[b, 3],
        sums[a, 4] + sums[b, 4], sums[a, 5] + sums[b, 5], sums[a, 6] + sums[b, 6], sums[a, 7] + sums[b, 7],
        sums[a, 8] + sums[b, 8], sums[a, 9] + sums[b, 9], reg,
    )  # fmt: skip


@njit(cache=True, inline="always")
def _cell(keys, v, level):
    """The (x, y, z) of voxel v in units of the finest voxels (a larger voxel: its lowest corner),
    shifted right by `level` (cells of 2^level finest voxels)."""
    key = keys[v]
    own = key >> _LEVEL_SHIFT
    x = (((key >> (2 * _KEY_BITS)) & _MASK) - _KEY_OFFSET) << own
    y = (((key >> _KEY_BITS) & _MASK) - _KEY_OFFSET) << own
    z = ((key & _MASK) - _KEY_OFFSET) << own
    return x >> level, y >> level, z >> level


@njit(cache=True, inline="always")
def _key_of(x, y, z, level):
    return (((x + _KEY_OFFSET) << (2 * _KEY_BITS)) + ((y + _KEY_OFFSET) << _KEY_BITS) + z + _KEY_OFFSET) + (
        level << _LEVEL_SHIFT
    )


@njit(cache=True)
def _voxel_edges(keys, voxel_size, tier_ranges):
    """Pairs of neighbouring voxels (eu, ev): the 18 neighbours of a voxel (sharing a face or an
    edge) among those of its size, an edge neighbour only where no voxel shares a face with both
    (_FACE_PATHS), and, for a voxel at the outer range of its tier (`tier_ranges`, voxels of
    `voxel_size` within the first), the voxels of the next tier it touches; a voxel with none of
    these, to the nearest voxel of its size within two."""
    m = keys.shape[0]
    table, shift = _table_of(keys)
    # at most 9 forward neighbours, 8 voxels of the next tier and 1 nearest a voxel; the pages never
    # written cost nothing (an array assigned in the loop, to grow it, would cost numba a reference count)
    eu = np.empty(18 * m, dtype=np.int32)
    ev = np.empty(18 * m, dtype=np.int32)
    n = 0
    # a voxel's centre this far inside its tier's outer range may touch a voxel of the next tier
    boundary = np.empty(tier_ranges.shape[0])
    for level in range(tier_ranges.shape[0]):
        boundary[level] = max(tier_ranges[level] - 2.0 * np.sqrt(3.0) * voxel_size * (1 << level), 0.0)
    touched = np.empty(8, dtype=np.int64)
    for v in range(m):
        for d in range(_FORWARD.shape[0]):
            u = _lookup(table, shift, keys[v] + _FORWARD[d])
            if u < 0 or (
                _FACE_PATHS[d, 0] != 0
                and (
                    _lookup(table, shift, keys[v] + _FACE_PATHS[d, 0]) >= 0
                    or _lookup(table, shift, keys[v] + _FACE_PATHS[d, 1]) >= 0
                )
            ):
                continue
            eu[n], ev[n] = v, u
            n += 1
        level = keys[v] >> _LEVEL_SHIFT
        if level < tier_ranges.shape[0]:
            c = _cell(keys, v, level)  # in its own voxels
            size = voxel_size * (1 << level)
            r2 = ((c[0] + 0.5) ** 2 + (c[1] + 0.5) ** 2 + (c[2] + 0.5) ** 2) * size * size
            if r2 >= boundary[level] * boundary[level]:
                count = 0
                for d in range(27):
                    dx, dy, dz = d // 9 - 1, (d // 3) % 3 - 1, d % 3 - 1
                    up = _key_of((c[0] + dx) >> 1, (c[1] + dy) >> 1, (c[2] + dz) >> 1, level + 1)
                    u = _lookup(table, shift, up)
                    if u < 0 or _listed(touched, count, u):
                        continue
                    touched[count] = u
                    count += 1
                    eu[n], ev[n] = v, u
                    n += 1
    degree = np.zeros(m, dtype=np.int64)
    for e in range(n):
        degree[eu[e]] += 1
        degree[ev[e]] += 1
    for v in range(m):
        if degree[v] == 0:
            for delta in _NEAREST:
                u = _lookup(table, shift, keys[v] + delta)
                if u >= 0:
                    eu[n], ev[n] = v, u
                    n += 1
                    degree[u] += 1  # no longer alone: it looks for no edge of its own
                    break
    return eu[:n].copy(), ev[:n].copy()


@njit(cache=True, inline="always")
def _listed(values, count, u):
    for i in range(count):
        if values[i] == u:
            return True
    return False


@njit(cache=True)
def _pieces(m, eu, ev):
    """The connected pieces of the graph of m nodes and edges (eu, ev): each node's piece, 0 .. P - 1, and P."""
    root = np.arange(m)
    for e in range(eu.shape[0]):
        a, b = _root(root, eu[e]), _root(root, ev[e])
        if a != b:
            root[max(a, b)] = min(a, b)  # a piece's root is its first node
    piece = np.empty(m, dtype=np.int64)
    count = 0
    for v in range(m):
        if root[v] == v:
            piece[v] = count
            count += 1
        else:
            piece[v] = piece[_root(root, v)]
    return piece, count


@njit(cache=True, inline="always")
def _root(root, v):
    """The root of v's tree, halving the path on the way (union-find)."""
    while root[v] != v:
        root[v] = root[root[v]]
        v = root[v]
    return v


@njit(cache=True)
def _bridges(keys, piece, n_pieces, level):
    """Edges between pieces (`piece` of each voxel, 0 .. n_pieces - 1) with voxels in one cell of
    2^level finest voxels or in two neighbouring ones: one edge a pair of pieces, between the first
    voxels of each piece in such cells."""
    m = keys.shape[0]
    cell_keys = np.empty(m, dtype=np.int64)
    for v in range(m):
        x, y, z = _cell(keys, v, level)
        cell_keys[v] = _key_of(x, y, z, 0)
    cell_of, n_cells = _numbered(cell_keys)
    # the distinct (cell, piece) pairs, grouped by cell, each with its first voxel
    member_of, n_members = _numbered(cell_of * n_pieces + piece)
    first_key = np.empty(n_cells, dtype=np.int64)
    cell_start = np.zeros(n_cells + 1, dtype=np.int64)
    voxel_of = np.full(n_members, -1, dtype=np.int64)
    for v in range(m):
        first_key[cell_of[v]] = cell_keys[v]
        if voxel_of[member_of[v]] < 0:
            voxel_of[member_of[v]] = v
            cell_start[cell_of[v] + 1] += 1
    for c in range(n_cells):
        cell_start[c + 1] += cell_start[c]
    members = np.empty(n_members, dtype=np.int64)
    filled = cell_start[:-1].copy()
    for i in range(n_members):
        members[filled[cell_of[voxel_of[i]]]] = voxel_of[i]
        filled[cell_of[voxel_of[i]]] += 1
    table, shift = _table_of(first_key)
    neighbour = np.full((n_cells, _CELL_FORWARD.shape[0]), -1, dtype=np.int64)
    size = 0
    for c in range(n_cells):
        for d in range(_CELL_FORWARD.shape[0]):
            other = _lookup(table, shift, first_key[c] + _CELL_FORWARD[d])
            neighbour[c, d] = other
            if other >= 0:
                size += (cell_start[c + 1] - cell_start[c]) * (cell_start[other + 1] - cell_start[other])
    eu = np.empty(size, dtype=np.int32)
    ev = np.empty(size, dtype=np.int32)
    pair = np.empty(size, dtype=np.int64)
    n = 0
    for c in range(n_cells):
        for other in neighbour[c]:
            if other < 0:
                continue
            for i in range(cell_start[c], cell_start[c + 1]):
                for j in range(cell_start[other], cell_start[other + 1]):
                    a, b = piece[members[i]], piece[members[j]]
                    if a == b:
                        continue
                    eu[n], ev[n] = members[i], members[j]
                    pair[n] = min(a, b) * n_pieces + max(a, b)
                    n += 1
    pair_of, n_pairs = _numbered(pair[:n])
    keep = np.empty(n_pairs, dtype=np.int64)
    taken = 0
    for i in range(n):
        if pair_of[i] == taken:  # numbers are handed out in order: a first occurrence
            keep[taken] = i
            taken += 1
    return eu[keep], ev[keep]


@njit(cache=True, inline="always")
def _best_again(x, pool, row_start, row_len, dead, cost, eu, ev, best, best_to):
    """x's cheapest edge from the costs kept per edge; x's row loses its dead edges."""
    bx, bt = np.inf, -1
    n = 0
    for i in range(row_len[x]):
        e = pool[row_start[x] + i]
        if dead[e]:
            continue
        pool[row_start[x] + n] = e
        n += 1
        if cost[e] < bx:
            bx, bt = cost[e], (ev[e] if eu[e] == x else eu[e])
    row_len[x] = n
    best[x], best_to[x] = bx, bt


@njit(cache=True)
def _compacted(pool, row_start, row_len, nodes, group):
    """The rows of the groups among `nodes` moved to the front of `pool`, in the order they lie in it
    (each moves down, so none overwrites a row not yet moved); returns the end of the last."""
    roots = np.array([v for v in nodes if group[v] == v])
    end = 0
    for v in roots[np.argsort(row_start[roots])]:
        pool[end : end + row_len[v]] = pool[row_start[v] : row_start[v] + row_len[v]].copy()
        row_start[v] = end
        end += row_len[v]
    return end


@njit(cache=True)
def _merge(sums, eu, ev, n_groups, reg_covar):
    """Merges the nodes (rows of `sums`, added up in place) along the edges (eu, ev; changed) until
    `n_groups` are left or no edge is; returns each node's group (the node that holds its sums)."""
    m, n_edges = sums.shape[0], eu.shape[0]
    ll = np.empty(m)
    for v in range(m):
        ll[v] = _group(sums, v, reg_covar)
    cost = np.empty(n_edges)
    dead = np.zeros(n_edges, dtype=np.bool_)
    best = np.full(m, np.inf)
    best_to = np.full(m, -1, dtype=np.int64)
    row_len = np.zeros(m, dtype=np.int64)
    for e in range(n_edges):
        a, b = eu[e], ev[e]
        c = ll[a] + ll[b] - _merged(sums, a, b, reg_covar)
        cost[e] = c
        row_len[a] += 1
        row_len[b] += 1
        if c < best[a]:
            best[a], best_to[a] = c, b
        if c < best[b]:
            best[b], best_to[b] = c, a
    # Each node's row of edge numbers in one pool; a merged group's row is written at its end.
    row_start = np.empty(m, dtype=np.int64)
    end = 0
    for v in range(m):
        row_start[v] = end
        end += row_len[v]
        row_len[v] = 0
    pool = np.empty(8 * n_edges + 16, dtype=np.int32)  # rows written after merges go on at the end
    for e in range(n_edges):
        for a in (eu[e], ev[e]):
            pool[row_start[a] + row_len[a]] = e
            row_len[a] += 1
    group = np.arange(m)
    mark = np.full(m, -1, dtype=np.int64)
    live = np.arange(m)
    n_live, count, stamp = m, m, 0
    pairs = np.empty(m, dtype=np.int64)
    pair_cost = np.empty(m)
    while count > n_groups:
        n_pairs, kept = 0, 0
        for i in range(n_live):
            x = live[i]
            if group[x] != x:
                continue
            live[kept] = x
            kept += 1
            y = best_to[x]
            if y >= 0 and best_to[y] == x and x < y:
                pairs[n_pairs] = x
                pair_cost[n_pairs] = best[x]
                n_pairs += 1
        n_live = kept
        if n_pairs == 0:
            break
        take = min(n_pairs, max(1, int(_MERGE_SHARE * (count - n_groups))))
        limit = np.inf if take == n_pairs else kth_smallest(pair_cost[:n_pairs].copy(), take - 1)
        for i in range(n_pairs):
            x = pairs[i]
            p = best_to[x]
            # a pair an earlier merge of this round changed waits for the next round
            if count <= n_groups or pair_cost[i] > limit or best[x] != pair_cost[i] or p < 0 or best_to[p] != x:
                continue
            if end + row_len[x] + row_len[p] > pool.shape[0]:
                end = _compacted(pool, row_start, row_len, live[:n_live], group)
            for q in range(sums.shape[1]):
                sums[x, q] += sums[p, q]
            ll[x] = _group(sums, x, reg_covar)
            group[p] = x
            count -= 1
            stamp += 1
            mark[x] = stamp
            mark[p] = stamp
            start, n = end, 0
            bx, bt = np.inf, -1
            for u in (x, p):
                for j in range(row_len[u]):
                    e = pool[row_start[u] + j]
                    if dead[e]:
                        continue
                    y = ev[e] if eu[e] == u else eu[e]
                    if mark[y] == stamp:  # the edge x - p, or a second edge to y
                        dead[e] = True
                        continue
                    mark[y] = stamp
                    eu[e], ev[e] = x, y
                    c = ll[x] + ll[y] - _merged(sums, x, y, reg_covar)
                    cost[e] = c
                    pool[start + n] = e
                    n += 1
                    if c < bx:
                        bx, bt = c, y
                    if c < best[y]:
                        best[y], best_to[y] = c, x
                    elif best_to[y] == x or best_to[y] == p:
                        best_to[y] = -2  # its cheapest edge is found again once x's row is written
            row_start[x], row_len[x] = start, n
            end += n
            best[x], best_to[x] = bx, bt
            for j in range(n):
                y = ev[pool[start + j]]
                if best_to[y] == -2:
                    _best_again(y, pool, row_start, row_len, dead, cost, eu, ev, best, best_to)
    for v in range(m):
        root = v
        while group[root] != root:
            root = group[root]
        group[v] = root
    return group


@njit(cache=True)
def merge_voxels(keys, sums, costed, n_groups, reg_covar, voxel_size, tier_ranges, base_level):
    """The summed statistics (G, 10) of at most `n_groups` groups of the voxels (`keys`, `sums`
    as voxels._voxel_statistics gives them with `voxel_size` and `tier_ranges`), fewer only when
    there are fewer voxels, and each voxel's group (M,). The merge costs are those of `costed` (the
    sums with their footprint across a lidar's rings, rings.py; changed), the groups' statistics
    `sums`'. Pieces are bridged in cells of 2, 4, ... base voxels (2^base_level finest ones)."""
    m = keys.shape[0]
    eu, ev = _voxel_edges(keys, voxel_size, tier_ranges)
    piece, n_pieces = _pieces(m, eu, ev)
    level = base_level + 1
    while level <= 2 * _KEY_BITS and (
        n_pieces > n_groups or (n_pieces > _BRIDGED_PIECES * n_groups and level <= base_level + _BRIDGED_LEVELS)
    ):
        bu, bv = _bridges(keys, piece, n_pieces, level)
        eu, ev = np.concatenate((eu, bu)), np.concatenate((ev, bv))
        piece, n_pieces = _pieces(m, eu, ev)
        level += 1
    group = _merge(costed, eu, ev, n_groups, reg_covar)
    index = np.full(m, -1, dtype=np.int64)
    count = 0
    for v in range(m):
        if group[v] == v:
            index[v] = count
            count += 1
    grouped = np.zeros((count, sums.shape[1]))
    for v in range(m):
        group[v] = index[group[v]]
        for q in range(sums.shape[1]):
            grouped[group[v], q] += sums[v, q]
    return grouped, group
