"""Map quality: area under the ROC curve, and the occupied cells a map calls free."""

from __future__ import annotations

import numpy as np

from gmm_core.occupancy import FREE, classify


def auroc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Probability that a random positive scores above a random negative (ties count one half).

    The Mann-Whitney U statistic over mid-ranks, O(n log n).
    """
    scores = np.asarray(scores, dtype=np.float64).ravel()
    labels = np.asarray(labels, dtype=bool).ravel()
    n_pos = int(labels.sum())
    n_neg = labels.size - n_pos
    if n_pos == 0 or n_neg == 0:
        raise ValueError("auroc: needs at least one positive and one negative label")
    order = np.argsort(scores, kind="mergesort")
    sorted_scores = scores[order]
    # Mid-rank of each run of equal scores.
    boundaries = np.flatnonzero(np.diff(sorted_scores)) + 1
    starts = np.concatenate([[0], boundaries])
    ends = np.concatenate([boundaries, [scores.size]])
    run_rank = (starts + ends + 1) / 2.0
    ranks = np.empty(scores.size)
    ranks[order] = np.repeat(run_rank, ends - starts)
    u = ranks[labels].sum() - n_pos * (n_pos + 1) / 2.0
    return float(u / (n_pos * n_neg))


def grid_auroc(prob: np.ndarray, truth_hits: np.ndarray, truth_misses: np.ndarray) -> float:
    """AUROC of `prob` against a counting grid: occupied where hits > misses, cells never seen left out."""
    observed = (truth_hits + truth_misses) > 0
    return auroc(prob[observed], (truth_hits > truth_misses)[observed])


def called_free(prob: np.ndarray, occupied: np.ndarray, variance: float) -> float:
    """The share of the `occupied` cells (a mask over `prob`) that `prob` classifies FREE by Eq. 12
    with sigma^2 = `variance`: the error a robot planning through the map must not make, and one that
    AUROC, a ranking, does not see (docs/BENCHMARKS.md, thirty-fourth session)."""
    occupied = np.asarray(occupied, dtype=bool)
    if occupied.shape != np.shape(prob):
        raise ValueError(f"called_free: occupied must have prob's shape {np.shape(prob)}, got {occupied.shape}")
    if not occupied.any():
        raise ValueError("called_free: needs at least one occupied cell")
    return float((classify(np.asarray(prob)[occupied], variance) == FREE).mean())
