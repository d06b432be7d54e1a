"""The firmware-style voters under a false-alarm budget: their thresholds scaled to it.

px4-selector and ap-consistency keep the firmware's rule (the same statistic, filter, hold
time and threshold ratios); with ``false_alarms`` > 0 every threshold of a sensor type is
multiplied by one factor ``s``, chosen at fit time so that fault-free data with the
calibrated noise raise the budget's share of false alarm episodes on that channel:

* **ap-consistency** (:func:`ap_limit_scale`): an IMU fails when
  ``|W (x_i - x_ref)| > s e_i`` on each of the last h samples. Without a fault the
  difference is white, so with ``p_i = P(|W Delta_i| > s e_i)`` the runs of h failures
  start ``(1 - p_i) p_i^h`` times per sample (exact for independent samples), summed over
  the IMUs that can fail (a union bound). ``p_i`` is the tail of a weighted sum of three
  squared Gaussians (:func:`weighted_chi2_sf`). The rate is averaged over the error of the
  calibrated variances; for the firmware's 10 s hold it is extremely sensitive to them
  (``p^h`` with h = 1001: a variance 6 % too low triples the rate).
* **px4-selector** (:func:`px4_scale`): the accumulated error ``E_i`` of an IMU whose
  smoothed deviation ``|d_i|`` exceeds ``s r`` must exceed ``s A``. ``|d_i|`` is an
  exponentially smoothed (time constant ``dt / c``) norm, strongly correlated in time, and
  at a budget ``s r`` sits not far above its mean: an episode is a long excursion of the
  smoothed disagreement, far in the tail of its time averages. ``|d|``
  is a Markov chain (the filter of isotropic white noise), so E is a reflected
  Markov-modulated random walk, whose upcrossings of a level u fall as
  ``C exp(-theta* u)`` with theta* the root of the log Perron root of the tilted
  transition kernel (Lundberg's exponent); theta* is computed from the kernel, C from a
  short simulation of the recursion at low levels (:func:`px4_null_rate`); s is the
  smallest factor whose rate, the calibrated offsets' error included, meets the budget
  and leaves at most :data:`PERMANENT_SHARE` of calibrations with an IMU whose offset
  error alone keeps it in alarm (:func:`px4_scale`).

Both assume what the firmware assumes: the IMUs disagree only by their white noise. On an
array whose IMUs disagree more (accelerometer lever arms in rotation, scale and
misalignment errors in motion, the wander of real chips) the level does not hold;
:class:`Disagreement` measures it on the processed data and the detector warns
(``calibration_warnings``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from functools import lru_cache
from typing import Any

import numpy as np

from imufdi_cli.maths.robust import clipped_square_moments, robust_scale, scale_estimator_dof
from imufdi_cli.maths.sequential.thresholds import bisect_boundary

#: The thresholds are set for this share of the budget (the parity detectors' margin).
BUDGET_SHARE = 0.5
#: Clip of the robust (Huber proposal 2) noise scale, standard deviations.
SCALE_CLIP = 3.0
#: px4-selector under a budget: at most this share of calibrations leaves an IMU whose
#: offset error alone keeps its smoothed deviation above the scaled rate threshold (an
#: alarm for the whole log).
PERMANENT_SHARE = 0.01
#: Detect warns when, over seconds of the log, the median IMU disagreed more than this many
#: times the calibrated noise variance ...
DISAGREEMENT_WARNING = 2.0
#: ... on at least this share of the log's seconds (and 2 of them).
WARNING_SHARE = 0.005


def outlier_fraction(values: np.ndarray, variance: np.ndarray) -> float:
    """Share of the samples (rows of ``values`` (N, k, 3)) with a component beyond
    ``OUTLIER_LEVEL`` standard deviations (``variance`` (k, 3)) of the noise, less what a
    Gaussian puts there (at least 0)."""
    from imufdi_cli.maths.sequential import OUTLIER_LEVEL

    z = np.abs(values) / np.sqrt(np.maximum(variance, 1e-300))[None]
    beyond = np.count_nonzero((z > OUTLIER_LEVEL).any(axis=2))
    total = values.shape[0] * values.shape[1]
    gaussian = 1.0 - (1.0 - math.erfc(OUTLIER_LEVEL / math.sqrt(2.0))) ** 3
    return max(0.0, beyond / max(total, 1) - gaussian)


def difference_noise(values: np.ndarray, robust: bool = True) -> tuple[np.ndarray, float]:
    """Noise variance of every column of ``values`` (N, ...) from its first differences
    (``Var(x_t - x_{t-1}) / 2``; smooth motion cancels), and the estimate's equivalent
    degrees of freedom: robustly (Huber's proposal 2 at :data:`SCALE_CLIP`: the Gaussian
    part, outliers left out) or the plain mean square (outliers' power included)."""
    flat = values.reshape(values.shape[0], -1)
    differences = np.diff(flat, axis=0)
    clip = SCALE_CLIP if robust else math.inf
    mean = clipped_square_moments(clip)[0]
    variance = robust_scale(differences, clip, mean) / 2.0
    dof = scale_estimator_dof(max(differences.shape[0], 2), clip)
    return variance.reshape(values.shape[1:]), float(dof)


def imu_noise(deviation_variance: np.ndarray) -> np.ndarray:
    """Per-IMU noise variances (m, 3) from the variances (m, 3) of each IMU's deviation from
    the array mean, ``v_i = sigma_i^2 (1 - 2/m) + S / m^2`` with ``S = sum_j sigma_j^2``
    (per axis); for 2 IMUs the deviations cannot tell the two apart and each gets ``2 v``."""
    v = np.asarray(deviation_variance, float)
    m = v.shape[0]
    if m <= 2:
        return 2.0 * v
    total = v.sum(axis=0) / (1.0 - 1.0 / m)  # S per axis
    sigma2 = (v - total / m**2) / (1.0 - 2.0 / m)
    return np.maximum(sigma2, 0.05 * v)


def accumulate_excess(excess: np.ndarray, start: np.ndarray) -> np.ndarray:
    """``E_t = max(0, E_{t-1} + x_t)`` for every column, vectorised (Lindley's recursion).

    With ``C_t = x_1 + ... + x_t``: ``E_t = C_t - min(-E_0, min_{s<=t} C_s)``.

    Parameters
    ----------
    excess : ndarray, shape (N, m)
        Increments x_t.
    start : ndarray, shape (m,)
        E_0 (>= 0).

    Returns
    -------
    ndarray, shape (N, m)
    """
    if excess.shape[0] == 0:
        return np.zeros_like(excess)
    cumulative = np.cumsum(excess, axis=0)
    floor = np.minimum(np.minimum.accumulate(cumulative, axis=0), -start[None, :])
    return np.maximum(cumulative - floor, 0.0)


# --- ap-consistency --------------------------------------------------------------------


_LEGENDRE = np.polynomial.legendre.leggauss(48)
_ANGLES = 2.0 * math.pi * (np.arange(64) + 0.5) / 64


def weighted_chi2_sf(threshold: np.ndarray | float, weights: np.ndarray) -> np.ndarray:
    """``P(a_1 u_1^2 + a_2 u_2^2 + a_3 u_3^2 > t)`` for independent standard normal u and
    weights ``a`` (3,) > 0, at every ``t`` (any shape).

    The two smaller weights in polar coordinates (``P(a_1 u_1^2 + a_2 u_2^2 > t') =
    mean_phi exp(-t' / (2 g(phi)))``, ``g = a_1 cos^2 + a_2 sin^2``: the trapezoid rule on
    64 angles, exact to rounding for a periodic integrand this smooth), the largest by
    Gauss-Legendre quadrature over ``|u_3| < sqrt(t / a_3)`` plus the tail beyond it; both
    tails are computed directly, so tiny and near-1 probabilities keep their precision."""
    a = np.sort(np.asarray(weights, float))
    t = np.atleast_1d(np.asarray(threshold, float))
    g = a[0] * np.cos(_ANGLES) ** 2 + a[1] * np.sin(_ANGLES) ** 2  # (64,)
    half = np.sqrt(np.maximum(t, 0.0) / a[2])  # (T,)
    nodes, node_weights = _LEGENDRE
    u3 = half[:, None] * nodes[None, :]  # (T, 48)
    remaining = np.maximum(t[:, None] - a[2] * u3**2, 0.0)  # (T, 48)
    inner = np.exp(-remaining[:, :, None] / (2.0 * g[None, None, :])).mean(axis=2)
    density = np.exp(-0.5 * u3**2) / math.sqrt(2.0 * math.pi)
    inside = half * (density * inner * node_weights[None, :]).sum(axis=1)
    outside = np.array([math.erfc(h / math.sqrt(2.0)) for h in half])
    out = np.where(t <= 0, 1.0, np.minimum(inside + outside, 1.0))
    return out.reshape(np.shape(threshold))


#: Gauss-Hermite nodes and weights (probabilists', 9 points) of the variance-error average.
_HERMITE = np.polynomial.hermite_e.hermegauss(9)


def _error_points(dof: float) -> list[tuple[float, float]]:
    """(factor on the calibrated variances, weight) of the average over their relative
    error ``N(0, 2 / dof)``."""
    if not math.isfinite(dof) or dof <= 0:
        return [(1.0, 1.0)]
    spread = math.sqrt(2.0 / dof)
    nodes, weights = _HERMITE
    weights = weights / weights.sum()
    return [(max(0.2, 1.0 + spread * x), float(w)) for x, w in zip(nodes, weights)]


def ap_episode_rate(
    scale: float,
    variances: np.ndarray,
    weights: np.ndarray,
    limits: np.ndarray,
    hold: int,
    dof: float,
    contamination: float = 0.0,
) -> float:
    """Expected false episodes per sample of ap-consistency at limits ``scale * limits``:
    ``sum_i E[(1 - p_i) p_i^h]`` over the IMUs that can fail (rows of ``variances``, the
    per-axis variances (k, 3) of their differences, body frame), averaged over the
    variances' error (``dof`` degrees of freedom); a share ``contamination`` of samples
    are outliers that always fail."""
    total = 0.0
    for factor, weight in _error_points(dof):
        for variance, limit in zip(variances, limits):
            a = np.maximum(np.asarray(weights, float) ** 2 * variance * factor, 1e-300)
            p = float(weighted_chi2_sf((scale * limit) ** 2, a))
            p = contamination + (1.0 - contamination) * p
            if p <= 0.0:
                continue
            log_rate = math.log1p(-p) + hold * math.log(p) if p < 1.0 else 0.0
            total += weight * (math.exp(log_rate) if p < 1.0 else 1.0)
    return total


def _smallest_scale(too_small: Callable[[float], bool], low: float, high: float) -> float:
    """The scale at the bisected boundary of ``too_small`` (a predicate on log s) between
    ``low`` (too small) and ``high`` (not), to 1e-5 in log s: the upper end, so the
    scale returned is never one the predicate refuses."""
    return math.exp(bisect_boundary(too_small, low, high, 1e-5))


def ap_limit_scale(
    variances: np.ndarray,
    weights: np.ndarray,
    limits: np.ndarray,
    hold: int,
    per_sample: float,
    dof: float,
    contamination: float = 0.0,
) -> float:
    """The factor s on every limit whose :func:`ap_episode_rate` is ``per_sample``.

    The rate ``(1 - p) p^h`` is largest at ``p = h / (h + 1)``; below that scale the IMU
    fails on nearly every sample (one endless episode, not few), so s is sought above the
    largest scale of that peak over the IMUs, where the rate falls with s (bisection on
    log s). If even the peak is below the budget, s is that peak."""
    target = math.log(per_sample)
    weights = np.asarray(weights, float)

    def log_scale_of(variance: np.ndarray, limit: float, probability: float) -> float:
        """log s with ``P(|W Delta| > s e) = probability`` for one IMU (bisection)."""
        a = np.maximum(weights**2 * variance, 1e-300)
        unit = math.sqrt(float(a.max())) / limit
        low, high = math.log(unit) - 30.0, math.log(unit) + 10.0
        for _ in range(80):
            middle = 0.5 * (low + high)
            if float(weighted_chi2_sf((math.exp(middle) * limit) ** 2, a)) > probability:
                low = middle
            else:
                high = middle
        return 0.5 * (low + high)

    def gap(log_scale: float) -> float:
        rate = ap_episode_rate(
            math.exp(log_scale), variances, weights, limits, hold, dof, contamination
        )
        return math.log(max(rate, 1e-300)) - target

    peak = hold / (hold + 1.0)
    low = max(log_scale_of(v, float(e), peak) for v, e in zip(variances, limits))
    if gap(low) <= 0:
        return math.exp(low)
    # an IMU's p falls below the per-sample budget itself at this scale: far enough
    high = max(log_scale_of(v, float(e), per_sample) for v, e in zip(variances, limits)) + 0.5
    for _ in range(20):
        if gap(high) <= 0:
            break
        high += 1.0
    else:  # outliers alone exceed the budget: the largest scale tried
        return math.exp(high)
    return _smallest_scale(lambda log_scale: gap(log_scale) > 0, low, high)


# --- px4-selector ----------------------------------------------------------------------


def _norm_kernel(smoothing: float, top: float, cells: int) -> tuple[np.ndarray, np.ndarray]:
    """Transition matrix (cells, cells) of ``|d|`` for ``d' = (1 - c) d + c u`` (u standard
    normal in 3 dimensions; sigma units) on ``[0, top]`` in equal cells, from the cell
    centres (the mass beyond ``top`` in the last cell): ``|d'| / c`` given ``|d|`` is a
    noncentral chi with 3 degrees of freedom and noncentrality ``(1 - c) |d| / c``, whose
    CDF is ``Phi(R - m) + Phi(R + m) - 1 + (phi(R + m) - phi(R - m)) / m``."""
    from imufdi_cli.maths.quantiles import norm

    c = smoothing
    edges = np.linspace(0.0, top, cells + 1)
    centres = 0.5 * (edges[1:] + edges[:-1])
    m = (1.0 - c) * centres[:, None] / c
    r = edges[None, :] / c
    cdf = norm.cdf(r - m) + norm.cdf(r + m) - 1.0 + (norm.pdf(r + m) - norm.pdf(r - m)) / m
    cdf[:, 0] = 0.0
    cdf[:, -1] = 1.0
    return centres, np.diff(cdf, axis=1)


def _log_perron(theta: float, rho: float, centres: np.ndarray, kernel: np.ndarray) -> float:
    """log of the Perron root of the kernel tilted by ``exp(theta (|d'| - rho))``."""
    tilted = kernel * np.exp(theta * (centres - rho))[None, :]
    return math.log(float(np.max(np.abs(np.linalg.eigvals(tilted)))))


def lundberg_exponent(rho: float, smoothing: float) -> float:
    """theta* > 0 with ``Lambda(theta*) = 0``, Lambda the log Perron root of the tilted
    kernel of ``|d|`` (:func:`_norm_kernel`): the decay rate of ``P(E > u) ~ C
    exp(-theta* u)`` for the reflected walk E with the Markov-modulated increments
    ``|d| - rho`` (Asmussen, *Applied Probability and Queues*, 2003, XIII.8). Brent's
    method on 80 and 160 cells, extrapolated (Richardson, the error falls as the square
    of the cell width: 0.2 % left, tested)."""
    from scipy.optimize import brentq  # imported when a budget is fitted

    unit = math.sqrt(smoothing / (2.0 - smoothing))
    found = []
    for cells in (80, 160):
        centres, kernel = _norm_kernel(smoothing, rho + 14.0 * unit, cells)
        high = 0.5
        while _log_perron(high, rho, centres, kernel) <= 0.0 and high < 1e6:
            high *= 2.0
        low = high / 2.0
        while _log_perron(low, rho, centres, kernel) > 0.0 and low > 1e-9:
            low /= 2.0
        found.append(
            brentq(lambda t, c=centres, k=kernel: _log_perron(t, rho, c, k), low, high, xtol=1e-6)
        )
    return found[1] + (found[1] - found[0]) / 3.0


def _log_prefactor(
    rho: float, smoothing: float, theta: float, seed: int, chains: int = 32, length: int = 8192
) -> tuple[float, int]:
    """``log C`` of the upcrossing count ``C exp(-theta u)`` of E's levels u, from a
    simulation of the recursion (chains of ``length`` samples from the filter's stationary
    law): the median of ``log count(u) + theta u`` over the upper half of the levels that
    at least 50 upcrossings reach; and the samples simulated."""
    from scipy.signal import lfilter  # imported when a budget is fitted

    c = smoothing
    rng = np.random.default_rng([seed, 0x9F4, round(rho * 1e9)])
    unit = math.sqrt(c / (2.0 - c))
    start = ((1.0 - c) * rng.standard_normal((chains, 3)) * unit)[None]
    d, _ = lfilter(
        [c], [1.0, -(1.0 - c)], rng.standard_normal((length, chains, 3)), axis=0, zi=start
    )
    energy = accumulate_excess(np.linalg.norm(d, axis=2) - rho, np.zeros(chains))
    before, after = energy[:-1], energy[1:]
    rising = after > before
    lows, highs = np.sort(before[rising]), np.sort(after[rising])
    levels = np.linspace(0.0, float(energy.max()), 200)[1:]
    counts = np.searchsorted(lows, levels, side="right") - np.searchsorted(
        highs, levels, side="right"
    )
    reliable = counts >= 50
    samples = chains * length
    if np.count_nonzero(reliable) < 2:
        return math.log(max(int(counts.max()), 1)), samples
    values = np.log(counts[reliable]) + theta * levels[reliable]
    return float(np.median(values[values.size // 2 :])), samples


#: E|d| of the filter's stationary law, in sigma units per unit of ``sqrt(c / (2 - c))``.
_MEAN_NORM = 1.5957691216057308  # 2 sqrt(2 / pi)


@lru_cache(maxsize=8)
def _px4_curve(smoothing: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rho, theta*, log C per sample)`` on a grid of rho from 1.03 to 2 times E|d|
    (sigma units): the Lundberg exponent (:func:`lundberg_exponent`) and the prefactor
    (:func:`_log_prefactor`) of one IMU's upcrossing rate ``C exp(-theta* u)``. Neither
    depends on the level, so one grid serves every hold and budget."""
    mean = math.sqrt(smoothing / (2.0 - smoothing)) * _MEAN_NORM
    grid = mean * np.geomspace(1.03, 2.0, 12)
    thetas, logs = [], []
    for rho in grid:
        theta = lundberg_exponent(float(rho), smoothing)
        log_c, samples = _log_prefactor(float(rho), smoothing, theta, seed)
        thetas.append(theta)
        logs.append(log_c - math.log(samples))
    return grid, np.array(thetas), np.array(logs)


def px4_null_rate(rho: np.ndarray | float, hold: float, smoothing: float, seed: int) -> np.ndarray:
    """False episodes per sample of one IMU of px4-selector (sigma units) at ``rho`` (any
    shape): the upcrossings of ``H rho`` by ``E' = max(0, E + |d'| - rho)``,
    ``C exp(-theta* H rho)`` with the Lundberg exponent theta* and the prefactor C
    interpolated on :func:`_px4_curve` (checked against a direct simulation of the
    recursion, tests). At or below 1.03 E|d| E drifts up and every sample alarms: 1."""
    grid, thetas, logs = _px4_curve(float(smoothing), int(seed))
    x = np.asarray(rho, float)
    theta = np.interp(x, grid, thetas)
    log_c = np.interp(x, grid, logs)
    beyond = x > grid[-1]  # linear extrapolation of theta* (it grows steadily)
    slope = (thetas[-1] - thetas[-2]) / (grid[-1] - grid[-2])
    theta = np.where(beyond, thetas[-1] + slope * (x - grid[-1]), theta)
    rate = np.exp(np.minimum(log_c - theta * hold * x, 0.0))
    return np.where(x <= grid[0], 1.0, rate)


def px4_scale(
    noise_variance: np.ndarray,
    smoothing: float,
    step: float,
    rate_threshold: float,
    accumulated_threshold: float,
    per_sample: float,
    dof: float,
    calibration_samples: float,
    seed: int = 0,
) -> float:
    """The factor s on (r, A) whose modelled false episode rate is at most ``per_sample``.

    Every IMU's deviation from the array mean is taken as isotropic white noise of the
    largest per-IMU sigma of the array (the mean of an IMU's three axis variances; the
    noisiest IMU sets the level of a threshold all IMUs share, the others alarm less),
    raised by two standard errors of that estimate. The calibration's offset error b of
    each IMU (``N(0, sigma_i^2 / N)`` per axis) stays in its smoothed deviation for the
    whole log; since ``|d + b| <= |d| + |b|``, IMU i alarms at most as often as the
    isotropic null at ``rho = (s r - |b_i|) / sigma``, averaged over the chi-3 law of
    ``|b_i|`` (24 equal-probability points), and the channel's rate is bounded by the sum
    over the IMUs (:func:`px4_null_rate`). An offset error that leaves ``s r`` at or
    below the mean of ``|d + b|`` is one alarm that never ends, not a rate: s is also large
    enough that this happens on at most :data:`PERMANENT_SHARE` of calibrations. With a
    2 s calibration that condition sets s (the offsets' error, not the noise, limits the
    firmware rule at a low budget).

    Parameters
    ----------
    noise_variance : ndarray, shape (m, 3)
        Per-IMU, per-axis variance of the deviation from the array mean, body frame, SI.
    smoothing, step : float
        The firmware filter's gain c and the accumulated time step (s).
    rate_threshold, accumulated_threshold : float
        The firmware's r and A (SI).
    per_sample : float
        Episodes per sample to meet.
    dof : float
        Degrees of freedom of each per-axis variance estimate.
    calibration_samples : float
        N, the samples the offsets were averaged over (inf: no offset error).
    seed : int
        Seed of the null simulation.
    """
    from imufdi_cli.maths.quantiles import chi2

    variance = np.asarray(noise_variance, float)
    imus = variance.shape[0]
    per_imu = variance.mean(axis=1)
    sigma = math.sqrt(float(per_imu.max()))
    if math.isfinite(dof) and dof > 0:
        sigma *= 1.0 + 2.0 / math.sqrt(2.0 * 3.0 * dof)  # sd of a sigma from 3 dof
    hold = accumulated_threshold / (rate_threshold * step)
    mean = math.sqrt(smoothing / (2.0 - smoothing)) * _MEAN_NORM
    floor = _px4_curve(float(smoothing), int(seed))[0][0]  # below: E drifts up for ever
    if math.isfinite(calibration_samples) and calibration_samples > 0:
        offset_sd = np.sqrt(per_imu / calibration_samples)  # (m,) per axis, SI
    else:
        offset_sd = np.zeros(imus)
    quantiles = (np.arange(24) + 0.5) / 24.0
    radii = np.sqrt(chi2.ppf(quantiles, 3))  # |b| / offset_sd at 24 equal-probability points

    def permanent(scale: float) -> float:
        """Probability that some IMU's offset error alone keeps ``|d + b|`` above r."""
        room = (scale * rate_threshold - floor * sigma) / np.maximum(offset_sd, 1e-300)
        return float(np.sum(np.where(room > 0, chi2.sf(np.maximum(room, 0.0) ** 2, 3), 1.0)))

    def log_total(scale: float) -> float:
        rho = (scale * rate_threshold - offset_sd[:, None] * radii[None, :]) / sigma
        rate = px4_null_rate(rho, hold, smoothing, seed)
        # a point below the floor is a log that alarms for ever (counted by `permanent`)
        rate = np.where(rho > floor, rate, 0.0).mean(axis=1).sum()
        return math.log(max(float(rate), 1e-300))

    target = math.log(per_sample)
    low = math.log(mean * sigma / rate_threshold)  # at the mean: rate 1 per IMU
    high = low + 0.5
    while log_total(math.exp(high)) > target or permanent(math.exp(high)) > PERMANENT_SHARE:
        high += 0.5
    return _smallest_scale(
        lambda log_scale: (
            log_total(math.exp(log_scale)) > target
            or permanent(math.exp(log_scale)) > PERMANENT_SHARE
        ),
        low,
        high,
    )


# --- what the model assumes, checked on the data ---------------------------------------


class Disagreement:
    """Whether the IMUs still disagree by the calibrated noise only, second by second.

    Each compared IMU's ``|x_i - ref_i|^2`` (after the calibration offsets) relative to its
    expectation from the calibrated noise feeds a :class:`~imufdi_cli.maths.contrasts.ModelCheck`
    over windows of ``window`` samples: a window is flagged when the median IMU disagrees
    more than :data:`DISAGREEMENT_WARNING` times as much (one faulty IMU does not move it).
    """

    def __init__(self, expected: np.ndarray, window: int) -> None:
        from imufdi_cli.maths.contrasts import ModelCheck

        self.expected = np.maximum(np.asarray(expected, float), 1e-300)  # (m,)
        self.check = ModelCheck(self.expected.size, window, DISAGREEMENT_WARNING)

    def add(self, deviation: np.ndarray) -> None:
        """Deviations (N, m, 3) of the next samples."""
        self.check.push(np.einsum("nka,nka->nk", deviation, deviation) / self.expected)

    def warning(self, detector: str, sensor_type: str, what: str) -> str | None:
        """One line when the flagged time is not negligible (:data:`WARNING_SHARE` of the
        windows, and 2 of them), else None."""
        check = self.check
        if check.flagged < max(2, WARNING_SHARE * check.windows):
            return None
        return (
            f"{detector}: {sensor_type}: on {check.flagged} s of this log"
            f" ({100 * check.share():.2g} %) the IMUs disagreed more than"
            f" {DISAGREEMENT_WARNING:g}x (up to {check.worst:.3g}x, in variance, median IMU)"
            f" the calibrated noise its budget {what} assume: lever arms, motion or sensor"
            " errors the firmware rule does not model; the false-alarm budget does not hold"
            " there"
        )

    def metadata(self) -> dict[str, float]:
        return {
            "seconds_beyond_the_noise_model": float(self.check.flagged),
            "seconds_checked": float(self.check.windows),
            "worst_disagreement_ratio": self.check.worst,
        }


def disagreement_warnings(detector: str, states: Mapping[str, Any], what: str) -> list[str]:
    """:meth:`Disagreement.warning` of every sensor type's state (its ``disagreement``,
    None when the type runs without a budget) that has one to give."""
    messages = []
    for sensor_type, state in states.items():
        if state.disagreement is None:
            continue
        note = state.disagreement.warning(detector, sensor_type, what)
        if note is not None:
            messages.append(note)
    return messages
