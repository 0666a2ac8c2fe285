"""The statistics the diagnostics need (``_diagnostics``; docs/diagnostics.md), in NumPy
float64 and without a statistics library: the chi-square and F quantiles, the pooled
autocorrelation of series with missing values and the Ljung-Box statistic, least squares, and
the autoregressive model of a residual that says how much its correlation in time inflates
what a regressor takes from noise; and two helpers for series with missing values that the
set-up check and the model-mismatch check share (``hold_last``, ``moving_mean``).

The chi-square quantile is Wilson and Hilferty's approximation, the F quantile the
regularised incomplete beta function inverted by bisection (both tested against table
values). The matrix work is elementwise or a few rows wide on purpose: OpenBLAS's threads,
on a machine whose cores are busy, made a 100 x 100 solve take 80 ms and one diagnostics of
600 s of rows 38 s (0.7 s without them).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

#: The highest order of the autoregressive model of a residual (``noise_model``).
AR_MAX_ORDER = 100
_Z95 = 1.6448536269514722  # one-sided 95 % point of the standard normal


# ----------------------------------------------------------------------------- quantiles
def hold_last(u: np.ndarray) -> np.ndarray:
    """``u`` with every NaN replaced by the last finite value before it (the first finite
    value before the first; zeros if there is none)."""
    ok = np.isfinite(u)
    if not ok.any():
        return np.zeros_like(u)
    idx = np.where(ok, np.arange(u.size), 0)
    np.maximum.accumulate(idx, out=idx)
    out = u[idx]
    out[: int(np.argmax(ok))] = u[int(np.argmax(ok))]
    return out


def moving_mean(x: np.ndarray, n: int) -> np.ndarray:
    """The centred ``n``-row moving mean of ``x`` (rows ``k - n // 2 .. k + (n - 1) // 2``,
    cut at the ends), NaNs skipped (NaN where all are)."""
    if n <= 1:
        return x.copy()
    ok = np.isfinite(x)
    s = np.concatenate([[0.0], np.cumsum(np.where(ok, x, 0.0))])
    c = np.concatenate([[0], np.cumsum(ok)])
    k = np.arange(x.size)
    lo = np.clip(k - n // 2, 0, x.size)
    hi = np.clip(k + (n - 1) // 2 + 1, 0, x.size)
    count = c[hi] - c[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, (s[hi] - s[lo]) / np.maximum(count, 1), np.nan)


def chi2_quantile(dof: float, z: float) -> float:
    """The quantile of the chi-square distribution with ``dof`` degrees of freedom at the
    standard normal's ``z`` (Wilson and Hilferty's cube-root approximation)."""
    c = 2.0 / (9.0 * dof)
    return float(dof * (1.0 - c + z * math.sqrt(c)) ** 3)


def chi2_quantile95(dof: float) -> float:
    """The 95 % quantile of the chi-square distribution with ``dof`` degrees of freedom
    (``chi2_quantile``; 31.41 for 20, 18.31 for 10)."""
    return chi2_quantile(dof, _Z95)


def _betacf(a: float, b: float, x: float) -> float:
    """The continued fraction of the incomplete beta function (modified Lentz)."""
    tiny = 1e-300
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 400):
        m2 = 2 * m
        for num in (m * (b - m) * x / ((qam + m2) * (a + m2)),
                    -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))):
            d = 1.0 + num * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + num / c
            c = c if abs(c) > tiny else tiny
            h *= d * c
        if abs(d * c - 1.0) < 1e-15:
            break
    return h


def betainc(a: float, b: float, x: float) -> float:
    """The regularised incomplete beta function ``I_x(a, b)``."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    front = math.exp(math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b)
                     + a * math.log(x) + b * math.log1p(-x))
    if x < (a + 1.0) / (a + b + 2.0):
        return front * _betacf(a, b, x) / a
    return 1.0 - front * _betacf(b, a, 1.0 - x) / b


def f_quantile(p: float, d1: float, d2: float) -> float:
    """The ``p`` quantile of the F distribution with ``(d1, d2)`` degrees of freedom (any
    positive reals): its distribution function ``I_{d1 x / (d1 x + d2)}(d1/2, d2/2)``
    inverted by bisection (F_0.95(1, 10) = 4.965, F_0.95(3, 20) = 3.098)."""
    def cdf(x):
        return betainc(d1 / 2.0, d2 / 2.0, d1 * x / (d1 * x + d2))

    lo, hi = 0.0, 1.0
    while cdf(hi) < p and hi < 1e12:
        lo, hi = hi, hi * 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if cdf(mid) < p else (lo, mid)
        if hi - lo <= 1e-12 * hi:
            break
    return 0.5 * (lo + hi)


