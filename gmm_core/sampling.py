"""Deterministic Monte-Carlo samples of a scan's mixtures (Sec. III-C3, Algorithm 1 line 1).

Each component k gets n_k samples, enough to put a few in every cell it covers at the query
resolution, and each sample carries the weight N pi_k / n_k. Summed along rays, the weights
estimate the expected number of beams (Eq. 10) whatever n_k is: more samples only lower the
Monte-Carlo variance, so maps at different resolutions agree in their counts.

Samples are randomised quasi-Monte-Carlo: the uniforms of sample j of a mixture are point j of the
Kronecker sequence frac(c + j alpha) of the golden-ratio generalisation R_d (alpha_a = phi_d^-(a+1),
phi_d the root of x^(d+1) = x + 1; Roberts 2018), shifted by c, a hash of the mixture's key
(Cranley-Patterson rotation: each sample is uniform, so the counts stay unbiased). A component's
samples are a run of the sequence, itself a shifted Kronecker sequence, so they cover its Gaussian
more evenly than independent draws, whatever their number: less Monte-Carlo noise for the same
samples (docs/BENCHMARKS.md, eleventh session). Sample j needs only (key, j), so any component's
samples can be drawn alone, in any order. A query then draws only the components whose rays can
reach its grid (gmm_core.scan_trace), and a sample is the same whichever others were drawn. Each
normal is clipped to [-Z_MAX, Z_MAX]: every sample of a component lies in a box known before
drawing it (`sample_bounds`), which is what makes skipping a component exact.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from gmm_core.mixture import Mixture
from gmm_core.scan import ScanModel

MAX_SAMPLES_PER_COMPONENT = 4096
# Weights are rounded to multiples of 2^-26 (relative change below 1e-5 for weights over 0.003):
# sums of them are then exact in float64 up to 2^27 beams in a cell, so counts do not depend on
# the order scans are added in, and a map server can add and subtract scans on a cached tile
# and still get the bytes of a fresh reconstruction.
WEIGHT_QUANTUM = 2.0**-26


def samples_per_component(mixture: Mixture, resolution: float, samples_per_cell: float) -> np.ndarray:
    """n_k = ceil(samples_per_cell * max(N pi_k, cells covered by the 2-sigma box of k))."""
    return _counts(_sigmas(mixture), mixture.support * mixture.weights, resolution, samples_per_cell)


def _sigmas(mixture: Mixture) -> np.ndarray:
    """(K, d) standard deviations along each component's principal axes."""
    if mixture.n_components == 0:
        return np.zeros((0, mixture.dim))
    return np.sqrt(np.clip(np.linalg.eigvalsh(mixture.covariances), 0.0, None))


def _counts(sigmas: np.ndarray, expected_points: np.ndarray, resolution: float, samples_per_cell: float) -> np.ndarray:
    cells = np.prod(np.maximum(1.0, 4.0 * sigmas / resolution), axis=1)
    n = np.ceil(samples_per_cell * np.maximum(expected_points, cells))
    return np.clip(n, 1, MAX_SAMPLES_PER_COMPONENT).astype(np.int64)


Z_MAX = 4.0  # normals are clipped here: 6e-5 of them per coordinate move to the edge of the box
BOX_SLACK = 1e-6  # m added to sample boxes: round-off in placing a sample stays far below it
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)  # splitmix64's increment


# alpha_a of R_2 and R_3 in 64-bit fixed point: frac(c + j alpha) is then the integer sum mod 2^64,
# exact for any j (in floating point, j alpha loses a bit of the fraction per doubling of j).
_R2 = (np.uint64(0xC13FA9A902A6328F), np.uint64(0x91E10DA5C79E7B1C))
_R3 = (np.uint64(0xD1B54A32D192ED03), np.uint64(0xABC98388FB8FAC02), np.uint64(0x8CB92BA72F3D8DD7))


@njit(cache=True, inline="always")
def _splitmix(key, counter):
    """The splitmix64 output `counter` of the stream `key` (64 bits)."""
    x = key + counter * _GOLDEN
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


