"""A 3D scan's voxels: numbered by a hash table (one probe per point), and the sums of
[1, x, x x^T] of each voxel's points, the statistics the voxel fit works on (voxel_merge,
voxel_em).

Voxel coordinates are packed into one int64 key with the voxel's level: the voxels double in size
at each of a few ranges from the sensor (`tier_ranges`), where a scan's rings lie farther apart
(the sensor's footprint grows with range).
"""

from __future__ import annotations

import numpy as np
from numba import njit

# Voxel coordinates are packed into one int64 key, this many bits per axis (+-2^19 voxels from
# the origin: +-26 km at 5 cm), and above them the voxel's level l (its size 2^l the finest's;
# at most FINE_LEVELS + 1 = 3: the key stays below 2^62).
_KEY_BITS = 20
_LEVEL_SHIFT = 3 * _KEY_BITS
_KEY_OFFSET = 1 << (_KEY_BITS - 1)
_FIBONACCI_HASH = np.uint64(0x9E3779B97F4A7C15)
_FIRST_TABLE_BITS = 10  # the hash table grows from 1024 slots
# ... when more than this share of its slots is taken: at 1/4 instead of 1/2, numbering BALM #4's
# 85,655 points (7,464 voxels) takes 0.52 instead of 0.77 ms, fewer probes run past their slot
# (docs/BENCHMARKS.md, twentieth session).
_TABLE_LOAD = 4


# Within the fine range of a voxel fit, voxels of half the size, and within half of it a quarter:
# the voxel follows the sensor's footprint, which halves with the range. Kurt3D's 10,000-point
# subsample, no EM pass: one tier (0.125 m within 3 m) 0.045 nats a point below scikit-learn's EM,
# two 0.022, none 0.167 (docs/BENCHMARKS.md, thirty-seventh session).
FINE_LEVELS = 2


def voxel_tiers(voxel_size: float, fine_range: float, near_range: float) -> tuple[float, np.ndarray, int]:
    """The finest voxel (m), the ranges at which voxels double (m, increasing) and the level of
    `voxel_size` among them: voxels of `voxel_size` from `fine_range` to `near_range` (0 and inf:
    none), of twice the size beyond, and FINE_LEVELS tiers of halved voxels within."""
    fine = [fine_range / (1 << (FINE_LEVELS - 1 - level)) for level in range(FINE_LEVELS)] if fine_range > 0 else []
    ranges = np.array(fine + ([near_range] if near_range < np.inf else []), dtype=np.float64)
    if not fine_range < near_range:
        raise ValueError(f"voxels: fine_range {fine_range} m must lie within near_range {near_range} m")
    return voxel_size / (1 << len(fine)), ranges, len(fine)


@njit(cache=True, inline="always")
def _voxel_key(points, i, d, size, b0, b1, b2):
    """Voxel floor(x_i / (2^l size)) packed into one int64, _KEY_BITS per axis, offset by half their
    range, with its level l above them: l is how many of the squared ranges b0 <= b1 <= b2 (inf
    where there is no such tier) x_i lies beyond. `d`: the points' columns."""
    r2 = 0.0
    for a in range(d):
        r2 += points[i, a] * points[i, a]
    if not r2 < np.inf:  # NaN or inf in the point (em.checked_points' check, here at no extra pass)
        raise ValueError("voxels: points contain NaN or inf")
    # three scalars compared, no loop: with a loop over the bounds in an array, BALM #3's keys took
    # 966 instead of 383 us (docs/BENCHMARKS.md, thirty-seventh session)
    level = int(r2 > b0) + int(r2 > b1) + int(r2 > b2)
    size = size * (1 << level)
    key = 0
    for a in range(d):
        c = int(np.floor(points[i, a] / size)) + _KEY_OFFSET
        if c < 0 or c >= 2 * _KEY_OFFSET:
            raise ValueError("voxels: a point lies more than 2^19 voxels from the origin")
        key = (key << _KEY_BITS) + c
    return key + (level << _LEVEL_SHIFT)


@njit(cache=True)
def _hash_table(bits):
    """An open-addressing table of 2^bits slots: rows (key, -1 where empty; the key's voxel
    number), side by side so that a probe reads one cache line; and the shift of the hash."""
    return np.full((1 << bits, 2), -1, dtype=np.int64), np.uint64(64 - bits)


@njit(cache=True, inline="always")
def _voxel_number(table, shift, key, n_voxels):
    """The number of the voxel `key` (linear probing); a new key gets `n_voxels`."""
    mask = table.shape[0] - 1
    h = np.int64((np.uint64(key) * _FIBONACCI_HASH) >> shift)
    while table[h, 0] != -1 and table[h, 0] != key:
        h = (h + 1) & mask
    if table[h, 0] == -1:
        table[h, 0] = key
        table[h, 1] = n_voxels
    return table[h, 1]


