"""Stroke-time series for the predictor tests, and the reference fits they are checked against."""

from __future__ import annotations

from fractions import Fraction

import numpy as np

NOMINAL_NS = 10_000_000  # ~10 ms strokes, like the rig


def ar_around_mean(coefs: list[float], n: int, seed: int, sigma_ns: float = 1e5) -> list[int]:
    """A stationary AR process around NOMINAL_NS: the centered model's own equation."""
    rng = np.random.default_rng(seed)
    burn = 200
    e = rng.normal(0.0, sigma_ns, n + burn)
    x = np.zeros(n + burn)
    for i in range(len(coefs), n + burn):
        x[i] = sum(c * x[i - 1 - j] for j, c in enumerate(coefs)) + e[i]
    return [int(v) for v in np.rint(NOMINAL_NS + x[burn:])]


def ar_no_intercept(coefs: list[float], n: int, seed: int, sigma_ns: float = 1e5) -> list[int]:
    """t_i = sum a_j t_{i-j} + e_i with no intercept: the paper model's own equation (Eq. 2)."""
    rng = np.random.default_rng(seed)
    burn = 100
    e = rng.normal(0.0, sigma_ns, n + burn)
    x = [float(NOMINAL_NS)] * len(coefs)
    for i in range(n + burn):
        x.append(sum(c * x[-1 - j] for j, c in enumerate(coefs)) + e[i])
    return [round(v) for v in x[-n:]]


def drifting(n: int, seed: int) -> list[int]:
    """Thermal-like drift (slow sinusoid and a random walk) plus correlated friction noise."""
    rng = np.random.default_rng(seed)
    i = np.arange(n)
    walk = np.cumsum(rng.normal(0.0, 4e3, n))
    noise = np.zeros(n)
    e = rng.normal(0.0, 6e4, n)
    for k in range(1, n):
        noise[k] = 0.5 * noise[k - 1] + e[k]
    x = NOMINAL_NS + 4e5 * np.sin(2 * np.pi * i / 2500.0) + walk + noise
    return [int(v) for v in np.rint(x)]


def steps(n: int, seed: int) -> list[int]:
    """Piecewise-constant levels (a changed drive frequency, say) that jump every few hundred strokes."""
    rng = np.random.default_rng(seed)
    out: list[int] = []
    while len(out) < n:
        level = NOMINAL_NS + rng.uniform(-1.5e6, 1.5e6)
        span = int(rng.integers(50, 600))
        out.extend(int(v) for v in np.rint(level + rng.normal(0.0, 8e4, span)))
    return out[:n]


def design(window: list[int] | np.ndarray, order: int, model: str) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 3's X and beta for a window (oldest first), with a leading ones column for "centered"."""
    w = np.asarray(window, dtype=float)
    n = len(w)
    x = np.column_stack([w[order - j : n - j] for j in range(1, order + 1)])
    if model == "centered":
        x = np.column_stack([np.ones(n - order), x])
    return x, w[order:]


def lstsq_forecast(window: list[int] | np.ndarray, order: int, model: str) -> tuple[float, np.ndarray]:
    """A fresh numpy lstsq fit of the window: (t_hat of the next stroke, coefficients)."""
    x, y = design(window, order, model)
    coef = np.linalg.lstsq(x, y, rcond=None)[0]
    last = np.asarray(window, dtype=float)[::-1][:order]
    regressors = np.concatenate([[1.0], last]) if model == "centered" else last
    return float(regressors @ coef), coef


def exact_least_squares(
    window: list[int], order: int, model: str
) -> tuple[int, Fraction, list[Fraction] | None]:
    """Rational least squares of Eq. 3 by Gram-Schmidt: (rank, RSS, coefficients if full rank)."""
    n = len(window)
    cols = [[Fraction(window[i - j]) for i in range(order, n)] for j in range(1, order + 1)]
    if model == "centered":
        cols.insert(0, [Fraction(1)] * (n - order))
    y = [Fraction(v) for v in window[order:]]

    def dot(a: list[Fraction], b: list[Fraction]) -> Fraction:
        return sum((p * q for p, q in zip(a, b, strict=True)), Fraction(0))

    basis: list[list[Fraction]] = []
    for c in cols:
        r = c[:]
        for q in basis:
            f = dot(r, q) / dot(q, q)
            r = [ri - f * qi for ri, qi in zip(r, q, strict=True)]
        if any(r):
            basis.append(r)
    resid = y[:]
    for q in basis:
        f = dot(resid, q) / dot(q, q)
        resid = [ri - f * qi for ri, qi in zip(resid, q, strict=True)]
    rss = dot(resid, resid)
    if len(basis) < len(cols):
        return len(basis), rss, None
    # Full rank: the normal equations by Gauss-Jordan.
    k = len(cols)
    a = [[dot(cols[i], cols[j]) for j in range(k)] + [dot(cols[i], y)] for i in range(k)]
    for p in range(k):
        piv = next(i for i in range(p, k) if a[i][p] != 0)
        a[p], a[piv] = a[piv], a[p]
        a[p] = [v / a[p][p] for v in a[p]]
        for i in range(k):
            if i != p and a[i][p] != 0:
                f = a[i][p]
                a[i] = [vi - f * vp for vi, vp in zip(a[i], a[p], strict=True)]
    return k, rss, [a[i][k] for i in range(k)]
