"""The regularized incomplete gamma and beta functions and their inverses, on scalars.

The detectors' thresholds are quantiles of chi-square, F and gamma laws at a handful of
(often fractional) degrees of freedom, computed once per run. ``scipy.special`` has them as
compiled ufuncs, but importing it costs about 0.27 s of CPU (it loads ``scipy._lib``'s array
API layer), a fifth of a whole ``imufdi detect -d glt`` on a 10-minute 16-IMU log
(docs/performance.md), for five numbers. These functions compute the same quantities in
pure Python with the :mod:`math` module, in microseconds a call:

- ``log_gamma_tails(a, t)``: ``(log P(a, x), log Q(a, x))`` at ``x = e^t``, by the series
  of Abramowitz & Stegun 6.5.29 below ``x = a + 1`` and Legendre's continued fraction
  (A&S 6.5.31) above, each evaluated for the smaller tail, the other as its complement;
- ``log_beta_tails(a, b, t)``: ``(log I_y(a, b), log(1 - I_y(a, b)))`` at ``y = e^t``, by
  the continued fraction of A&S 26.5.8 on the side of the mean where it converges fast
  (``y < (a + 1) / (a + b + 2)``), the symmetry ``I_y(a, b) = 1 - I_{1-y}(b, a)`` on the
  other;
- ``gamma_inverse(a, lower, upper)`` and ``beta_inverse(a, b, lower, upper)``: the point
  where the lower tail is ``lower`` (``upper = 1 - lower``, both given so that a tail
  probability near 1 keeps its complement exactly), by Newton's method on the logarithm
  of the smaller tail in ``t = log x``, safeguarded by bisection once the root is
  bracketed. In ``t`` the log-tail is close to linear over the whole range (slope ``a``
  as ``x -> 0``), so a few steps reach a relative change of ``2^-50``.

Both continued fractions are evaluated by the modified Lentz method (Press et al.,
*Numerical Recipes*, 3rd ed., 5.2). The prefactors ``x^a e^-x / Gamma(a)`` and
``y^a (1 - y)^b / B(a, b)`` are formed in logarithms; for shapes of 10 and more, Stirling's
series (A&S 6.1.41) for ``log Gamma`` turns them into sums of terms of order one, instead
of differences of ``log Gamma`` values of order ``a log a`` whose rounding (about
``1e-16 a log a``) would otherwise limit the result to about 1e-12 at ``a = 10^3``.

Accuracy (``tests/maths/test_incomplete.py``): the quantiles agree with ``scipy.special``'s
to 2e-13 relative for shapes 0.05 to 10^4 (gamma down to tails of 1e-300; beta from
1e-12, below which scipy's own inverse is the less accurate), and land on their level to
the log-tail's own error for any shapes and tails down to 1e-300. Shapes above
``MAX_SHAPE`` (10^6: the series would take more than about 10^4 terms a call) are left to
the caller (:mod:`~imufdi_cli.maths.quantiles` sends them to ``scipy.special``).
"""

from __future__ import annotations

import math
from collections.abc import Callable

#: the largest shape parameter computed here (beyond it, the caller uses scipy.special)
MAX_SHAPE = 1e6

_EPS = 2.0**-53  # unit roundoff of float64
_TINY = 1e-300  # the Lentz method's replacement for a zero denominator
_MAX_TERMS = 100_000  # far above the ~10 sqrt(MAX_SHAPE) terms the largest shape needs
_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)
_STIRLING = 10.0  # shapes from which Stirling's series is used
_STEP_LIMIT = 10.0  # largest Newton step in t before a bracket is known (a factor e^10)


def _stirling_correction(a: float) -> float:
    """``log Gamma(a) - ((a - 1/2) log a - a + log(2 pi) / 2)`` for ``a >= 10`` (A&S
    6.1.41; the first omitted term is below 3e-17 at ``a = 10``)."""
    r = 1.0 / (a * a)
    series = 1.0 / 156.0
    for coefficient in (-691.0 / 360360.0, 1.0 / 1188.0, -1.0 / 1680.0, 1.0 / 1260.0):
        series = coefficient + r * series
    series = -1.0 / 360.0 + r * series
    return (1.0 / 12.0 + r * series) / a


def _log_ratio(u: float, log_ratio: float) -> float:
    """``log(1 + u)``: by ``log1p`` near 0 (where it matters: the ratio is near 1), else the
    given ``log_ratio`` (also defined when the ratio underflows to 0)."""
    return math.log1p(u) if abs(u) < 0.5 else log_ratio


