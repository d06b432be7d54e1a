"""Sequential decisions under a false-alarm budget: a bank of robust CUSUM tests.

A per-sample test at level alpha raises ``alpha x rate`` false alarms a second (3,600 an
hour at 1 % and 100 Hz). A user who records for hours acts on decisions that are wrong
about once a day, and still wants a real fault caught within a fraction of a second. That
is quickest change detection: accumulate the evidence of each fault hypothesis over time
and decide when it is strong enough (Page 1954; Lorden 1971; Basseville & Nikiforov,
*Detection of Abrupt Changes*, 1993, §2.2 and §7.2).

**Evidence.** A detector hands in, per sample t and sensor i, a standardized signed
statistic ``z_t,i``: N(0, 1) without a fault, and shifted by ``delta_i = g_i f`` by a
step ``f`` (SI) on sensor i (``g_i``, the sensor's *sensitivity*, in z units per SI unit).
For the parity tests ``z_i = r_i / sqrt(P_ii)`` (r the whitened parity residual,
``P = I - H_w H_w^+``): the log-likelihood ratio of "a step of whitened size a on sensor i"
against "no fault", given the whole parity vector, is ``a r_i - a^2 P_ii / 2``, i.e.
``mu z_i - mu^2 / 2`` with ``mu = a sqrt(P_ii)``. A CUSUM on column i is therefore the
optimal test of the hypothesis "sensor i has a step of that size", correlations between
the sensors' residuals included.

**The bank.** For every sensor i, sign s = +-1 and design shift ``mu_d`` (z units,
:attr:`CusumDesign.shifts`), Page's CUSUM of the log-likelihood ratio of the clipped
evidence::

    l_t = mu_d s clip(z'_t,i, -c, c) - mu_d^2 / 2                       (1)
    S_t = max(0, S_{t-1} + l_t)                                         (2)

The clip (in the spirit of Huber's robust tests, 1965) bounds what one outlier can add
(``mu_d c - mu_d^2 / 2``), so that a decision needs several samples of evidence and an
isolated spike raises no alarm; for Gaussian noise it costs almost nothing (``c = 3.5``
is 2.5 standard deviations above the largest design's ``mu / 2``). An alarm episode starts at the first sample where any
``S > h`` (2 n D hypotheses); its isolated sensor is the one whose unclipped evidence
summed since the estimated onset is largest in magnitude (the generalized likelihood
ratio of a step on it: the clip saturates a large fault's evidence on every sensor
correlated with it). While it lasts, a second CUSUM tests "the fault has ended" on that
sensor and sign, with the increments ``-l_t`` of a design shift equal to the fault's mean
evidence since the onset; when that reaches ``h`` the episode ends and every statistic
restarts from 0 (a renewal: each false episode costs one average run length).

**The threshold.** ``h`` is set so that the expected number of false alarm episodes per
sample is the budget's ``lambda = rate / f_s``: with the average run length ``ARL_d(h)``
of one CUSUM of design d without fault, computed by the Markov-chain method of Brook &
Evans (Biometrika 59, 1972) for the exact distribution of (1), the union bound
``sum_d 2 n / ARL_d(h) = lambda`` (:func:`budget_threshold`). The bound counts every
hypothesis as if alone, so the realised rate is at or below the budget.

**Slow reference.** Real MEMS biases wander (0.1–0.3 deg/s over minutes): a CUSUM with a
small design shift would accumulate the wander. Each column's offset is followed by an
exponential average of time constant ``tau`` of its innovations clipped at ``+-gate``,
frozen while an episode is open (so a fault is never absorbed once it is detected, and
before that only ``delay / tau`` of it), and subtracted causally: ``z'_t = z_t - b_{t-1}``.
A step of size delta is absorbed by ``delta (1 - exp(-t / tau))`` until detected, a
drift of rate k leaves a lag ``k tau``: a drift slower than the wander it must follow is
indistinguishable from it.

**Correlated noise.** A CUSUM sums its evidence, so what matters is the variance of sums
(the long-run variance), not of single samples: ``kappa`` = (variance of means of L
consecutive samples) x L / (variance of one), estimated on the calibration window and
pooled over the sensors (:func:`long_run_factor`), divides the evidence's variance
(``z / sqrt(kappa)``); white noise gives ``kappa ~ 1``.

**Reference delay.** Against a step whose evidence has non-centrality ``delta^2`` per
sample, no test with an average run length ``gamma`` between false alarms over K
hypotheses detects faster, asymptotically, than ``2 ln(gamma K) / delta^2`` samples
(Lorden 1971: Page's CUSUM attains it): :func:`lorden_delay_samples`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

NO_ISOLATION = -1
NOT_ISOLABLE = -2


@dataclass(frozen=True)
class CusumDesign:
    """The bank's fixed design.

    Attributes
    ----------
    shifts : tuple of float
        Design shifts ``mu_d`` in standard deviations of the evidence *at rest*: each is
        optimal for a step of that size. In motion, where the evidence's standard
        deviation grows by a factor ``s_t``, a design of the same physical size has the
        effective shift ``mu_d / s_t``, so the larger designs, inert at rest (a shift
        above ``2 c`` never has a positive increment), take over: a geometric grid of
        ratio 2 (at most 9 % efficiency lost between neighbours) from 2 to 32 covers rest
        and hand motion. A step below ``mu_min / 2`` (one standard deviation at rest) is
        never detected: the bias wander of real chips lives below it.
    clip : float
        Clip c of the standardized evidence in (1): one outlier adds at most
        ``mu c - mu^2 / 2``.
    tau_s : float
        Time constant of the slow bias reference, seconds (0: none).
    gate : float
        Clip of the reference's innovations, standard deviations of a sub-block's sum.
    block : int
        L of :func:`long_run_factor`.
    scale_tau_s : float
        Time constant of each column's tracked variance at rest, seconds (0: the
        calibrated sigma is kept): a running mean of the squared evidence (winsorized at 4
        standard deviations) from the calibration window on, then an exponential average;
        a sigma estimated from a short window is off by a few percent per sensor, and a
        sensor whose sigma was underestimated by 10 % raises about three times the false
        alarms of the others at h ~ 17.
    hold_s : float
        Longest time the references stay frozen in an episode, seconds: after it they
        resume (a fault that lasts is then absorbed over about ``tau`` ln(size)), so that
        a false alarm raised by bias wander does not latch.
    rest_factor : float
        Rows whose motion variance factor exceeds this are in motion: they teach the offset
        and variance references nothing (the noise model covers them).
    min_shift : float
        Effective shifts below this are not run (they would need more than ``2 h /
        min_shift^2`` samples).
    """

    shifts: tuple[float, ...] = (2.0, 4.0, 8.0, 16.0, 32.0)
    clip: float = 3.5
    tau_s: float = 30.0
    gate: float = 3.0
    block: int = 10
    scale_tau_s: float = 300.0
    hold_s: float = 10.0
    rest_factor: float = 2.0
    min_shift: float = 0.25


# --- threshold -------------------------------------------------------------------------


_ERFC = np.frompyfunc(math.erfc, 1, 1)


def _normal_cdf(x: np.ndarray) -> np.ndarray:
    """Standard normal CDF (the few hundred values a run length needs: math.erfc, which
    keeps scipy's import, longer than a whole short detect, off this path)."""
    return 0.5 * np.asarray(_ERFC(-np.asarray(x, float) / math.sqrt(2.0)), dtype=float)


def _increment_cdf(
    shift: float, clip: float, x: np.ndarray, scale: float = 1.0, contamination: float = 0.0
) -> np.ndarray:
    """CDF of ``l = mu clip(z, -c, c) - mu^2 / 2`` at ``x`` (any shape), for z ~ N(0,
    scale^2) with probability 1 - p and an outlier beyond the clip (either sign, equally
    likely) with probability p = ``contamination``."""
    level = (np.asarray(x, float) + 0.5 * shift * shift) / shift  # l <= x <=> clip(z) <= level
    inside = _normal_cdf(level / scale)
    gaussian = np.where(level < -clip, 0.0, np.where(level >= clip, 1.0, inside))
    if contamination <= 0:
        return gaussian
    outliers = 0.5 * (level >= -clip) + 0.5 * (level >= clip)
    return (1.0 - contamination) * gaussian + contamination * outliers


def increments(shift: float, clip: float, signed: np.ndarray) -> np.ndarray:
    """The log-likelihood ratio increments (1) of design ``shift`` for evidence ``signed``
    (the evidence times the hypothesis' sign)."""
    return shift * np.clip(signed, -clip, clip) - 0.5 * shift * shift


@lru_cache(maxsize=2048)
def average_run_length(
    shift: float,
    clip: float,
    threshold: float,
    states: int = 100,
    scale: float = 1.0,
    contamination: float = 0.0,
) -> float:
    """Average run length (samples) of one CUSUM (1)-(2) without fault, from S = 0, when
    the evidence has standard deviation ``scale`` (1: as calibrated) and a share
    ``contamination`` of outliers beyond the clip.

    Brook & Evans' Markov chain: S on ``[0, h)`` in ``states`` cells of width
    ``w = 2h / (2 states - 1)`` (cell 0 holds ``[0, w/2)``, the atom at 0 included; cell j
    is centred on ``j w``), absorbed at ``S >= h``; ``ARL = [(I - Q)^-1 1]_0``. With
    ``clip`` large and ``shift = 1`` this is the classic one-sided CUSUM of reference value
    0.5 (ARL 336 at h = 4 and 930 at h = 5: twice the two-sided 168 and 465 of the
    tables, e.g. Montgomery, *Statistical Quality Control*, Table 9.3).
    """
    if threshold <= 0:
        return 1.0
    if shift * clip - 0.5 * shift * shift <= 0.0:
        return math.inf  # no increment is positive: the statistic never leaves 0
    width = 2.0 * threshold / (2 * states - 1)
    # cell l's lower edge seen from cell j's centre is (l - j - 1/2) w: a Toeplitz CDF,
    # evaluated once per offset; l = 0 takes everything at or below 0 (the atom)
    offsets = np.arange(-states, states + 1)
    values = _increment_cdf(shift, clip, (offsets - 0.5) * width, scale, contamination)
    j = np.arange(states)[:, None]
    l_edges = np.arange(states + 1)[None, :]
    cdf = values[l_edges - j + states]
    cdf[:, 0] = 0.0
    transition = np.diff(cdf, axis=1)  # (states, states), rows sum to P(S' < h)
    system = np.eye(states) - transition
    try:
        lengths = np.linalg.solve(system, np.ones(states))
    except np.linalg.LinAlgError:  # absorption too unlikely to resolve: no false alarm
        return math.inf
    return float(lengths[0])


#: Gauss-Hermite nodes and weights (probabilists', 3 points: exact for polynomials of
#: degree 5) for the average over the sigma error.
_HERMITE_NODES = (-math.sqrt(3.0), 0.0, math.sqrt(3.0))
_HERMITE_WEIGHTS = (1.0 / 6.0, 2.0 / 3.0, 1.0 / 6.0)


#: Motion scales s over which the union bound is maximised (one octave of the design grid
#: is enough when the shifts are a geometric grid of ratio 2: the sum is periodic in log s).
_SCALES = (1.0, 2.0**0.5)


def effective_shifts(design: CusumDesign, scale: float) -> list[float]:
    """The design shifts run at motion scale ``scale`` (effective shift ``mu / scale`` at
    least ``min_shift`` and below ``2 clip``, where an increment can be positive)."""
    return [
        mu / scale for mu in design.shifts if design.min_shift <= mu / scale < 2.0 * design.clip
    ]


def false_alarm_rate(
    design: CusumDesign,
    sensors: int,
    threshold: float,
    scale_variance: float = 0.0,
    contamination: float = 0.0,
) -> float:
    """Union bound of the bank's false alarm episodes per sample at threshold ``h``, at
    the worst motion scale.

    At a motion scale s every design runs with the effective shift ``mu / s``
    (:func:`effective_shifts`): the rate is the largest, over s, of the sum over the
    shifts run there (the grid's octave beyond s = 1 is enough, except for the designs
    that run out at the top: s up to ``max shift / min_shift`` is checked at octave steps).

    ``scale_variance``: the variance of ``sigma_hat^2 / sigma^2`` of each sensor's
    calibrated sigma (e.g. 2 / N from N calibration samples). A sensor whose sigma was
    underestimated has evidence of standard deviation ``(sigma_hat^2 / sigma^2)^-1/2 > 1``
    and alarms more often, more than one overestimated by as much alarms less (the run
    length is exponential in h / scale^2): the rate is averaged over that error
    (Gauss-Hermite quadrature), as for CUSUM charts with estimated parameters (Jones,
    Champ & Rigdon, Technometrics 43, 2001). ``contamination``: the share of samples that
    are outliers (:func:`outlier_share`)."""
    if scale_variance <= 0:
        points: tuple[tuple[float, float], ...] = ((1.0, 1.0),)
    else:
        spread = math.sqrt(scale_variance)
        points = tuple(
            (round(1.0 / math.sqrt(max(0.2, 1.0 + spread * node)), 6), weight)
            for node, weight in zip(_HERMITE_NODES, _HERMITE_WEIGHTS)
        )
    octaves = max(0, math.ceil(math.log2(max(design.shifts) / design.min_shift)))
    worst = 0.0
    for octave in range(octaves + 1):
        for base in _SCALES:
            scale = base * 2.0**octave
            total = sum(
                weight
                / average_run_length(
                    round(mu, 9),
                    design.clip,
                    threshold,
                    scale=error,
                    contamination=round(contamination, 7),
                )
                for mu in effective_shifts(design, scale)
                for error, weight in points
            )
            worst = max(worst, total)
    return float(2.0 * sensors * worst)


def budget_threshold(
    design: CusumDesign,
    sensors: int,
    per_sample: float,
    scale_variance: float = 0.0,
    contamination: float = 0.0,
) -> float:
    """The threshold h whose union-bound false alarm rate is ``per_sample`` (episodes per
    sample; e.g. ``budget_per_s / rate_hz``), sigma errors of ``scale_variance`` and
    outliers included (:func:`false_alarm_rate`).

    ``log rate(h)`` is close to linear in h (the run length grows like ``exp(theta h)``),
    so a secant iteration on it converges in a few Markov-chain solves; h is rounded up
    to 1e-3 (a slightly lower rate than asked).
    """
    if not 0.0 < per_sample < 1.0:
        raise ValueError(f"per-sample rate must be in (0, 1), got {per_sample!r}")
    target = math.log(per_sample)

    def gap(h: float) -> float:
        rate = false_alarm_rate(design, sensors, h, scale_variance, contamination)
        return math.log(rate) - target

    # log rate(h) is close to linear in h: secant steps from a first guess, each new
    # point kept as a bracket end, then regula falsi (Illinois) inside the bracket
    low, g_low = 0.5, gap(0.5)
    if g_low <= 0:  # even a tiny threshold meets the budget
        return low
    h_a = max(1.0, 0.9 * math.log(4.0 * sensors / per_sample))
    h_b = h_a + 1.0
    g_a, g_b = gap(h_a), gap(h_b)
    high, g_high = math.inf, -math.inf
    for h, g in ((h_a, g_a), (h_b, g_b)):
        if g > 0:
            low, g_low = max((low, g_low), (h, g))
        elif h < high:
            high, g_high = h, g
    for _ in range(8):  # secant from the last two points, until bracketed
        if math.isfinite(high):
            break
        step = (h_b - h_a) / (g_a - g_b) * g_b if g_a != g_b else 2.0
        h_a, g_a = h_b, g_b
        h_b = h_b + min(max(step, 0.5), 20.0)
        g_b = gap(h_b)
        if g_b > 0:
            low, g_low = h_b, g_b
        else:
            high, g_high = h_b, g_b
    side = 0
    for _ in range(100):
        if high - low < 1e-4:
            break
        h = high - g_high * (high - low) / (g_high - g_low)
        g = gap(h)
        if g > 0:
            low, g_low = h, g
            if side == 1:
                g_high /= 2.0
            side = 1
        else:
            high, g_high = h, g
            if side == -1:
                g_low /= 2.0
            side = -1
        if abs(g) < 1e-7:
            break
    return math.ceil(high * 1000.0) / 1000.0


def lorden_delay_samples(noncentrality: float, run_length: float, hypotheses: int) -> float:
    """``2 ln(gamma K) / delta^2``: samples an optimal test needs, asymptotically, to detect
    a step of per-sample non-centrality ``delta^2`` at an average run length ``gamma``
    between false alarms among K hypotheses (Lorden 1971)."""
    if noncentrality <= 0:
        return math.inf
    return 2.0 * math.log(max(run_length * hypotheses, 1.0)) / noncentrality


def lorden_drift_samples(slope: float, run_length: float, hypotheses: int) -> float:
    """The same for a drift whose evidence grows by ``slope`` z units per sample: the
    number m of samples whose accumulated non-centrality ``slope^2 m^3 / 3`` reaches
    ``2 ln(gamma K)`` (the matched test of a ramp from a known onset)."""
    if slope <= 0:
        return math.inf
    return (3.0 * 2.0 * math.log(max(run_length * hypotheses, 1.0)) / slope**2) ** (1.0 / 3.0)


#: |z| beyond which a calibration sample counts as an outlier (Gaussian share 6.8e-6).
OUTLIER_LEVEL = 4.5


def outlier_share(z: np.ndarray, level: float = OUTLIER_LEVEL) -> float:
    """Share of the samples of standardized evidence ``z`` (any shape) that are outliers:
    beyond ``level`` in magnitude, less what a Gaussian puts there (at least 0)."""
    z = np.asarray(z, float)
    finite = np.isfinite(z)
    total = int(np.count_nonzero(finite))
    if total == 0:
        return 0.0
    beyond = int(np.count_nonzero(np.abs(z[finite]) > level))
    return max(0.0, beyond / total - math.erfc(level / math.sqrt(2.0)))


def long_run_factor(z: np.ndarray, block: int) -> float:
    """Pooled long-run variance factor of standardized evidence ``z`` (N, n), >= 1.

    ``kappa = L mean(m_b^2) / mean(z^2)`` over the non-overlapping L-sample block means
    ``m_b`` of every column (each column centred on its mean), clipped below at 1: a
    white sequence gives about 1, positively correlated noise more.
    """
    z = np.asarray(z, float)
    n_blocks = z.shape[0] // block
    if block <= 1 or n_blocks < 2 or z.shape[1] == 0:
        return 1.0
    centred = z - np.nanmean(z, axis=0)
    per_sample = float(np.nanmean(centred**2))
    if not per_sample > 0:
        return 1.0
    means = centred[: n_blocks * block].reshape(n_blocks, block, -1).mean(axis=1)
    # the block means' variance around the common mean: ddof 1 per column
    factor = block * float(np.nanmean(means**2)) * n_blocks / (n_blocks - 1) / per_sample
    return max(1.0, factor)