@njit(cache=True, inline="always")
def _lookup(table, shift, key):
    """The number of the voxel `key`, -1 where it is not in the table."""
    mask = table.shape[0] - 1
    h = np.int64((np.uint64(key) * _FIBONACCI_HASH) >> shift)
    while table[h, 0] != -1:
        if table[h, 0] == key:
            return table[h, 1]
        h = (h + 1) & mask
    return -1


@njit(cache=True)
def _table_of(keys):
    """A table of distinct `keys`, each numbered by its place in them, at 1 / 4 load; and its shift."""
    bits = 4
    while (1 << bits) < 4 * keys.shape[0]:
        bits += 1
    table, shift = _hash_table(bits)
    for i in range(keys.shape[0]):
        _voxel_number(table, shift, keys[i], i)
    return table, shift


@njit(cache=True)
def _grown(table, n_voxels):
    """`table` with room for twice `n_voxels` at 1 / _TABLE_LOAD: the table stays as small as the
    voxels (a few hundred KB for a lidar scan's), not as the points, and so in cache."""
    bits = 4
    while (1 << bits) < 2 * _TABLE_LOAD * n_voxels:
        bits += 1
    grown, shift = _hash_table(bits)
    for h in range(table.shape[0]):
        if table[h, 0] != -1:
            _voxel_number(grown, shift, table[h, 0], table[h, 1])
    return grown, shift


@njit(cache=True)
def _numbered(keys):
    """Each key's number among the distinct keys, in the order they first come (n,), and how many
    distinct keys there are: one hash probe per key."""
    numbers = np.empty(keys.shape[0], dtype=np.int64)
    table, shift = _hash_table(_FIRST_TABLE_BITS)
    i, count = 0, 0
    while i < keys.shape[0]:
        # The table grows here, between calls: an array assigned in a loop costs numba an atomic
        # increment and decrement of its reference count per pass (docs/BENCHMARKS.md, twelfth
        # session), so the loop over the keys does not assign it.
        i, count = _number_until_full(keys, i, table, shift, numbers, count)
        if i < keys.shape[0]:
            table, shift = _grown(table, count)
    return numbers, count


@njit(cache=True)
def _number_until_full(keys, i, table, shift, numbers, count):
    """_numbered's numbers of keys i, i + 1, ... until the last key or a table over 1 / _TABLE_LOAD full;
    returns the next key and the count so far."""
    while i < keys.shape[0]:
        numbers[i] = _voxel_number(table, shift, keys[i], count)
        if numbers[i] == count:
            count += 1
        i += 1
        if _TABLE_LOAD * count > table.shape[0]:
            break
    return i, count


@njit(cache=True)
def count_voxels(points, size):
    """How many voxels floor(x / size) the (n, d) points occupy (np.unique of them)."""
    keys = np.empty(points.shape[0], dtype=np.int64)
    for i in range(points.shape[0]):
        keys[i] = _voxel_key(points, i, points.shape[1], size, np.inf, np.inf, np.inf)
    return _numbered(keys)[1]


# Points are voxelised in blocks of this many: a block's keys are hashed and its points summed while
# they are still in cache. A pass of keys over the whole scan and then one of sums read the points
# twice from memory when OctoMap's insertion (or anything else) has left the caches cold: BALM's 15
# scans 1.27x faster cold, the same warm (0.98x) (docs/BENCHMARKS.md, twenty-fifth session).
_BLOCK = 1024