# Acklam's rational approximation of the normal quantile (relative error below 1.2e-9): cheaper
# than Box-Muller's logarithm, square root and sine per pair, one uniform per normal.
_A = (
    -3.969683028665376e01,
    2.209460984245205e02,
    -2.759285104469687e02,
    1.383577518672690e02,
    -3.066479806614716e01,
    2.506628277459239e00,
)
_B = (-5.447609879822406e01, 1.615858368580409e02, -1.556989798598866e02, 6.680131188771972e01, -1.328068155288572e01)
_C = (
    -7.784894002430293e-03,
    -3.223964580411365e-01,
    -2.400758277161838e00,
    -2.549732539343734e00,
    4.374664141464968e00,
    2.938163982698783e00,
)
_D = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e00, 3.754408661907416e00)
_P_TAIL = 0.02425


@njit(cache=True, inline="always")
def _tail(q):
    """The quantile of p = exp(-q^2 / 2) (a lower tail), by Acklam's outer approximation."""
    c, d = _C, _D
    return (((((c[0] * q + c[1]) * q + c[2]) * q + c[3]) * q + c[4]) * q + c[5]) / (
        (((d[0] * q + d[1]) * q + d[2]) * q + d[3]) * q + 1.0
    )


@njit(cache=True, inline="always")
def normal_quantile(p):
    """Phi^-1(p) for p in (0, 1), within 1.2e-9 relative (Acklam)."""
    if p < _P_TAIL:
        return _tail(np.sqrt(-2.0 * np.log(p)))
    if p > 1.0 - _P_TAIL:
        return -_tail(np.sqrt(-2.0 * np.log(1.0 - p)))
    a, b = _A, _B
    q = p - 0.5
    r = q * q
    return (
        (((((a[0] * r + a[1]) * r + a[2]) * r + a[3]) * r + a[4]) * r + a[5])
        * q
        / (((((b[0] * r + b[1]) * r + b[2]) * r + b[3]) * r + b[4]) * r + 1.0)
    )


@njit(cache=True, inline="always")
def sample_normals(key, j, z):
    """z[:d] = the standard normals of sample j of stream `key` (d = 2 or 3): the quantiles of point j
    of R_d shifted by the stream's hash, each clipped to [-Z_MAX, Z_MAX]."""
    d = z.shape[0]
    for a in range(d):
        x = _splitmix(key, np.uint64(a)) + np.uint64(j) * (_R3[a] if d == 3 else _R2[a])
        z[a] = min(max(normal_quantile((np.float64(x >> np.uint64(11)) + 0.5) * 2.0**-53), -Z_MAX), Z_MAX)


@dataclass(frozen=True)
class MixtureSamples:
    """What to draw of one mixture: counts[k] samples of component k, each of weight weights[k],
    at means[k] + chol[k] z with the normals z of sample offsets[k] + i of stream `key`."""

    means: np.ndarray  # (K, d)
    chol: np.ndarray  # (K, d, d) lower Cholesky factors of the covariances
    counts: np.ndarray  # (K,) int64
    offsets: np.ndarray  # (K,) int64: index of each component's first sample
    weights: np.ndarray  # (K,) float64, multiples of WEIGHT_QUANTUM
    key: np.uint64
    thickness: np.ndarray  # (K,) m: each component's thinnest principal standard deviation (a view)

    @property
    def n_samples(self) -> int:
        return int(self.counts.sum())


@dataclass(frozen=True)
class ScanSamples:
    """The samples of a scan model at one resolution (both mixtures), in the scan frame."""

    occupied: MixtureSamples  # samples end in a hit
    free: MixtureSamples  # samples only add misses (no-return beams)
    origin: np.ndarray  # (d,) sensor origin

    @property
    def n_samples(self) -> int:
        return self.occupied.n_samples + self.free.n_samples