# ------------------------------------------------------------------------ autocorrelation
def lag_products(x: np.ndarray, ok: np.ndarray, max_lag: int) -> tuple[np.ndarray, np.ndarray]:
    """``sum x_t x_{t+k}`` over the pairs with both ``ok`` and the number of such pairs, for
    ``k = 0..max_lag`` (one series; NumPy FFT, so a long lag range costs ``T log T``)."""
    x = np.where(ok, x, 0.0)
    v = ok.astype(np.float64)
    n = x.shape[0]
    max_lag = min(max_lag, n - 1)
    size = 1 << int(2 * n - 1).bit_length()
    fx, fv = np.fft.rfft(x, size), np.fft.rfft(v, size)
    prod = np.fft.irfft(fx * np.conj(fx), size)[: max_lag + 1]
    pairs = np.rint(np.fft.irfft(fv * np.conj(fv), size)[: max_lag + 1])
    return prod, pairs


def pooled_acf(pieces: Sequence[tuple[np.ndarray, np.ndarray]], lags: int,
               demean: bool = True) -> tuple[np.ndarray, np.ndarray, int]:
    """The autocorrelation at lags ``1..lags`` of series observed in ``pieces`` (``(x, ok)``
    each: a session or a stretch of one; no pair crosses from one piece to the next): each
    lag's mean product over its valid pairs divided by the pooled variance (the pooled mean
    taken off first where ``demean``). Returns ``(acf, pairs, n)``: ``(lags,)`` values, the
    number of pairs behind each, and the number of valid values. Under whiteness each value
    has variance about ``1 / pairs``."""
    n = sum(int(ok.sum()) for _, ok in pieces)
    if n == 0:
        return np.full(lags, np.nan), np.zeros(lags), 0
    mean = sum(float(x[ok].sum()) for x, ok in pieces) / n if demean else 0.0
    prod, pairs = np.zeros(lags + 1), np.zeros(lags + 1)
    for x, ok in pieces:
        if x.shape[0] < 2:
            continue
        p, c = lag_products(x - mean, ok, lags)
        prod[: p.shape[0]] += p
        pairs[: c.shape[0]] += c
    var = prod[0] / n
    with np.errstate(invalid="ignore", divide="ignore"):
        acf = np.where(pairs[1:] > 0, prod[1:] / np.maximum(pairs[1:], 1) / var, np.nan)
    return acf, pairs[1:], n


def ljung_box(acf: np.ndarray, pairs: np.ndarray, n: int) -> float:
    """Ljung and Box's ``Q = N (N + 2) sum_k r_k^2 / (N - k)`` for autocorrelations from
    valid pairs (``pooled_acf``): ``(N + 2) / N sum_k pairs_k acf_k^2``, the same value for a
    single complete series, where ``pairs_k = N - k``; chi-square with ``len(acf)`` degrees
    of freedom for white values."""
    ok = np.isfinite(acf)
    return float((n + 2) / max(n, 1) * np.sum(pairs[ok] * acf[ok] ** 2))


# ---------------------------------------------------------- the noise behind a residual
def _lagged_gram(x: np.ndarray, order: int) -> np.ndarray:
    """``H[i, j] = sum_{t = order}^{n - 1} x_{t - i} x_{t - j}`` for ``i, j = 0..order``: the
    normal equations of the autoregression of ``x`` on its ``order`` lags, from one running
    sum of ``x_s x_{s - d}`` per lag ``d`` (elementwise: no matrix product, so no BLAS
    threads, which a busy machine starves)."""
    n = x.shape[0]
    H = np.zeros((order + 1, order + 1))
    i = np.arange(order + 1)
    for d in range(order + 1):
        run = np.concatenate([[0.0], np.cumsum(x[d:] * x[: n - d])])  # run[k]: s < d + k
        rows = i[: order + 1 - d]
        # s = t - i from order - i to n - 1 - i, s >= d: run indices s - d.
        H[rows, rows + d] = run[n - rows - d] - run[order - rows - d]
    return np.triu(H) + np.triu(H, 1).T


