"""Run lengths, thresholds and reference delays of the CUSUM bank
(:mod:`imufdi_cli.maths.sequential`)."""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Callable
from functools import lru_cache

import numpy as np

from imufdi_cli.maths.sequential.design import CusumDesign

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


_Key = tuple[float, float, float, int, float, float]
#: Run lengths computed so far, least recently used first (at most _CACHED of them).
_RUN_LENGTHS: OrderedDict[_Key, float] = OrderedDict()
_CACHED = 2048
_LOCK = threading.Lock()


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
    return run_lengths([(shift, clip, threshold, states, scale, contamination)])[0]


def run_lengths(keys: list[_Key]) -> list[float]:
    """:func:`average_run_length` of each ``(shift, clip, threshold, states, scale,
    contamination)``: those not computed before in one stacked solve of their chains (per
    number of states), the same floats as one at a time. Thread-safe (one lock around the
    cache)."""
    with _LOCK:
        return _run_lengths(keys)


def _run_lengths(keys: list[_Key]) -> list[float]:
    found: dict[_Key, float] = {}
    chains: dict[int, list[tuple[_Key, np.ndarray]]] = {}
    for key in dict.fromkeys(keys):
        cached = _RUN_LENGTHS.get(key)
        if cached is not None:
            _RUN_LENGTHS.move_to_end(key)  # recently used
            found[key] = cached
            continue
        shift, clip, threshold, states, scale, contamination = key
        if threshold <= 0:
            found[key] = 1.0
        elif shift * clip - 0.5 * shift * shift <= 0.0:
            found[key] = math.inf  # no increment is positive: the statistic never leaves 0
        else:
            width = 2.0 * threshold / (2 * states - 1)
            # cell l's lower edge seen from cell j's centre is (l - j - 1/2) w: a Toeplitz
            # CDF, evaluated once per offset; l = 0 takes everything at or below 0 (the atom)
            offsets = np.arange(-states, states + 1)
            values = _increment_cdf(shift, clip, (offsets - 0.5) * width, scale, contamination)
            chains.setdefault(states, []).append((key, values))
    for states, pending in chains.items():
        try:
            lengths = chain_run_lengths(np.stack([values for _, values in pending]), states)
        except np.linalg.LinAlgError:  # one at a time: the singular ones have no false alarm
            lengths = np.array([_one_chain(values, states) for _, values in pending])
        for (key, _), length in zip(pending, lengths, strict=True):
            found[key] = float(length)
    for key, length in found.items():
        _RUN_LENGTHS[key] = length
        _RUN_LENGTHS.move_to_end(key)
    while len(_RUN_LENGTHS) > _CACHED:
        _RUN_LENGTHS.popitem(last=False)
    return [found[key] for key in keys]


def _one_chain(values: np.ndarray, states: int) -> float:
    try:
        return float(chain_run_lengths(values, states)[0])
    except np.linalg.LinAlgError:  # absorption too unlikely to resolve: no false alarm
        return math.inf


def chain_run_lengths(cdf_at_edges: np.ndarray, states: int) -> np.ndarray:
    """Average run lengths from 0 of CUSUMs on ``[0, h)`` in ``states`` cells (Brook &
    Evans), one per row of ``cdf_at_edges`` (k, 2 states + 1): the increment's CDF at
    ``(e - states - 1/2) w`` for ``e = 0 .. 2 states``, ``w = 2h / (2 states - 1)`` (cell 0
    holds ``[0, w/2)`` and the atom at 0, cell j is centred on ``j w``; the chain is
    absorbed at ``S >= h``).

    The transition from cell j to cell l >= 1 is the CDF's step between l's edges seen
    from j, ``F(l - j + 1/2) - F(l - j - 1/2)`` (in cells): one difference per offset,
    laid out as a Toeplitz matrix; to cell 0 it is everything up to its upper edge."""
    cdf_at_edges = np.atleast_2d(np.asarray(cdf_at_edges, float))
    offset, first, identity = _chain_layout(states)
    steps = np.diff(cdf_at_edges, axis=1)  # (k, 2 states): F(e + 1) - F(e)
    transition = steps[:, offset]  # (k, states, states)
    transition[:, :, 0] = cdf_at_edges[:, first]
    system = np.subtract(identity, transition, out=transition)
    lengths = np.linalg.solve(system, np.ones((cdf_at_edges.shape[0], states, 1)))
    return lengths[:, 0, 0]