def _log_gamma_front(a: float, t: float, x: float) -> float:
    """``log(x^a e^-x / Gamma(a))`` at ``x = e^t`` (``x pdf(x)`` of the gamma law)."""
    if a < _STIRLING:
        return a * t - x - math.lgamma(a)
    u = (x - a) / a
    return (
        a * (_log_ratio(u, t - math.log(a)) - u)
        + 0.5 * math.log(a)
        - _HALF_LOG_2PI
        - _stirling_correction(a)
    )


def log_gamma_tails(a: float, t: float) -> tuple[float, float]:
    """The logarithms of the regularized incomplete gamma functions.

    Parameters
    ----------
    a : float
        Shape, ``0 < a <= MAX_SHAPE``.
    t : float
        ``log x``, finite.

    Returns
    -------
    (float, float)
        ``log P(a, x)`` and ``log Q(a, x) = log(1 - P(a, x))``.
    """
    x = math.exp(t)
    log_front = _log_gamma_front(a, t, x)
    if x < a + 1.0:
        # A&S 6.5.29: P = x^a e^-x / Gamma(a + 1) * sum_n x^n / ((a + 1) ... (a + n))
        term = total = 1.0
        denominator = a
        for _ in range(_MAX_TERMS):
            denominator += 1.0
            term *= x / denominator
            total += term
            if term < total * _EPS:
                break
        else:  # pragma: no cover - bounded by MAX_SHAPE
            raise ArithmeticError(f"incomplete gamma series did not converge at a={a}, x={x}")
        log_p = log_front - math.log(a) + math.log(total)
        return log_p, math.log1p(-math.exp(log_p))
    # A&S 6.5.31: Q = x^a e^-x / Gamma(a) * 1/(x + 1 - a - 1(1 - a)/(x + 3 - a - ...))
    b = x + 1.0 - a
    c = 1.0 / _TINY
    d = 1.0 / b
    fraction = d
    for i in range(1, _MAX_TERMS):
        coefficient = -i * (i - a)
        b += 2.0
        d = coefficient * d + b
        d = 1.0 / (d if abs(d) >= _TINY else _TINY)
        c = b + coefficient / c
        c = c if abs(c) >= _TINY else _TINY
        delta = d * c
        fraction *= delta
        if abs(delta - 1.0) < _EPS:
            break
    else:  # pragma: no cover - bounded by MAX_SHAPE
        raise ArithmeticError(f"incomplete gamma fraction did not converge at a={a}, x={x}")
    log_q = log_front + math.log(fraction)
    return math.log1p(-math.exp(log_q)), log_q


def _log_gamma_shift(a: float, b: float) -> float:
    """``log Gamma(a + b) - log Gamma(b)`` for ``b >= 10``, by Stirling's series:
    ``a log(a + b) + (b - 1/2) log(1 + a/b) - a`` plus the two series' difference (terms
    of order ``a``, where the two log-gammas are of order ``b log b``)."""
    s = a + b
    return (
        a * math.log(s)
        + (b - 0.5) * math.log1p(a / b)
        - a
        + _stirling_correction(s)
        - _stirling_correction(b)
    )


def _log_beta_front(a: float, b: float, t: float, y: float, w: float) -> float:
    """``log(y^a (1 - y)^b / B(a, b))`` at ``y = e^t``, ``w = 1 - y``."""
    # each of y and w is accurate to its own rounding; log(w) by log1p(-y) for a small y
    log_w = math.log1p(-y) if y < 0.5 else math.log(w)
    if a >= _STIRLING and b >= _STIRLING:
        # a log(y / m) + b log(w / (1 - m)) with m = a / (a + b), and Stirling's series;
        # u = y / m - 1 and v = w / (1 - m) - 1 = -u a / b, from the smaller of y and w
        s = a + b
        if y <= 0.5:
            u = (y - a / s) / (a / s)
            v = -u * a / b
        else:
            v = (w - b / s) / (b / s)
            u = -v * b / a
        corrections = _stirling_correction(a) + _stirling_correction(b) - _stirling_correction(s)
        return (
            a * (_log_ratio(u, t - math.log(a / s)) - u)
            + b * (_log_ratio(v, log_w - math.log(b / s)) - v)
            + 0.5 * math.log(a * b / s)
            - _HALF_LOG_2PI
            - corrections
        )
    if b >= _STIRLING:
        return a * t + b * log_w - math.lgamma(a) + _log_gamma_shift(a, b)
    if a >= _STIRLING:
        return a * t + b * log_w - math.lgamma(b) + _log_gamma_shift(b, a)
    return a * t + b * log_w - (math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b))