def noise_model(pieces, max_order: int = AR_MAX_ORDER) -> tuple[np.ndarray, float]:
    """An autoregressive model of the noise behind a residual (``pieces`` as
    ``pooled_acf``'s; no lag crosses from one piece to the next, a missing value counts as
    the residual's mean, 0): ``x_t = sum_j a_j x_{t-j} + w_t``, fitted by least squares,
    its order ``1..max_order`` (at most a twentieth of the values) chosen by Akaike's
    criterion, which takes the high orders that a slow wander under white noise needs.
    Returns ``(a, var_w)``; ``(no coefficients, 1)`` where there are too few values."""
    n = sum(int(ok.sum()) for _, ok in pieces)
    order = min(max_order, n // 20)
    if order < 1:
        return np.zeros(0), 1.0
    H, rows = np.zeros((order + 1, order + 1)), 0
    for x, ok in pieces:
        if x.shape[0] > order:
            H += _lagged_gram(np.where(ok, x, 0.0), order)
            rows += x.shape[0] - order
    gram, cross, yy = H[1:, 1:], H[0, 1:], H[0, 0]
    if rows <= 2 * order or yy <= 0:
        return np.zeros(0), 1.0
    # Nested least squares from one Cholesky factor: order p leaves yy - sum_{j<=p} w_j^2.
    chol = np.linalg.cholesky(gram + 1e-12 * np.trace(gram) / order * np.eye(order))
    w = _substitute(chol, cross)
    rss = np.maximum(yy - np.cumsum(w**2), 1e-12 * yy)
    p = int(np.argmin(rows * np.log(rss / rows) + 2 * np.arange(1, order + 1))) + 1
    return _substitute(chol[:p, :p].T[::-1, ::-1], w[:p][::-1])[::-1], float(rss[p - 1] / rows)


def _substitute(lower: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``lower^-1 b`` for a lower-triangular ``lower``, row by row (a hundred rows: a LAPACK
    call here waited on BLAS threads that a busy machine starves, 80 ms a solve)."""
    out = np.zeros_like(b)
    for i in range(b.shape[0]):
        out[i] = (b[i] - lower[i, :i] @ out[:i]) / lower[i, i]
    return out


def variance_inflation(noise: tuple[np.ndarray, float], comp_pieces) -> float:
    """``Var(x' w) / (|x|^2 var_w)`` for noise ``w`` of the spectrum of ``noise``
    (``noise_model``) and a component ``x`` over ``comp_pieces``: the factor by which the
    noise's correlation in time inflates the part of the residual a regressor along ``x``
    takes (``sum_w S(w) P_x(w) / (mean S sum P_x)``, ``P_x`` the periodogram); 1 for white
    noise, ``(1 + rho) / (1 - rho)`` for an AR(1) noise and a constant ``x``. At least 1."""
    a, var = noise
    size = 1 << int(2 * max(x.shape[0] for x, _ in comp_pieces) - 1).bit_length()
    weight = np.full(size // 2 + 1, 2.0)
    weight[0] = weight[-1] = 1.0  # a one-sided spectrum's weights
    gain = np.abs(np.fft.rfft(np.r_[1.0, -a], size)) ** 2
    spectrum = var / np.maximum(gain, 1e-300)
    power = sum(np.abs(np.fft.rfft(np.where(ok, x, 0.0), size)) ** 2 for x, ok in comp_pieces)
    total = float(np.sum(weight * power))
    if total <= 0:
        return 1.0
    tau = float(np.sum(weight * spectrum * power)) / (float(np.sum(weight * spectrum)) / size
                                                      * total)
    return max(tau, 1.0) if math.isfinite(tau) else math.inf


def least_squares(X: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares through the normal equations (columns of unit RMS, a few of them: well
    conditioned), summed by ``einsum``'s own loops rather than threaded BLAS (as
    ``_substitute``)."""
    if X.shape[1] == 0:
        return np.zeros(0), np.zeros_like(y)
    gram = np.einsum("ni,nj->ij", X, X)
    beta = np.linalg.solve(gram + 1e-12 * np.trace(gram) * np.eye(X.shape[1]),
                           np.einsum("ni,n->i", X, y))
    return beta, np.einsum("ni,i->n", X, beta)
