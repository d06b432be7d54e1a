"""Robust (clipped) mean squares of Gaussian terms: their null moments, Huber's scale and
its degrees of freedom.

The squares of standardized Gaussian terms clipped at c, ``q = min(z^2, c^2)``, bound what
one outlier adds to a sum; their mean, variance and lag-1 covariance are closed form or one
integral (:func:`clipped_square_moments`), a sum of k of them has the Satterthwaite degrees
of freedom of :func:`equivalent_dof`, and the scale that makes their mean what a Gaussian
gives is Huber's "proposal 2" (:func:`robust_scale`; Huber, *Robust Statistics*, 1981, §5.3)
with the degrees of freedom of :func:`scale_estimator_dof`. noise-glr's windowed test, its
sequential test under a budget, cnn-map's input test and the firmware voters' noise
estimates share them.
"""

from __future__ import annotations

import functools

import numpy as np

from imufdi_cli.maths.quantiles import norm

#: Lag-1 correlation of the differences of a white sequence.
DIFFERENCE_CORRELATION = -0.5


def _truncated_square_mean(mean: np.ndarray, std: float, clip: float) -> np.ndarray:
    """``E[min(Y^2, c^2)]`` for Y ~ N(mean, std^2) (elementwise in ``mean``)."""
    lo, hi = (-clip - mean) / std, (clip - mean) / std
    inside = norm.cdf(hi) - norm.cdf(lo)
    pdf_lo, pdf_hi = norm.pdf(lo), norm.pdf(hi)
    # E[(m + s Z)^2 ; lo < Z < hi]
    square = (
        mean**2 * inside
        + 2.0 * mean * std * (pdf_lo - pdf_hi)
        + std**2 * (inside + lo * pdf_lo - hi * pdf_hi)
    )
    return square + clip**2 * (1.0 - inside)


@functools.lru_cache(maxsize=64)
def clipped_square_moments(clip: float, rho: float = DIFFERENCE_CORRELATION) -> tuple[float, ...]:
    """Null moments of ``q = min(z^2, c^2)`` for standard normal z.

    A pure function of ``(clip, rho)``, memoised per process (the same tuple of floats):
    each fit asks for it three times and :func:`samples_for_factor` once per bisection
    step, and the lag-1 integral over 24 001 grid points costs about 8 ms of CPU.

    Parameters
    ----------
    clip : float
        c, in standard deviations; ``inf`` for plain squares.
    rho : float
        Correlation of consecutive z (differences of white noise: -1/2).

    Returns
    -------
    mean, variance, lag1_covariance : float
        ``E q``, ``Var q`` (truncated normal moments, closed form) and
        ``Cov(q_t, q_{t+1})`` (one integral over z_t of ``E[q_{t+1} | z_t]``, with
        ``z_{t+1} | z_t ~ N(rho z_t, 1 - rho^2)``; for c = inf it is ``2 rho^2``).
    """
    if not np.isfinite(clip):
        return 1.0, 2.0, 2.0 * rho**2
    tail = 2.0 * norm.sf(clip)
    inside = 1.0 - tail
    pdf = norm.pdf(clip)
    second = inside - 2.0 * clip * pdf  # E[z^2 ; |z| < c]
    fourth = 3.0 * inside - 2.0 * pdf * (clip**3 + 3.0 * clip)  # E[z^4 ; |z| < c]
    mean = second + clip**2 * tail
    variance = fourth + clip**4 * tail - mean**2
    grid = np.linspace(-12.0, 12.0, 24001)
    weight = norm.pdf(grid) * np.minimum(grid**2, clip**2)
    conditional = _truncated_square_mean(rho * grid, float(np.sqrt(1.0 - rho**2)), clip)
    joint = float(np.sum(weight * conditional) * (grid[1] - grid[0]))
    return float(mean), float(variance), joint - float(mean) ** 2


def equivalent_dof(counts: np.ndarray, moments: tuple[float, ...]) -> np.ndarray:
    """Satterthwaite degrees of freedom of a sum of k consecutive q (lag-1 dependent).

    ``nu_k = 2 (k mu)^2 / (k v + 2 (k - 1) c1)``, so that ``sum(q)/(k mu)`` has the mean and
    variance of ``chi2(nu_k)/nu_k``.
    """
    mean, variance, lag1 = moments
    k = np.asarray(counts, dtype=np.float64)
    return 2.0 * (k * mean) ** 2 / (k * variance + 2.0 * np.maximum(k - 1.0, 0.0) * lag1)


def scale_estimator_dof(count: int, clip: float) -> float:
    """Equivalent degrees of freedom of the calibrated scale tau (``robust_scale``).

    Parameters
    ----------
    count : int
        N, the number of calibration differences (lag-1 correlated, rho = -1/2).
    clip : float
        c, in standard deviations (``inf``: the plain mean square).

    Returns
    -------
    float
        ``nu_cal = 2 / Var(ln tau_hat)``, so that ``tau_hat / tau ~ chi2(nu_cal)/nu_cal``
        to two moments. Linearizing the estimating equation ``mean(min(d^2/tau, c^2)) = mu``
        gives ``Var(ln tau_hat) = Var(mean q) / s^2`` with ``s = E[z^2 ; |z| < c]`` (the
        derivative of the clipped square; Huber, *Robust Statistics*, 1981, §5.3) and
        ``Var(mean q) = (N v + 2 (N - 1) c1) / N^2`` (lag-1 dependent q). Hence
        ``nu_cal = nu_N (s / mu)^2`` with ``nu_N`` of :func:`equivalent_dof`: clipping at
        c = 3 costs 5 % of the calibration's degrees of freedom (``s/mu = 0.976``).
    """
    moments = clipped_square_moments(clip)
    mean = moments[0]
    inner = mean - clip**2 * 2.0 * norm.sf(clip) if np.isfinite(clip) else 1.0
    dof = float(equivalent_dof(np.array([max(count, 1)]), moments)[0])
    return dof * (inner / mean) ** 2


def robust_scale(differences: np.ndarray, clip: float, mean: float) -> np.ndarray:
    """Per-column tau with ``mean(min(d^2/tau, c^2)) = E q`` (Huber's proposal 2).

    Parameters
    ----------
    differences : ndarray, shape (N, n)
    clip, mean : float
        c and the null mean of q for that c.

    Returns
    -------
    tau : ndarray, shape (n,)
        Variance of d (for Gaussian d, an estimate of Var d).
    """
    squares = differences**2
    tau = np.mean(squares, axis=0)
    if not np.isfinite(clip):
        return tau
    tau = np.maximum(np.median(squares, axis=0) / 0.4549364231195724, 1e-300)
    for _ in range(200):  # fixed point, monotone convergence
        updated = tau * np.mean(np.minimum(squares / tau, clip**2), axis=0) / mean
        done = np.all(np.abs(updated - tau) <= 1e-12 * np.abs(tau))
        tau = np.maximum(updated, 1e-300)
        if done:
            break
    return tau