def _beta_fraction(a: float, b: float, y: float) -> float:
    """The continued fraction of A&S 26.5.8, ``I_y(a, b) = front / a * fraction``."""
    c = 1.0
    d = 1.0 - (a + b) * y / (a + 1.0)
    d = 1.0 / (d if abs(d) >= _TINY else _TINY)
    fraction = d
    for m in range(1, _MAX_TERMS):
        m2 = 2 * m
        # the even and the odd term of step m
        coefficient = m * (b - m) * y / ((a - 1.0 + m2) * (a + m2))
        d = 1.0 + coefficient * d
        d = 1.0 / (d if abs(d) >= _TINY else _TINY)
        c = 1.0 + coefficient / c
        c = c if abs(c) >= _TINY else _TINY
        fraction *= d * c
        coefficient = -(a + m) * (a + b + m) * y / ((a + m2) * (a + 1.0 + m2))
        d = 1.0 + coefficient * d
        d = 1.0 / (d if abs(d) >= _TINY else _TINY)
        c = 1.0 + coefficient / c
        c = c if abs(c) >= _TINY else _TINY
        delta = d * c
        fraction *= delta
        if abs(delta - 1.0) < _EPS:
            return fraction
    raise ArithmeticError(  # pragma: no cover - bounded by MAX_SHAPE
        f"incomplete beta fraction did not converge at a={a}, b={b}, y={y}"
    )


def log_beta_tails(a: float, b: float, t: float) -> tuple[float, float]:
    """The logarithms of the regularized incomplete beta function and its complement.

    Parameters
    ----------
    a, b : float
        Shapes, ``0 < a, b <= MAX_SHAPE``.
    t : float
        ``log y``, ``t < 0``.

    Returns
    -------
    (float, float)
        ``log I_y(a, b)`` and ``log(1 - I_y(a, b))``.
    """
    log_i, log_j, _ = _beta_tails(a, b, t)
    return log_i, log_j


def _beta_tails(a: float, b: float, t: float) -> tuple[float, float, float]:
    """``log_beta_tails`` and ``log(y^a (1 - y)^(b - 1) / B(a, b))``, the log of the lower
    tail's derivative in ``t``."""
    y = math.exp(t)
    w = -math.expm1(t)
    log_front = _log_beta_front(a, b, t, y, w)
    log_slope = log_front - (math.log1p(-y) if y < 0.5 else math.log(w))
    if y < (a + 1.0) / (a + b + 2.0):
        log_i = log_front + math.log(_beta_fraction(a, b, y) / a)
        return log_i, math.log1p(-math.exp(log_i)), log_slope
    log_j = log_front + math.log(_beta_fraction(b, a, w) / b)
    return math.log1p(-math.exp(log_j)), log_j, log_slope


def _rough_normal_quantile(lower: float, upper: float) -> float:
    """The standard normal quantile at ``lower`` to 4.5e-4 (A&S 26.2.23): a start only."""
    tail = min(lower, upper)
    r = math.sqrt(-2.0 * math.log(tail))
    z = r - (2.515517 + r * (0.802853 + r * 0.010328)) / (
        1.0 + r * (1.432788 + r * (0.189269 + r * 0.001308))
    )
    return -z if lower <= upper else z


def _solve(
    tails: Callable[[float], tuple[float, float, float]],
    log_target: float,
    lower_side: bool,
    t: float,
    hi: float,
    floor: float,
) -> float:
    """``t`` where ``tails(t)`` (the lower and upper log-tails and the log of the lower
    tail's derivative in t) reaches ``log_target``: Newton's method on the lower tail's
    log if ``lower_side``, else on the upper tail's, bisection once bracketed, ``t < hi``.
    It stops at a step below 8 ulps of ``max(|t|, floor)``."""
    lo = -math.inf
    for _ in range(400):
        log_lower, log_upper, log_slope = tails(t)
        if lower_side:  # log P rises with t
            f = log_lower - log_target
            slope = math.exp(log_slope - log_lower)
        else:  # -log Q rises with t
            f = log_target - log_upper
            slope = math.exp(log_slope - log_upper)
        if f == 0.0:
            return t
        if f < 0.0:
            lo = max(lo, t)
        else:
            hi = min(hi, t)
        tolerance = 8.0 * _EPS * max(abs(t), floor)
        new = t - f / slope if slope > 0.0 else math.nan
        if abs(new - t) <= tolerance:  # converged (a step below rounding lands on t)
            return new
        if not lo < new < hi:
            if math.isfinite(lo) and math.isfinite(hi):
                new = 0.5 * (lo + hi)
            else:
                new = t + (_STEP_LIMIT if f < 0.0 else -_STEP_LIMIT)
            if abs(new - t) <= tolerance:
                return new
        t = new
    raise ArithmeticError("quantile iteration did not converge")  # pragma: no cover