@lru_cache(maxsize=8)
def _chain_layout(states: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The chain's index arrays: the CDF step of each (cell, cell) pair (states, states),
    the upper edge of cell 0 seen from each cell (states,), and the identity."""
    cells = np.arange(states)
    offset = cells[None, :] - cells[:, None] + states
    return offset, states + 1 - cells, np.eye(states)[None, :, :]


#: Gauss-Hermite nodes and weights (probabilists', 3 points: exact for polynomials of
#: degree 5) for the average over the sigma error.
_HERMITE_NODES = (-math.sqrt(3.0), 0.0, math.sqrt(3.0))
_HERMITE_WEIGHTS = (1.0 / 6.0, 2.0 / 3.0, 1.0 / 6.0)


def scale_points(scale_variance: float, digits: int) -> tuple[tuple[float, float], ...]:
    """(evidence standard deviation, weight) of the Gauss-Hermite average over a variance
    estimate whose relative error ``sigma_hat^2 / sigma^2 - 1`` has variance
    ``scale_variance``: the evidence's standard deviation is ``(sigma_hat^2 /
    sigma^2)^-1/2`` (at least 0.2 under the root), rounded to ``digits`` (the run lengths'
    cache keys)."""
    if scale_variance <= 0:
        return ((1.0, 1.0),)
    spread = math.sqrt(scale_variance)
    return tuple(
        (round(1.0 / math.sqrt(max(0.2, 1.0 + spread * node)), digits), weight)
        for node, weight in zip(_HERMITE_NODES, _HERMITE_WEIGHTS)
    )


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
    points = scale_points(scale_variance, 6)
    octaves = max(0, math.ceil(math.log2(max(design.shifts) / design.min_shift)))
    scales = [base * 2.0**octave for octave in range(octaves + 1) for base in _SCALES]
    # every chain this rate needs, solved together (the sums below find them computed)
    run_lengths(
        [
            (round(mu, 9), design.clip, threshold, 100, error, round(contamination, 7))
            for scale in scales
            for mu in effective_shifts(design, scale)
            for error, _ in points
        ]
    )
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

    return threshold_root(gap, 0.5, max(1.0, 0.9 * math.log(4.0 * sensors / per_sample)), 8)


def bisect_boundary(
    fails: Callable[[float], bool], low: float, high: float, tolerance: float
) -> float:
    """The boundary of a predicate by bisection: ``fails(low)`` true, ``fails(high)``
    false, halved until ``high - low < tolerance`` (at most 60 times); returns the upper
    end, so the value returned is never one the predicate refuses. Callers bisect on a log
    scale for a relative tolerance."""
    for _ in range(60):
        middle = 0.5 * (low + high)
        if fails(middle):
            low = middle
        else:
            high = middle
        if high - low < tolerance:
            break
    return high


def threshold_root(gap: Callable[[float], float], floor: float, guess: float, tries: int) -> float:
    """The h where a decreasing ``gap(h)`` (log false-alarm rate less its target's log)
    crosses 0, rounded up to 1e-3 (a slightly lower rate than asked); ``floor`` when the
    rate there already meets the target.

    ``log rate(h)`` is close to linear in h (the run length grows like ``exp(theta h)``):
    secant steps from ``guess`` (at most ``tries``), each new point kept as a bracket end,
    then regula falsi (Illinois) inside the bracket. Raises ValueError when no bracket is
    found.
    """
    low, g_low = floor, gap(floor)
    if g_low <= 0:  # even a tiny threshold meets the budget
        return low
    h_a = guess
    h_b = h_a + 1.0
    g_a, g_b = gap(h_a), gap(h_b)
    high, g_high = math.inf, -math.inf
    for h, g in ((h_a, g_a), (h_b, g_b)):
        if g > 0:
            low, g_low = max((low, g_low), (h, g))
        elif h < high:
            high, g_high = h, g
    for _ in range(tries):  # secant from the last two points, until bracketed
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
    if not math.isfinite(high):
        raise ValueError(f"no threshold below {h_b:.0f} meets the target rate")
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


def step_information(
    noncentrality: np.ndarray | float, contamination: float = 0.0, outlier: float = 0.0
) -> np.ndarray:
    """Kullback-Leibler information per sample (nats) of a step in standardized evidence.

    Parameters
    ----------
    noncentrality : float or ndarray, any shape
        ``delta^2``, the step's squared size in standard deviations of the evidence.
    contamination : float
        Share p of outliers in the fault-free evidence (:func:`outlier_share`).
    outlier : float
        Their size o, standard deviations (:func:`outlier_size`).

    Returns
    -------
    ndarray, the shape of ``noncentrality``
        ``I(delta) = E[ln f1(y) / f0(y)]`` for ``y ~ f1``, the information Lorden's bound
        divides by. Fault-free evidence has the density ``f0 = (1 - p) N(0, 1) + p/2
        (N(o, 1) + N(-o, 1))``, a faulty sample is the same noise plus delta, ``f1(y) =
        f0(y - delta)``. Without outliers ``I = delta^2 / 2``. With them I is smaller
        (the step is added to noise that is no longer Gaussian: by the data-processing
        inequality it never exceeds ``delta^2 / 2``): a step about the outliers' size
        looks like a run of outliers, and each sample of it carries about
        ``ln(phi(0) / (p/2 phi(delta - o)))`` nats instead of ``delta^2 / 2``. The
        expectation is a 96-node Gauss-Hermite quadrature over each of the three
        components (a smooth integrand: the log of a sum of Gaussians).
    """
    shift = np.sqrt(np.maximum(np.asarray(noncentrality, float), 0.0))
    if not contamination > 0 or not outlier > 0:
        return 0.5 * shift * shift
    p = min(float(contamination), 0.5)
    nodes, weights = _hermite_nodes()
    logs = (math.log1p(-p), math.log(0.5 * p), math.log(0.5 * p))
    centres = (0.0, float(outlier), -float(outlier))

    def log_f0(x: np.ndarray) -> np.ndarray:
        parts = [w - 0.5 * (x - c) ** 2 for w, c in zip(logs, centres)]
        return np.logaddexp(np.logaddexp(parts[0], parts[1]), parts[2])

    total = np.zeros(shift.shape)
    for w, c in zip(logs, centres):
        x = c + nodes  # the noise X, of component c; the sample is X + delta
        gap = log_f0(x) - log_f0(x + shift[..., None])
        total += math.exp(w) * (gap @ weights)
    return np.maximum(total, 0.0)


@lru_cache(maxsize=1)
def _hermite_nodes() -> tuple[np.ndarray, np.ndarray]:
    """Probabilists' Gauss-Hermite nodes and weights normalised to the N(0, 1) mean."""
    nodes, weights = np.polynomial.hermite_e.hermegauss(96)
    return nodes, weights / math.sqrt(2.0 * math.pi)


def lorden_delay_samples(
    noncentrality: float,
    run_length: float,
    hypotheses: int,
    contamination: float = 0.0,
    outlier: float = 0.0,
) -> float:
    """``ln(gamma K) / I``: samples an optimal test needs, asymptotically, to detect a step
    of per-sample non-centrality ``delta^2`` at an average run length ``gamma`` between
    false alarms among K hypotheses (Lorden 1971), with I the step's information per
    sample (:func:`step_information`): ``delta^2 / 2`` for Gaussian evidence, so
    ``2 ln(gamma K) / delta^2``; less with the evidence's outliers."""
    if noncentrality <= 0:
        return math.inf
    information = float(step_information(noncentrality, contamination, outlier))
    if not information > 0:
        return math.inf
    return math.log(max(run_length * hypotheses, 1.0)) / information


def lorden_drift_samples(
    slope: float,
    run_length: float,
    hypotheses: int,
    contamination: float = 0.0,
    outlier: float = 0.0,
) -> float:
    """The same for a drift whose evidence grows by ``slope`` z units per sample: the
    number m of samples whose accumulated information ``int_0^m I(slope t) dt`` reaches
    ``ln(gamma K)`` (the matched test of a ramp from a known onset): for Gaussian evidence
    ``slope^2 m^3 / 6``, so ``m = (6 ln(gamma K) / slope^2)^(1/3)``."""
    if slope <= 0:
        return math.inf
    target = math.log(max(run_length * hypotheses, 1.0))
    gaussian = (6.0 * target / slope**2) ** (1.0 / 3.0)
    if not contamination > 0 or not outlier > 0:
        return gaussian
    nodes, weights = np.polynomial.legendre.leggauss(48)

    def accumulated(m: float) -> float:
        t = 0.5 * m * (nodes + 1.0)
        return 0.5 * m * float(step_information((slope * t) ** 2, contamination, outlier) @ weights)

    # the information never exceeds the Gaussian one, so m is at least the Gaussian m;
    # widen until the accumulated information passes the target, then bisect (on log m)
    low, high = gaussian, 2.0 * gaussian
    while accumulated(high) < target:
        low, high = high, 2.0 * high
        if high > 1e12:
            return math.inf
    return math.exp(
        bisect_boundary(
            lambda log_m: accumulated(math.exp(log_m)) < target,
            math.log(low),
            math.log(high),
            1e-9,
        )
    )


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


def outlier_size(z: np.ndarray, level: float = OUTLIER_LEVEL) -> float:
    """Median magnitude of the outliers of standardized evidence ``z`` (any shape): the
    samples beyond ``level``; 0 when there are none."""
    z = np.abs(np.asarray(z, float))
    beyond = z[np.isfinite(z) & (z > level)]
    return float(np.median(beyond)) if beyond.size else 0.0


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