def sample_bounds(mixture: Mixture) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box (lo, hi) holding every sample of every component: mu_k +- Z_MAX sum_b |L_k,ab|
    (the normals are clipped), widened by a micrometre against round-off."""
    if mixture.n_components == 0:
        return np.full(mixture.dim, np.inf), np.full(mixture.dim, -np.inf)
    half = Z_MAX * np.abs(np.linalg.cholesky(mixture.covariances)).sum(axis=2) + BOX_SLACK
    return (mixture.means - half).min(axis=0), (mixture.means + half).max(axis=0)


def mixture_samples(mixture: Mixture, counts: np.ndarray, key: np.uint64) -> MixtureSamples:
    """The samples `counts[k]` of each component, weights N pi_k / counts[k] (quantised)."""
    return MixtureSampler.of(mixture).samples(counts, key)


@dataclass(frozen=True)
class MixtureSampler:
    """What sampling a mixture needs at any resolution, made once: means, Cholesky factors,
    principal standard deviations and expected points N pi_k. Only the counts per component,
    their offsets and the weights depend on the resolution (`at`), a tenth of the bytes."""

    means: np.ndarray  # (K, d)
    chol: np.ndarray  # (K, d, d)
    sigmas: np.ndarray  # (K, d)
    expected_points: np.ndarray  # (K,) N pi_k

    @staticmethod
    def of(mixture: Mixture) -> MixtureSampler:
        chol = np.linalg.cholesky(mixture.covariances) if mixture.n_components else mixture.covariances
        return MixtureSampler(
            mixture.means, np.ascontiguousarray(chol), _sigmas(mixture), mixture.support * mixture.weights
        )

    @property
    def nbytes(self) -> int:
        return self.means.nbytes + self.chol.nbytes + self.sigmas.nbytes + self.expected_points.nbytes

    @property
    def thickness(self) -> np.ndarray:
        """(K,) each component's thinnest principal standard deviation (m): a view of `sigmas`."""
        return self.sigmas[:, 0]

    def samples(self, counts: np.ndarray, key: np.uint64) -> MixtureSamples:
        counts = np.ascontiguousarray(counts, dtype=np.int64)
        weights = np.rint(self.expected_points / np.maximum(counts, 1) / WEIGHT_QUANTUM) * WEIGHT_QUANTUM
        return MixtureSamples(self.means, self.chol, counts, np.cumsum(counts) - counts, weights, key, self.thickness)

    def at(self, resolution: float, samples_per_cell: float, key: np.uint64) -> MixtureSamples:
        """`samples` of the counts `samples_per_component` gives, in one kernel (a server makes one per
        node, resolution and samples per cell, holding the interpreter: the numpy expressions of
        `_counts` and `samples` cost ten times as much on a 2D scan's few dozen components)."""
        counts, offsets, weights = _plan(self.sigmas, self.expected_points, resolution, samples_per_cell)
        return MixtureSamples(self.means, self.chol, counts, offsets, weights, key, self.thickness)


@njit(cache=True)
def _plan(sigmas, expected_points, resolution, samples_per_cell):
    """The counts of `_counts`, their offsets and the weights of MixtureSampler.samples, component by
    component in the same operations, so the same bits (tests/unit/gmm_core/test_sampling.py)."""
    k_total, d = sigmas.shape
    counts, offsets, weights = np.empty(k_total, np.int64), np.empty(k_total, np.int64), np.empty(k_total)
    total = 0
    for k in range(k_total):
        cells = 1.0
        for a in range(d):
            cells *= max(1.0, 4.0 * sigmas[k, a] / resolution)
        n = min(max(np.ceil(samples_per_cell * max(expected_points[k], cells)), 1.0), MAX_SAMPLES_PER_COMPONENT)
        counts[k], offsets[k] = np.int64(n), total
        total += counts[k]
        weights[k] = np.rint(expected_points[k] / max(counts[k], 1) / WEIGHT_QUANTUM) * WEIGHT_QUANTUM
    return counts, offsets, weights