def gamma_inverse(a: float, lower: float, upper: float) -> float:
    """``x`` with ``P(a, x) = lower``, i.e. ``Q(a, x) = upper``.

    Parameters
    ----------
    a : float
        Shape, ``0 < a <= MAX_SHAPE``.
    lower, upper : float
        The two tail probabilities, ``lower + upper = 1``, each in (0, 1); the smaller one
        is matched, so give both exactly (e.g. ``upper = q`` and ``lower = 1 - q`` for an
        upper-tail quantile).

    Returns
    -------
    float
        The quantile of the standard gamma law with shape ``a``.
    """
    # start: Wilson & Hilferty's cube of a normal quantile (A&S 26.4.17), or the leading
    # term of the series, x ~ (lower a Gamma(a))^(1/a), where that cube is not positive
    z = _rough_normal_quantile(lower, upper)
    cube = 1.0 - 1.0 / (9.0 * a) + z / (3.0 * math.sqrt(a))
    if cube > 0.0:
        t = math.log(a) + 3.0 * math.log(cube)
    else:
        t = (math.log(lower) + math.log(a) + math.lgamma(a)) / a

    def tails(t: float) -> tuple[float, float, float]:
        log_p, log_q = log_gamma_tails(a, t)
        return log_p, log_q, _log_gamma_front(a, t, math.exp(t))

    use_lower = lower <= upper
    # x = e^t to 8 ulps of max(|t|, 1): the relative accuracy t itself carries
    log_target = math.log(lower if use_lower else upper)
    return math.exp(_solve(tails, log_target, use_lower, t, math.inf, 1.0))


def beta_inverse(a: float, b: float, lower: float, upper: float) -> tuple[float, float]:
    """``(y, 1 - y)`` with ``I_y(a, b) = lower``, i.e. ``1 - I_y(a, b) = upper``.

    Parameters
    ----------
    a, b : float
        Shapes, ``0 < a, b <= MAX_SHAPE``.
    lower, upper : float
        The two tail probabilities, ``lower + upper = 1``, each in (0, 1); the smaller one
        is matched.

    Returns
    -------
    (float, float)
        The quantile ``y`` of the beta law and ``1 - y``, each to its own relative accuracy
        (the F law's quantile ``d y / (n (1 - y))`` needs both).
    """
    if upper < lower:  # the upper tail of B(a, b) is the lower tail of B(b, a) at 1 - y
        w, y = beta_inverse(b, a, upper, lower)
        return y, w
    # start: with both shapes above 0.6, A&S 26.5.22's normal approximation (Newton then
    # takes 3-4 steps); else the series' leading term, y ~ (lower a B(a, b))^(1/a), at
    # most the mean
    log_beta = math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b)
    t = min((math.log(lower) + math.log(a) + log_beta) / a, math.log(a / (a + b)))
    if a > 0.6 and b > 0.6:
        z = -_rough_normal_quantile(lower, upper)  # the upper normal quantile at lower
        lam = (z * z - 3.0) / 6.0
        h = 2.0 / (1.0 / (2.0 * a - 1.0) + 1.0 / (2.0 * b - 1.0))
        if h + lam > 0.0:
            w = z * math.sqrt(h + lam) / h - (1.0 / (2.0 * b - 1.0) - 1.0 / (2.0 * a - 1.0)) * (
                lam + 5.0 / 6.0 - 2.0 / (3.0 * h)
            )
            # y = a / (a + b e^(2w)): t = -log(1 + e^x), x = log(b/a) + 2w, without overflow
            x = math.log(b / a) + 2.0 * w
            t = -(x + math.log1p(math.exp(-x))) if x > 0.0 else -math.log1p(math.exp(x))

    # relative to |t| alone: near y = 1, 1 - y = -expm1(t) needs t to its own accuracy
    t = _solve(lambda t: _beta_tails(a, b, t), math.log(lower), True, t, 0.0, 0.0)
    return math.exp(t), -math.expm1(t)


__all__ = [
    "MAX_SHAPE",
    "beta_inverse",
    "gamma_inverse",
    "log_beta_tails",
    "log_gamma_tails",
]
