"""A 3D scan's mixture from the sufficient statistics of a fine voxelisation, at sensor rate.

Three steps:

1. The points' voxels of size `voxel_size` are numbered and [1, x, x x^T] is summed per voxel
   (voxels.py).
2. The voxels are merged bottom-up into K groups, the merge that costs the classification
   log-likelihood least first (voxel_merge.py; the costs see a lidar's footprint across its
   rings, rings.py); the groups' summed statistics give the
   parameters (M-step, Sec. III-A). This alone ends above scikit-learn's converged EM with the
   same K on dense scans (docs/BENCHMARKS.md, twenty-second session).
3. Optionally (`max_iter` > 0), truncated EM on the voxels as weighted points (Verbeek, Nunnink &
   Vlassis 2006): a voxel's points share one responsibility, the E-step scores the voxel's mean
   and adds the trace of its scatter, the M-step sums its statistics; each voxel's
   responsibility is spread over its few most likely components, found by a search on a few
   passes and only re-scored on the others (Luecke & Eggert 2010). Each pass does not lower a
   bound on the points' log-likelihood, at the cost of M voxels times a few components instead
   of N points times about ten. From the third pass the M-step is over-relaxed (Salakhutdinov &
   Roweis 2003): a block's sums move _OVERRELAXATION times as far as EM's step would.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from gmm_core import em
from gmm_core.hash_grid import _block_cell_order, _candidates, _hash_grid
from gmm_core.mixture import Mixture
from gmm_core.rings import ring_spacing, with_footprint
from gmm_core.voxel_merge import merge_voxels
from gmm_core.voxels import _count_cells, _means_and_scatter, _voxel_statistics, count_voxels, voxel_tiers

_N_FEATURES = 10  # [1, x, upper triangle of x x^T] of a 3D point (em._features)
# Truncated EM (_voxel_em): a voxel's responsibility is spread over at most this many components,
# found on the first pass by a search of the components whose box of this many sigmas reaches the
# voxel's hash cell. Mean log-likelihood per point on three BALM scans after 8 passes (issue 15
# part 2): untruncated EM on the voxels -2.484; searching on passes 1, 2, 4 and 8: -2.496; on 1
# and 3: -2.514; on 1 only: -2.552, and -2.520 when keeping 8 components instead of 4. A search
# pass costs about three passes over the kept components, so one search and 10 passes beat two
# searches and 8 passes on every measure (docs/BENCHMARKS.md, issue 15 part 3).
_KEPT_COMPONENTS = 4
_SEARCH_BOX_SIGMAS = 3.0
# Over-relaxed M-step (_voxel_em): each block's sums move this many times the change of an EM
# step, from the third pass on (Salakhutdinov & Roweis, ICML 2003). On the 15 BALM scans, 8 such
# passes end 0.017-0.044 nats a point above 10 plain passes, the fit 1.08x faster; 10 such passes
# gain 0.04-0.10 on 10 plain ones; 2.5 instead of 1.9 overshoots (docs/BENCHMARKS.md, eighteenth
# session; measured from the old top-down split). From the merged voxels, EM is near its end at
# once: 8 such passes and 8 plain ones end within 0.003 of each other on BALM #0-#2 (twenty-second
# session). After a pass whose bound falls, plain EM.
_OVERRELAXATION = 1.9
# Hash grid and blocks of the voxel EM: as em._refine's for points, with more cells (voxels are
# sparse in the box of a scan) and smaller blocks (a voxel stands for several points).
_CELLS_PER_VOXEL = 8
_BLOCK_VOXELS_PER_COMPONENT = 2
_ROW = 10  # numbers per packed component (_pack_components)
# Voxels a cloud may make with the fine tiers (fit_mixture_voxels' fine_range): past this many its
# points fill a volume near the sensor (foliage, dust) rather than lie on surfaces, and it is voxelised
# again without them. Kurt3D's scans make 6,266-7,199, a depth camera's room 3,500; 200,000 points
# filling a ball of 4.4 m made 131,534 and took 541-832 ms to fit (two runs) against 99-100 ms without
# the fine tiers (54 ms before they reached 4.5 m and EM every group; docs/BENCHMARKS.md,
# thirty-eighth session).
_FINE_VOXEL_BUDGET = 32768


@njit(cache=True, inline="always")
def _pack_row(row, w, m0, m1, m2, c00, c10, c11, c20, c21, c22):
    """One component (weight w, mean m, covariance c by its lower triangle) as a row of _ROW (see
    _pack_components). Sigma^-1 from the cofactors of Sigma over its determinant: no square roots
    and one division, where a Cholesky factor took three of each and three more divisions (the
    packing runs once a block for every component: 1.07x the whole fit, docs/BENCHMARKS.md,
    twenty-first session)."""
    a00 = c11 * c22 - c21 * c21
    a10 = c20 * c21 - c10 * c22
    a20 = c10 * c21 - c11 * c20
    a11 = c00 * c22 - c20 * c20
    a21 = c10 * c20 - c00 * c21
    a22 = c00 * c11 - c10 * c10
    inverse_det = 1.0 / (c00 * a00 + c10 * a10 + c20 * a20)
    row[0], row[1], row[2] = m0, m1, m2
    row[3] = a00 * inverse_det
    row[4] = 2.0 * a10 * inverse_det
    row[5] = 2.0 * a20 * inverse_det
    row[6] = a11 * inverse_det
    row[7] = 2.0 * a21 * inverse_det
    row[8] = a22 * inverse_det
    row[9] = 0.5 * np.log(w * w * inverse_det) - 1.5 * em._LOG_2PI  # one log: log pi - log det(Sigma) / 2


@njit(cache=True)
def _pack_components(weights, mu, covs, packed):
    """Each 3D component as one row of `packed` (K, _ROW), what _score reads: mu (3), Sigma^-1
    (upper triangle by rows, off-diagonal entries doubled: 00, 01, 02, 11, 12, 22, the order of a
    voxel's scatter) and log pi - log det(2 pi Sigma) / 2. One contiguous row of 80 bytes per
    component."""
    for k in range(weights.shape[0]):
        c = covs[k]
        _pack_row(
            packed[k], weights[k], mu[k, 0], mu[k, 1], mu[k, 2], c[0, 0], c[1, 0], c[1, 1], c[2, 0], c[2, 1], c[2, 2]
        )


@njit(cache=True, inline="always")
def _moments(s, reg_covar):
    """Mean and covariance (lower triangle: 00, 10, 11, 20, 21, 22) of summed statistics s (10,),
    reg_covar on the diagonal, as em._m_step; and whether they make a component: a positive weight
    and a positive definite covariance (its leading minors positive), which over-relaxed sums can
    overshoot."""
    inverse = 1.0 / max(s[0], 1e-300)
    m0, m1, m2 = s[1] * inverse, s[2] * inverse, s[3] * inverse
    # Features' upper triangle: 4: 00, 5: 01, 6: 02, 7: 11, 8: 12, 9: 22 (em._features).
    c00 = max(s[4] * inverse - m0 * m0, 0.0) + reg_covar
    c11 = max(s[7] * inverse - m1 * m1, 0.0) + reg_covar
    c22 = max(s[9] * inverse - m2 * m2, 0.0) + reg_covar
    c10 = s[5] * inverse - m0 * m1
    c20 = s[6] * inverse - m0 * m2
    c21 = s[8] * inverse - m1 * m2
    det = c00 * (c11 * c22 - c21 * c21) - c10 * (c10 * c22 - c21 * c20) + c20 * (c10 * c21 - c11 * c20)
    valid = s[0] > 0.0 and c00 * c11 - c10 * c10 > 0.0 and det > 0.0
    return m0, m1, m2, c00, c10, c11, c20, c21, c22, valid


@njit(cache=True)
def _add_block(now, last, counted, step, total, plain, reg_covar, total_weight, packed, pack):
    """A block's fresh sums `now` (K, 10) into the totals: `plain`, the sum of every block's
    latest sums (EM's own step), and `total`, where the block counts its sums of the last pass
    `last` moved `step` times their change (over-relaxation; 1: its fresh sums). `counted`: what
    the block counted in `total` so far, updated.

    With `pack`, each component's M-step from its new totals straight into its packed row
    (_pack_components'), in the same loop: the M-step the E-steps between searches need, without
    writing and reading the parameters. A component whose `total` makes no component (_moments)
    is packed from `plain`. `total_weight`: the points' count, what the weights in `total` sum to
    once every block is counted (a voxel's responsibilities sum to 1, moved or not)."""
    for k in range(now.shape[0]):
        for q in range(now.shape[1]):
            change = now[k, q] - last[k, q]
            moved = last[k, q] + step * change
            plain[k, q] += change
            total[k, q] += moved - counted[k, q]
            counted[k, q] = moved
        if pack:
            w = total[k, 0]
            m0, m1, m2, c00, c10, c11, c20, c21, c22, valid = _moments(total[k], reg_covar)
            if not valid:
                w = plain[k, 0]
                m0, m1, m2, c00, c10, c11, c20, c21, c22, _ = _moments(plain[k], reg_covar)
            _pack_row(packed[k], w / total_weight, m0, m1, m2, c00, c10, c11, c20, c21, c22)


@njit(cache=True, inline="always")
def _score(packed, k, means, scatter, i):
    """log pi_k + the mean over voxel i's points of log N(x | mu_k, Sigma_k): with m_i the voxel's
    mean and S_i its scatter, the mean of (x - mu)^T Sigma^-1 (x - mu) is
    tr(Sigma^-1 ((m_i - mu)(m_i - mu)^T + S_i)) (Verbeek et al.)."""
    x0 = means[i, 0] - packed[k, 0]
    x1 = means[i, 1] - packed[k, 1]
    x2 = means[i, 2] - packed[k, 2]
    distance = (
        packed[k, 3] * (x0 * x0 + scatter[i, 0])
        + packed[k, 4] * (x0 * x1 + scatter[i, 1])
        + packed[k, 5] * (x0 * x2 + scatter[i, 2])
        + packed[k, 6] * (x1 * x1 + scatter[i, 3])
        + packed[k, 7] * (x1 * x2 + scatter[i, 4])
        + packed[k, 8] * (x2 * x2 + scatter[i, 5])
    )
    return packed[k, 9] - 0.5 * distance


@njit(cache=True, inline="always")
def _log(x):
    """np.log of a positive, finite x, within 1e-13: x = 2^e m with m in [1/sqrt(2), sqrt(2)),
    log m = 2 atanh(z) with z = (m - 1) / (m + 1), |z| < 0.172, by its series to z^15. The bound
    takes one per voxel and pass, of a sum in [1, kept]: glibc's log was 11 % of the voxel EM's
    profile (docs/BENCHMARKS.md, twentieth session); this one is a division and a few products."""
    m, e = math.frexp(x)
    if m < 0.7071067811865476:
        m *= 2.0
        e -= 1
    z = (m - 1.0) / (m + 1.0)
    z2 = z * z
    series = 1.0 / 13.0 + z2 / 15.0
    for c in (1.0 / 11.0, 1.0 / 9.0, 1.0 / 7.0, 1.0 / 5.0, 1.0 / 3.0, 1.0):
        series = c + z2 * series
    return e * 0.6931471805599453 + 2.0 * z * series


@njit(cache=True)
def _e_step_block(means, sums, scatter, lo_i, hi_i, search, voxel_cell, start, items, packed, kept, n_kept, stats):
    """E-step of voxels lo_i..hi_i fused with the M-step sums (into `stats`); returns the bound
    sum_i n_i logsumexp_k(score_ik) over each voxel's kept components k.

    Each voxel's responsibilities are spread over its kept.shape[1] most likely components
    only. With `search`, those are found among the components listed for the voxel's hash cell
    (`voxel_cell`, CSR `start`/`items`; all components where none is listed) and written to
    kept[i, :n_kept[i]]; without, the kept ones are scored again, and those below e^-20 of the
    voxel's best leave its list. One loop for both: numba compiles the shared responsibility code
    best inline.
    """
    k_count = packed.shape[0]
    n_top = kept.shape[1]
    log_p = np.empty(n_top)
    scores = np.empty(k_count if search else 0)
    stats[:] = 0.0
    bound = 0.0
    for i in range(lo_i, hi_i):
        if search:
            c = voxel_cell[i]
            first, n = start[c], start[c + 1] - start[c]
            listed = n > 0
            if not listed:
                first, n = 0, k_count
            # Every candidate scored first, then the best taken one at a time (the first of equal
            # scores): branch-free loops, 1.4x faster than inserting each score into the sorted
            # top list as it came (docs/BENCHMARKS.md, thirteenth session).
            for j in range(n):
                scores[j] = _score(packed, items[first + j] if listed else j, means, scatter, i)
            count = 0
            for top in range(min(n_top, n)):
                at, s = 0, scores[0]
                for j in range(1, n):
                    better = scores[j] > s
                    at = j if better else at
                    s = scores[j] if better else s
                if top > 0 and s < log_p[0] + em._LOG_RESP_FLOOR:
                    break  # a responsibility below e^-20 of the largest would add nothing in later passes
                log_p[top] = s
                kept[i, top] = items[first + at] if listed else at
                scores[at] = -np.inf
                count += 1
            n_kept[i] = count
        else:
            count = n_kept[i]
            for j in range(count):
                log_p[j] = _score(packed, kept[i, j], means, scatter, i)
        best = -np.inf
        for j in range(count):
            best = max(best, log_p[j])
        norm = 0.0
        for j in range(count):
            gap = log_p[j] - best
            log_p[j] = 1.0 if gap == 0.0 else (np.exp(gap) if gap > em._LOG_RESP_FLOOR else 0.0)  # exp(0) = 1, no call
            norm += log_p[j]
        if not search:
            # A kept component below e^-20 of the best adds nothing; it leaves the voxel's list
            # rather than be scored on every later pass (truncated EM keeps the components that
            # matter, Luecke & Eggert 2010): 1.04x the fit, log-likelihoods -0.006 to +0.004 on
            # BALM's 15 scans (docs/BENCHMARKS.md, twenty-first session).
            count = 0
            for j in range(n_kept[i]):
                if log_p[j] != 0.0:
                    kept[i, count] = kept[i, j]
                    log_p[count] = log_p[j]
                    count += 1
            n_kept[i] = count
        inverse = 1.0 / norm
        for j in range(count):
            r = log_p[j] * inverse
            k = kept[i, j]
            for q in range(_N_FEATURES):
                stats[k, q] += r * sums[i, q]
        bound += sums[i, 0] * (best + _log(norm))
    return bound


@njit(cache=True)
def _voxel_em(means, sums, scatter, weights, mu, covs, reg_covar, max_iter, tol, n_kept, overrelaxation, search_every):
    """Truncated incremental EM on voxels in place, at most `max_iter` passes, until the bound per
    point changes by less than `tol`; returns (passes, bound per point).

    The first pass searches each voxel's candidates (the components whose _SEARCH_BOX_SIGMAS box
    reaches its hash cell) and keeps its `n_kept` most likely; the other passes score only those,
    but for every `search_every`-th after the first (0: none), which searches again among the
    candidates of the components as they are then, and takes EM's own step.
    Such a pass is an exact E-step for responsibilities restricted to the kept components, so, as
    a full E-step, it does not lower a bound on the log-likelihood (truncated EM, Luecke & Eggert
    2010), and it costs a few scores per voxel instead of about ten.
    The schedule is em._refine's: voxel i in block i mod B, the M-step after every block from
    the second pass on (Neal & Hinton 1998). From the third pass, a block's sums count moved
    `overrelaxation` times their change since its last pass (1: plain EM); a component whose moved
    sums make no component (_moments) takes EM's own, and after a pass whose bound fell, the steps are plain.
    """
    m, d = means.shape
    k_count = weights.shape[0]
    n_blocks = max(1, min(em._MAX_BLOCKS, m // (_BLOCK_VOXELS_PER_COMPONENT * k_count)))
    lo, cell, dims = _hash_grid(means, k_count, m * _CELLS_PER_VOXEL)
    order, voxel_cell = _block_cell_order(means, n_blocks, lo, cell, dims)
    means, sums, scatter = means[order], sums[order], scatter[order]
    total_weight = sums[:, 0].sum()
    fresh = np.zeros((2, n_blocks, k_count, sums.shape[1]))  # each block's sums: this pass, the last
    counted = np.zeros((n_blocks, k_count, sums.shape[1]))
    total = np.zeros((k_count, sums.shape[1]))
    plain = np.zeros((k_count, sums.shape[1]))
    packed = np.empty((k_count, _ROW))
    kept = np.empty((m, n_kept), dtype=np.int64)
    n_kept_of = np.zeros(m, dtype=np.int64)
    start, items = _candidates(weights, mu, covs, lo, cell, dims, _SEARCH_BOX_SIGMAS)
    _pack_components(weights, mu, covs, packed)
    previous = -np.inf
    passes = 0
    while passes < max_iter:
        passes += 1
        search = passes == 1 or (search_every > 0 and (passes - 1) % search_every == 0)
        if search and passes > 1:
            _unpack(total, plain, reg_covar, weights, mu, covs)
            start, items = _candidates(weights, mu, covs, lo, cell, dims, _SEARCH_BOX_SIGMAS)
        now, last = fresh[passes % 2], fresh[(passes + 1) % 2]
        # A search changes the kept lists, so the change of a block's sums since its last pass is
        # no EM step to move further along.
        step = overrelaxation if passes > 2 and not search else 1.0
        bound = 0.0
        for b in range(n_blocks):
            lo_i, hi_i = (b * m) // n_blocks, ((b + 1) * m) // n_blocks
            bound += _e_step_block(
                means, sums, scatter, lo_i, hi_i, search, voxel_cell, start, items, packed, kept, n_kept_of, now[b]
            )
            pack = passes > 1 or b == n_blocks - 1
            _add_block(now[b], last[b], counted[b], step, total, plain, reg_covar, total_weight, packed, pack)
        bound /= total_weight
        if bound < previous:
            overrelaxation = 1.0
        if abs(bound - previous) < tol:
            break
        previous = bound
    _unpack(total, plain, reg_covar, weights, mu, covs)  # the parameters the last E-step's M-step packed
    return passes, bound


@njit(cache=True)
def _unpack(total, plain, reg_covar, weights, mu, covs):
    """The parameters _add_block packs from `total` into weights, mu and covs (em._m_step's):
    a row of `total` that makes no component is taken from `plain`. `total` stays the sum of what
    the blocks counted."""
    chosen = total.copy()
    for k in range(total.shape[0]):
        if not _moments(total[k], reg_covar)[-1]:
            chosen[k] = plain[k]
    em._m_step(chosen, reg_covar, weights, mu, covs)


def fit_mixture_voxels(
    points: np.ndarray,
    n_components: int,
    voxel_size: float,
    *,
    cell_size: float | None = None,
    near_range: float = np.inf,
    fine_range: float = 0.0,
    reg_covar: float = 1e-4,
    max_iter: int = 100,
    tol: float = 1e-3,
    overrelaxation: float = _OVERRELAXATION,
    search_every: int = 0,
    footprint: bool = True,
    rings: float | None = None,
) -> Mixture:
    """A mixture of at most `n_components` Gaussians for (n, 3) points from the statistics of
    voxels of size `voxel_size` (m): the voxels merged bottom-up into that many groups
    (voxel_merge), then at most `max_iter` passes of EM on the voxels (0: none); `reg_covar`,
    `max_iter` and `tol` as in em.fit_mixture (tol bounds the change of the bound per point), `overrelaxation` the
    factor of the M-step from the third pass (1: plain EM), `search_every` the passes between
    searches of each voxel's candidates after the first (0: the first pass only; fit_scan's for a
    cloud without rings: scan.DENSE_3D_VOXEL_SEARCH_EVERY; searched on every pass, on finer voxels,
    with more passes, the fit reaches scikit-learn's converged EM at several times the time,
    docs/BENCHMARKS.md). With `cell_size` (m),
    also at most one component per occupied cell of that size (count_voxels(points, cell_size)),
    counted from the voxels when it is a whole number of voxels. Points farther than `near_range`
    (m) from the origin of their frame (the sensor, for a scan) are summed in voxels of twice the
    size: there the scan's rings lie farther apart than a voxel, so a voxel holds few points; and
    within `fine_range` (m; 0: none) in voxels of half the size, within half of it a quarter
    (voxels.voxel_tiers): there the points are dense and a coarse voxel joins surfaces; unless those
    tiers make more than _FINE_VOXEL_BUDGET voxels (a volume of points, not surfaces).
    With `footprint`, the merge costs see each point's footprint across the rings of a spinning
    lidar (read off the points' elevations in their frame, rings.py; none where there are none;
    `rings`: their spacing where the caller has read it).

    Deterministic: no seed. Fewer components come back only when there are fewer voxels than
    asked (voxels are never cut: the voxels must be much smaller than the components).
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"fit_mixture_voxels: points must be (n, 3), got {points.shape}")
    if search_every < 0:
        raise ValueError(f"fit_mixture_voxels: search_every must be >= 0 (0: the first pass only), got {search_every}")
    n, d = points.shape
    if n == 0:
        return Mixture.empty(d)
    shift = points[0].copy()  # a point of the cloud: the second moments of x - shift stay precise
    finest, tier_ranges, base_level = voxel_tiers(float(voxel_size), float(fine_range), float(near_range))
    sums, keys = _voxel_statistics(points, finest, shift, tier_ranges)
    if fine_range > 0 and len(sums) > _FINE_VOXEL_BUDGET:  # a volume, not surfaces: no fine tiers
        finest, tier_ranges, base_level = voxel_tiers(float(voxel_size), 0.0, float(near_range))
        sums, keys = _voxel_statistics(points, finest, shift, tier_ranges)
    k = int(min(max(n_components, 1), n))
    if cell_size is not None:
        ratio = float(cell_size) / finest
        whole = round(ratio) >= 1 and abs(ratio - round(ratio)) < 1e-9 and round(ratio) % (1 << len(tier_ranges)) == 0
        k = min(k, _count_cells(keys, d, round(ratio)) if whole else count_voxels(points, float(cell_size)))
    spacing = ring_spacing(points) if rings is None else rings
    costed = with_footprint(sums, -shift, spacing) if footprint else sums.copy()
    group_sums, _ = merge_voxels(keys, sums, costed, k, float(reg_covar), finest, tier_ranges, base_level)
    k = group_sums.shape[0]
    weights, mu, covs = np.empty(k), np.empty((k, d)), np.empty((k, d, d))
    em._m_step(group_sums, float(reg_covar), weights, mu, covs)
    if max_iter > 0:
        means, scatter = _means_and_scatter(sums)
        _voxel_em(
            means, sums, scatter, weights, mu, covs, float(reg_covar), int(max_iter), float(tol), _KEPT_COMPONENTS,
            float(overrelaxation), int(search_every),
        )  # fmt: skip
    keep = weights > 1e-12
    return Mixture(weights[keep] / weights[keep].sum(), mu[keep] + shift, covs[keep], n)
