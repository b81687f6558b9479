"""Order statistics inside numba kernels: the k-th smallest value and the median.

numba's own np.partition and np.median are generic over types, layouts and NaN handling, and
compiling them is most of the cost of compiling the kernels that call them: on a 2-core AMD EPYC,
np.partition took 12.5 s and np.median 3.0 s to compile against 0.5 s for this quickselect
(docs/BENCHMARKS.md, twenty-ninth session). Every fresh install, CI run and first robot start pays
that. The values here are finite floats, so the plain algorithm is enough.
"""

from __future__ import annotations

from numba import njit


@njit(cache=True)
def kth_smallest(values, k):
    """The k-th smallest (0-based) of the 1D array `values`, which is reordered (Hoare's quickselect):
    afterwards values[:k] <= values[k] <= values[k + 1:]."""
    lo, hi = 0, values.shape[0] - 1
    while lo < hi:
        pivot = values[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while values[i] < pivot:
                i += 1
            while values[j] > pivot:
                j -= 1
            if i <= j:
                values[i], values[j] = values[j], values[i]
                i += 1
                j -= 1
        # now values[lo:j + 1] <= pivot <= values[i:hi + 1], and values[j + 1:i] == pivot
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return values[k]


@njit(cache=True)
def median(values):
    """np.median of the 1D array `values` (non-empty), which is reordered."""
    n = values.shape[0]
    upper = kth_smallest(values, n // 2)
    if n % 2:
        return upper
    return 0.5 * (values[: n // 2].max() + upper)
