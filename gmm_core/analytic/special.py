"""Special functions of the standard normal for the analytic evidence: tail Q(x), erf differences,
the lower quantile Phi^-1 and the bivariate normal orthant (Genz). numba kernels, float64."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

SQRT2 = math.sqrt(2.0)
SQRT_2PI = math.sqrt(2.0 * math.pi)
SQRT_HALF_PI = math.sqrt(0.5 * math.pi)
SQRT_2_OVER_PI = math.sqrt(2.0 / math.pi)

# Gauss-Legendre abscissae (the negative half) and weights for Genz's bivariate normal: 6, 12, 20 points.
_GL6_X, _GL6_W = (a[:3].copy() for a in np.polynomial.legendre.leggauss(6))
_GL12_X, _GL12_W = (a[:6].copy() for a in np.polynomial.legendre.leggauss(12))
_GL20_X, _GL20_W = (a[:10].copy() for a in np.polynomial.legendre.leggauss(20))


@njit(cache=True)
def norm_sf(x):
    """Q(x) = P(X > x), X ~ N(0, 1)."""
    return 0.5 * math.erfc(x / SQRT2)


@njit(cache=True)
def erf_diff(a, b):
    """erf(b) - erf(a), without cancellation in the tails."""
    if a > 0.0 and b > 0.0:
        return math.erfc(a) - math.erfc(b)
    if a < 0.0 and b < 0.0:
        return math.erfc(-b) - math.erfc(-a)
    return math.erf(b) - math.erf(a)


@njit(cache=True)
def norm_ppf_lower(t):
    """Phi^-1(t) for 0 < t <= 0.5: Acklam's rational approximation and one Halley step."""
    if t < 0.02425:
        q = math.sqrt(-2.0 * math.log(t))
        x = (
            (
                (
                    ((-7.784894002430293e-03 * q - 3.223964580411365e-01) * q - 2.400758277161838e00) * q
                    - 2.549732539343734e00
                )
                * q
                + 4.374664141464968e00
            )
            * q
            + 2.938163982698783e00
        ) / (
            (
                ((7.784695709041462e-03 * q + 3.224671290700398e-01) * q + 2.445134137142996e00) * q
                + 3.754408661907416e00
            )
            * q
            + 1.0
        )
    else:
        q = t - 0.5
        r = q * q
        x = (
            (
                (
                    (
                        ((-3.969683028665376e01 * r + 2.209460984245205e02) * r - 2.759285104469687e02) * r
                        + 1.383577518672690e02
                    )
                    * r
                    - 3.066479806614716e01
                )
                * r
                + 2.506628277459239e00
            )
            * q
            / (
                (
                    (
                        ((-5.447609879822406e01 * r + 1.615858368580409e02) * r - 1.556989798598866e02) * r
                        + 6.680131188771972e01
                    )
                    * r
                    - 1.328068155288572e01
                )
                * r
                + 1.0
            )
        )
    e = 0.5 * math.erfc(-x / SQRT2) - t
    u = e * SQRT_2PI * math.exp(0.5 * x * x)
    return x - u / (1.0 + 0.5 * x * u)


@njit(cache=True)
def bvn_upper(h, k, r):
    """P(X > h, Y > k) for standard normals with correlation r (Genz 2004, 'BVNU', ~1e-15)."""
    ar = abs(r)
    if ar < 0.3:
        xs, ws = _GL6_X, _GL6_W
    elif ar < 0.75:
        xs, ws = _GL12_X, _GL12_W
    else:
        xs, ws = _GL20_X, _GL20_W
    hk = h * k
    if ar < 0.925:
        hs = 0.5 * (h * h + k * k)
        asr = math.asin(r)
        total = 0.0
        for i in range(xs.shape[0]):
            for sign in (1.0, -1.0):
                sn = math.sin(0.5 * asr * (sign * xs[i] + 1.0))
                total += ws[i] * math.exp((sn * hk - hs) / (1.0 - sn * sn))
        return total * asr / (4.0 * math.pi) + norm_sf(h) * norm_sf(k)
    if r < 0.0:
        k = -k
        hk = -hk
    total = 0.0
    if ar < 1.0:
        a2 = (1.0 - r) * (1.0 + r)
        a = math.sqrt(a2)
        bs = (h - k) ** 2
        c = (4.0 - hk) / 8.0
        d = (12.0 - hk) / 16.0
        total = (
            a
            * math.exp(-0.5 * (bs / a2 + hk))
            * (1.0 - c * (bs - a2) * (1.0 - d * bs / 5.0) / 3.0 + c * d * a2 * a2 / 5.0)
        )
        if hk > -160.0:
            b = math.sqrt(bs)
            total -= math.exp(-0.5 * hk) * SQRT_2PI * norm_sf(b / a) * b * (1.0 - c * bs * (1.0 - d * bs / 5.0) / 3.0)
        a *= 0.5
        for i in range(xs.shape[0]):
            for sign in (1.0, -1.0):
                x2 = (a * (sign * xs[i] + 1.0)) ** 2
                rs = math.sqrt(1.0 - x2)
                asr = -0.5 * (bs / x2 + hk)
                if asr > -100.0:
                    total += (
                        a
                        * ws[i]
                        * math.exp(asr)
                        * (math.exp(-hk * x2 / (2.0 * (1.0 + rs) ** 2)) / rs - (1.0 + c * x2 * (1.0 + d * x2)))
                    )
        total = -total / (2.0 * math.pi)
    if r > 0.0:
        return total + norm_sf(max(h, k))
    total = -total
    if k > h:
        if h < 0.0:
            total += norm_sf(-k) - norm_sf(-h)
        else:
            total += norm_sf(h) - norm_sf(k)
    return total
