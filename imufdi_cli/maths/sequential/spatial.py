"""The noise variance of rows in motion from the rows' own evidence (``CusumBank(spatial=
True)``, :mod:`imufdi_cli.maths.sequential`).

In hand motion the MIMU4444 accelerometers' parity residual is white in time, and its size
changes from row to row alike on every sensor (a scale mixture: kurtosis 50-90 over the
motion, but near Gaussian given the row's scale). A jitter model driven by the
motion has to cover its largest rows; a row's own spread ``m_t = median_i(z_t,i^2) /
0.4549`` over the sensors follows it, and a fault on a few sensors leaves it. The test
standardizes the row by ``c_n m_t``, ``c_n`` (:func:`spatial_inflation`) the margin for
the median's own sampling error.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from imufdi_cli.maths.sequential.thresholds import _ERFC, _normal_cdf, bisect_boundary

#: Median of a chi-square variable of one degree of freedom.
CHI2_1_MEDIAN = 0.4549364231195724

#: Fewest testable sensors for the spatial noise variance in motion (below, its sampling
#: error needs a margin of 2.7 or more: ``spatial_inflation(12)``).
MIN_SPATIAL_COLUMNS = 12

_ERF = np.frompyfunc(math.erf, 1, 1)


def spatial_variance(
    z: np.ndarray, v: np.ndarray, columns: np.ndarray, clip: float, rest_factor: float
) -> np.ndarray:
    """The rows' noise variance factors (N,), those of the rows in motion (``v_t >
    rest_factor``) replaced by ``c_k m_t`` over the ``columns`` (n,) bool of ``z`` (N, n)
    that have evidence on the row (k of them, finite; ``c_k = spatial_inflation(k,
    clip)``), at least just above ``rest_factor`` (so the rows still count as in motion:
    they teach the references nothing). A row with fewer than MIN_SPATIAL_COLUMNS sensors
    with evidence keeps ``v_t``. A function of each row alone: the same whatever the
    decisions and however the rows are split into calls."""
    moving = v > rest_factor
    if not moving.any():
        return v
    rows = np.flatnonzero(moving)
    squares = np.square(z[np.ix_(rows, np.flatnonzero(columns))])
    out = v.copy()
    floor = math.nextafter(rest_factor, math.inf)
    if np.isfinite(squares).all():
        inflation = spatial_inflation(squares.shape[1], clip)
        out[rows] = np.maximum(np.median(squares, axis=1) * (inflation / CHI2_1_MEDIAN), floor)
        return out
    # a sensor without evidence on a row (NaN) is left out of its spread and its margin
    finite = np.isfinite(squares)
    counts = finite.sum(axis=1)
    squares[~finite] = np.nan
    for count in np.unique(counts[counts >= MIN_SPATIAL_COLUMNS]):
        these = counts == count
        middle = np.nanmedian(squares[these], axis=1)
        inflation = spatial_inflation(int(count), clip)
        out[rows[these]] = np.maximum(middle * (inflation / CHI2_1_MEDIAN), floor)
    return out


@lru_cache(maxsize=64)
def spatial_inflation(columns: int, clip: float = 3.5) -> float:
    """Margin ``c_n`` on a row's spatial noise variance ``m = median_i(z_i^2) / 0.4549``
    over ``columns`` sensors, so that the CUSUM increments of (1) keep ``E[exp(l)] <= 1``.

    With the row's evidence ``z_i = s e_i`` (``e_i ~ N(0, 1)``, one scale s for the row)
    the test standardizes by ``sqrt(c m)``; ``m / s^2`` is the median of n chi-square
    variables of one degree of freedom over its median, a law of its own (taken as the
    order statistic ``ceil(n/2)``: the lower of the two middle ones for an even n, which
    errs on the safe side). ``c`` is the smallest value for which, for every effective
    shift a of the bank (0.25 to 2 C, C = ``clip``), ``E[exp(a clip(r e, -C, C) - a^2/2)]
    <= 1`` averaged over ``r = (c m / s^2)^-1/2``: Ville's condition, under which an excursion of
    the CUSUM reaches h with probability at most ``exp(-h)``, the bound the threshold is
    designed on. Expectation over m: its density (that of the order statistic) by a
    400-point Gauss-Legendre rule in log m; over e: 64-point Gauss-Legendre inside the
    clip about the integrand's peak, the tails exactly; 40 shifts. About 0.2 s, once per n.
    Values: 2.69 for 12 sensors, 1.55 for 24, 1.21 for 48, 1.08 for 96 (to 1e-4).
    """
    n = int(columns)
    if n < 1:
        raise ValueError(f"columns must be at least 1, got {columns}")
    k = (n + 1) // 2
    # the law of the order statistic x (of n chi-square(1) variables) on a grid of log x:
    # density n!/((k-1)!(n-k)!) F^(k-1) (1-F)^(n-k) f(x), times x for d(log x)
    legendre_t, weights_t = np.polynomial.legendre.leggauss(400)
    t_low, t_high = math.log(1e-12), math.log(60.0)
    t = 0.5 * (t_high - t_low) * (legendre_t + 1.0) + t_low
    x = np.exp(t)
    root = np.sqrt(0.5 * x)
    cdf = np.asarray(_ERF(root), dtype=float)  # F(x) of chi-square(1)
    upper = np.asarray(_ERFC(root), dtype=float)  # 1 - F(x), precise in the tail
    log_front = math.lgamma(n + 1) - math.lgamma(k) - math.lgamma(n - k + 1)
    with np.errstate(divide="ignore"):
        log_density = (
            log_front
            + (k - 1) * np.log(cdf)
            + (n - k) * np.log(upper)
            - 0.5 * x
            - 0.5 * np.log(2.0 * math.pi * x)
            + t
        )
    mass = np.exp(log_density) * weights_t * 0.5 * (t_high - t_low)
    mass /= mass.sum()  # 1 to within the grid's error (the ends carry nothing)
    ratio = x / 0.4549364231195724  # m / s^2 at the nodes
    shifts = np.geomspace(0.25, 2.0 * clip, 40)[:, None, None]
    legendre, weights = np.polynomial.legendre.leggauss(64)

    def worst(c: float) -> float:
        r = 1.0 / np.sqrt(c * ratio)  # (nodes,)
        edge = np.broadcast_to(clip / r, (shifts.shape[0], r.size))
        # inside the clip: int_{-edge}^{edge} exp(a r e - a^2/2) phi(e) de, whose
        # integrand peaks at e = a r (width 1): over the part of [-edge, edge] within 9
        # of the peak clamped into it (the rest carries under exp(-40) of it), so the
        # exponent never exceeds a clip - a^2/2
        peak = np.clip(shifts[:, :, 0] * r, -edge, edge)
        lo, hi = np.maximum(-edge, peak - 9.0), np.minimum(edge, peak + 9.0)
        half = 0.5 * (hi - lo)
        e = (0.5 * (hi + lo))[..., None] + half[..., None] * legendre
        inner = np.exp(shifts * r[None, :, None] * e - 0.5 * shifts**2 - 0.5 * e * e)
        inside = (inner @ weights) * half / math.sqrt(2.0 * math.pi)
        edge = edge[0]
        tail = _normal_cdf(-edge)  # P(e > edge) = P(e < -edge): clipped to +-clip
        a = shifts[:, :, 0]
        beyond = (np.exp(a * clip - 0.5 * a * a) + np.exp(-a * clip - 0.5 * a * a)) * tail
        return float(np.max((inside + beyond) @ mass))

    if worst(64.0) > 1.0:
        return math.inf
    # on log c, to 1e-4 relative
    boundary = bisect_boundary(
        lambda log_c: worst(math.exp(log_c)) > 1.0, 0.0, math.log(64.0), math.log1p(1e-4)
    )
    return math.exp(boundary)