@dataclass(frozen=True)
class ScanSampler:
    """A scan model ready to sample at any resolution (both mixtures' MixtureSampler, the sensor
    origin and the seed): `at(resolution)` is scan_samples of the model without its linear algebra."""

    occupied: MixtureSampler
    free: MixtureSampler
    origin: np.ndarray
    seed: int
    samples_per_cell: float
    _keys: dict[float, np.ndarray] = field(default_factory=dict, compare=False, repr=False)  # by resolution

    @staticmethod
    def of(model: ScanModel, seed: int, samples_per_cell: float) -> ScanSampler:
        return ScanSampler(
            MixtureSampler.of(model.occupied), MixtureSampler.of(model.free), model.origin, seed, samples_per_cell
        )

    @property
    def nbytes(self) -> int:
        return self.occupied.nbytes + self.free.nbytes

    def at(self, resolution: float, samples_per_cell: float | None = None) -> ScanSamples:
        """The samples at `resolution`, `samples_per_cell` (default: the sampler's). The streams' keys
        depend on the resolution only; a component's run of its stream starts after the samples of the
        components before it, so other samples per cell draw other runs."""
        spc = self.samples_per_cell if samples_per_cell is None else samples_per_cell
        keys = self._keys.get(resolution)
        if keys is None:
            keys = np.random.SeedSequence([self.seed, int(round(resolution * 1e6))]).generate_state(2, np.uint64)
            self._keys[resolution] = keys
        return ScanSamples(
            self.occupied.at(resolution, spc, keys[0]),
            self.free.at(resolution, spc, keys[1]),
            self.origin,
        )


def scan_samples(model: ScanModel, resolution: float, seed: int, samples_per_cell: float) -> ScanSamples:
    """The samples of both mixtures of `model` at `resolution`, from `seed`: the same (model,
    resolution, seed), the same samples."""
    return ScanSampler.of(model, seed, samples_per_cell).at(resolution)


@njit(cache=True, nogil=True)
def _place(means, chol, counts, offsets, weights, key):
    """Every sample: sample i of component k at means[k] + chol[k] z(offsets[k] + i), weight weights[k]."""
    n, d = np.sum(counts), means.shape[1]
    points = np.empty((n, d))
    sample_weights = np.empty(n)
    z = np.empty(d)
    i = 0
    for k in range(counts.shape[0]):
        for s in range(counts[k]):
            sample_normals(key, offsets[k] + s, z)
            for a in range(d):
                p = 0.0
                for b in range(a + 1):  # lower triangular
                    p += chol[k, a, b] * z[b]
                points[i, a] = means[k, a] + p
            sample_weights[i] = weights[k]
            i += 1
    return points, sample_weights


def draw(samples: MixtureSamples) -> tuple[np.ndarray, np.ndarray]:
    """Every sample of a mixture in the scan frame, and its weight."""
    s = samples
    return _place(s.means, s.chol, s.counts, s.offsets, s.weights, s.key)


def scan_rays(model: ScanModel, resolution: float, seed: int, samples_per_cell: float):
    """Ray end points in the scan frame, their weights, and whether each ends in a hit.

    Samples of the occupied mixture end in a hit; samples of the free mixture (no-return
    beams) only add misses. The same (model, resolution, seed) always gives the same rays, the
    samples that gmm_core.scan_trace traces without holding them.
    """
    samples = scan_samples(model, resolution, seed, samples_per_cell)
    occ_points, occ_w = draw(samples.occupied)
    free_points, free_w = draw(samples.free)
    ends = np.concatenate([occ_points, free_points])
    weights = np.concatenate([occ_w, free_w])
    is_hit = np.concatenate([np.ones(len(occ_w), bool), np.zeros(len(free_w), bool)])
    return ends, weights, is_hit


def scan_seed(*keys) -> int:
    """A stable 63-bit seed from identifiers such as (robot, node) or (run seed, scan index).

    Stable across processes and Python versions (no `hash()`), so a restarted server draws
    the same samples.
    """
    digest = hashlib.blake2b(repr(keys).encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") >> 1