@njit(cache=True)
def _voxel_statistics(points, voxel_size, shift, tier_ranges):
    """Per occupied voxel floor(x / (2^l voxel_size)), l the number of the increasing ranges
    `tier_ranges` (m, as voxel_tiers gives them) the point lies beyond from the origin, the sums of
    em._features of x - shift over its points (M, f) and its key (M,), voxels in the order of their
    first point: one hash probe per point. The voxels are those of the points' frame; `shift` (near
    the points) keeps the second moments precise."""
    n, d = points.shape
    if tier_ranges.shape[0] > FINE_LEVELS + 1:
        raise ValueError("voxels: more tiers than voxel_tiers makes")
    bounds = np.full(FINE_LEVELS + 1, np.inf)
    bounds[: tier_ranges.shape[0]] = tier_ranges * tier_ranges
    # room for a voxel a point: the rows past the voxels' count are never written (nor faulted in)
    sums = np.empty((n, 1 + d + d * (d + 1) // 2))
    keys = np.empty(n, dtype=np.int64)
    block_keys = np.empty(_BLOCK, dtype=np.int64)
    numbers = np.empty(_BLOCK, dtype=np.int64)
    table, hash_shift = _hash_table(_FIRST_TABLE_BITS)
    count = 0
    for start in range(0, n, _BLOCK):
        stop = min(start + _BLOCK, n)
        _block_keys(points, start, stop, voxel_size, bounds[0], bounds[1], bounds[2], block_keys)
        made = count
        i, size = 0, stop - start
        while i < size:
            # the table grows here, between calls (see _numbered)
            i, count = _number_until_full(block_keys[:size], i, table, hash_shift, numbers, count)
            if i < size:
                table, hash_shift = _grown(table, count)
        _add_block(points, start, stop, shift, block_keys, numbers, made, sums, keys)
    return sums[:count], keys[:count]


@njit(cache=True)
def _block_keys(points, start, stop, size, b0, b1, b2, out):
    """The voxel keys of points start .. stop - 1 (out[0 .. stop - start - 1])."""
    # The dimension as a constant in each branch: the loops over the axes compile unrolled, 1.5x
    # faster than with the columns read from the array (docs/BENCHMARKS.md, tenth session).
    if points.shape[1] == 3:
        for i in range(start, stop):
            out[i - start] = _voxel_key(points, i, 3, size, b0, b1, b2)
    else:
        for i in range(start, stop):
            out[i - start] = _voxel_key(points, i, 2, size, b0, b1, b2)


@njit(cache=True)
def _add_block(points, start, stop, shift, block_keys, numbers, made, sums, keys):
    """Adds points start .. stop - 1 (their voxels `numbers`, those from `made` on new, in order)
    to the sums; a new voxel's row is set, and its key kept."""
    if points.shape[1] == 3:
        _add_points(points, 3, start, stop, shift, block_keys, numbers, made, sums, keys)
    else:
        _add_points(points, 2, start, stop, shift, block_keys, numbers, made, sums, keys)


@njit(cache=True, inline="always")
def _add_points(points, d, start, stop, shift, block_keys, numbers, made, sums, keys):
    for i in range(start, stop):
        v = numbers[i - start]
        if v == made:  # numbers are handed out in order: the voxel's first point
            keys[v] = block_keys[i - start]
            for q in range(sums.shape[1]):
                sums[v, q] = 0.0
            made += 1
        # the point's coordinates as locals, not in an array the compiler must assume sums may overwrite
        x0 = points[i, 0] - shift[0]
        x1 = points[i, 1] - shift[1]
        x2 = points[i, 2] - shift[2] if d == 3 else 0.0
        sums[v, 0] += 1.0
        sums[v, 1] += x0
        sums[v, 2] += x1
        if d == 3:
            sums[v, 3] += x2
            sums[v, 4] += x0 * x0
            sums[v, 5] += x0 * x1
            sums[v, 6] += x0 * x2
            sums[v, 7] += x1 * x1
            sums[v, 8] += x1 * x2
            sums[v, 9] += x2 * x2
        else:
            sums[v, 3] += x0 * x0
            sums[v, 4] += x0 * x1
            sums[v, 5] += x1 * x1


@njit(cache=True)
def _count_cells(keys, d, ratio):
    """How many cells of `ratio` x `ratio` finest voxels (the grid of the voxel keys, d axes;
    `ratio` a multiple of 2^l where voxels of level l are among them) hold one of the voxels `keys`:
    count_voxels(points, ratio * voxel_size) from the voxels, not the points
    (floor(floor(x / s) / r) = floor(x / (r s)); exact in floating point when r and s are powers
    of two, as 4 and 0.25 m)."""
    mask = (1 << _KEY_BITS) - 1
    cells = np.empty(keys.shape[0], dtype=np.int64)
    for v in range(keys.shape[0]):
        per_cell = ratio >> (keys[v] >> _LEVEL_SHIFT)
        cell = 0
        for a in range(d):
            c = (keys[v] >> (_KEY_BITS * (d - 1 - a))) & mask
            cell = (cell << _KEY_BITS) + (c - _KEY_OFFSET) // per_cell + _KEY_OFFSET
        cells[v] = cell
    return _numbered(cells)[1]


@njit(cache=True)
def _means_and_scatter(sums):
    """Each group's mean and its scatter (covariance of its points, upper triangle) from its sums."""
    m, f = sums.shape
    d = 3 if f == 10 else 2
    means = np.empty((m, d))
    scatter = np.empty((m, d * (d + 1) // 2))
    for v in range(m):
        n = sums[v, 0]
        for a in range(d):
            means[v, a] = sums[v, 1 + a] / n
        j = 1 + d
        for a in range(d):
            for b in range(a, d):
                s = sums[v, j] / n - means[v, a] * means[v, b]
                scatter[v, j - 1 - d] = max(s, 0.0) if a == b else s
                j += 1
    return means, scatter
