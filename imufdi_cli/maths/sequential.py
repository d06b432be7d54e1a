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
``S > h`` (2 n D hypotheses); its isolated sensor is the sensor of the largest ``S``.
While it lasts, a second CUSUM tests "the fault has ended" on the sensor and sign that
raised it, with the increments ``-l_t`` of a design shift equal to the fault's mean
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
from dataclasses import dataclass, field
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
        Design shifts ``mu_d`` (z units, i.e. per-sample standard deviations of the
        evidence): each is optimal for a step of that size; between two of them the
        efficiency loss is at most 1 - (2 sqrt(r) - 1) / r for a ratio r of neighbours
        (25 % for r = 3), and a shift below ``mu_min / 2`` is never detected.
    clip : float
        Clip c of the evidence in (1): one outlier adds at most ``mu_d c - mu_d^2 / 2``.
    tau_s : float
        Time constant of the slow reference, seconds (0: no reference).
    gate : float
        Clip of the reference's innovations, z units.
    block : int
        L of :func:`long_run_factor`.
    scale_tau_s : float
        Time constant of each column's tracked variance, seconds (0: the calibrated
        sigma is kept): a running mean of the squared evidence (winsorized at 4 standard
        deviations) from the calibration window on, then an exponential average; the
        sigma estimated from a short window is off by a few percent per sensor, and a
        sensor whose sigma was underestimated by 10 % raises about three times the false
        alarms of the others at h ~ 17.
    """

    shifts: tuple[float, ...] = (1.0, 3.0)
    clip: float = 3.5
    tau_s: float = 60.0
    gate: float = 3.0
    block: int = 10
    scale_tau_s: float = 300.0


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
    lengths = np.linalg.solve(system, np.ones(states))
    return float(lengths[0])


#: Gauss-Hermite nodes and weights (probabilists', 3 points: exact for polynomials of
#: degree 5) for the average over the sigma error.
_HERMITE_NODES = (-math.sqrt(3.0), 0.0, math.sqrt(3.0))
_HERMITE_WEIGHTS = (1.0 / 6.0, 2.0 / 3.0, 1.0 / 6.0)


def false_alarm_rate(
    design: CusumDesign,
    sensors: int,
    threshold: float,
    scale_variance: float = 0.0,
    contamination: float = 0.0,
) -> float:
    """Union bound of the bank's false alarm episodes per sample at threshold ``h``.

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
    return float(
        sum(
            weight
            * 2.0
            * sensors
            / average_run_length(
                mu, design.clip, threshold, scale=scale, contamination=round(contamination, 7)
            )
            for mu in design.shifts
            for scale, weight in points
        )
    )


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
    h_a = max(1.0, 0.9 * math.log(2.0 * sensors * len(design.shifts) / per_sample))
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


# --- the streaming bank ------------------------------------------------------------------


@dataclass
class Decisions:
    """Rows of one sensor type's sequential test (N samples, n sensors).

    Attributes
    ----------
    statistic : ndarray (N,)
        Largest CUSUM statistic of the bank (log-likelihood ratio units).
    threshold : ndarray (N,)
        h.
    alarm : ndarray (N,) bool
    isolated : ndarray (N,) int32
        Sensor of the largest statistic on alarm rows; NOT_ISOLABLE where that sensor
        cannot be told from another; NO_ISOLATION elsewhere.
    amplitude : ndarray (N,)
        On alarm rows, the isolated sensor's mean evidence since the episode's estimated
        onset, in SI units (``/ g_i``); NaN elsewhere.
    scores : ndarray (N, n)
        Per sensor, its largest statistic over signs and design shifts.
    """

    statistic: np.ndarray
    threshold: np.ndarray
    alarm: np.ndarray
    isolated: np.ndarray
    amplitude: np.ndarray
    scores: np.ndarray


@dataclass
class _Episode:
    shift: int  # design index of the hypothesis that raised it
    sign: float
    sensor: int
    recovery: float = 0.0  # the "fault has ended" CUSUM
    onset: int = 0  # estimated onset, absolute sample index
    sums: np.ndarray = field(default_factory=lambda: np.zeros(0))  # z' summed from onset
    count: int = 0


class _Reference:
    """The slow reference of every column of evidence: an offset ``b`` and, with
    regressors x (the tested state: rate, specific force), a linear model ``D`` of the
    evidence on the state's deviation from its running mean ``x_bar`` (which moves with
    the offset's gains, from the calibration window's mean)::

        z'_t = (z_t - b - D^T (x_t - x_bar)) / sqrt(1 + k (x_t - x_bar)^T Sigma (x_t - x_bar))

    ``D`` is the ridge (Gaussian prior ``N(0, prior_sd^2 I)``) regression of ``z - b`` on
    ``x - x_bar`` over the calibration window and the samples since, forgotten with time
    constant ``slope_tau``; ``Sigma`` its posterior covariance per unit noise variance,
    and k (``inflation``) widens the test by ``sqrt(k)`` standard deviations of what the
    model does not know yet. Both move once per sub-block of ``stride`` samples (aligned
    on the sample count), from that sub-block's sums, and stay frozen while an episode is
    open."""

    def __init__(
        self,
        n: int,
        step: float,
        stride: int,
        gate: float,
        calibration_samples: float,
        motion: MotionModel | None = None,
        scale_step: float = 0.0,
    ) -> None:
        self.n, self.step, self.stride, self.gate = n, step, stride, gate
        self.calibration_samples = calibration_samples
        self.scale_step = scale_step
        self.offset = np.zeros(n)
        self.variance = np.ones(n)
        self.pending = np.zeros(n)
        self.pending_squares = np.zeros(n)
        self.count = 0
        self.motion = motion
        p = 0 if motion is None else motion.centre.size
        # the state's own running mean (the same gains as the offset): the slopes are
        # regressed on the state's deviation from it, so that a mean of the state the
        # offset has absorbed is not taken for a slope
        self.state_mean = np.zeros(p) if motion is None else motion.centre.copy()
        self.pending_x = np.zeros(p)
        self.pending_xx = np.zeros((p, p))
        self.pending_xz = np.zeros((p, n))

    @property
    def active(self) -> bool:
        return self.step > 0.0 or self.scale_step > 0.0 or self.motion is not None

    def snapshot(self) -> tuple[np.ndarray, ...]:
        """The state, by reference: every array of it is replaced when the state moves,
        never changed in place (:meth:`restore` copies)."""
        motion = self.motion
        if motion is None:
            return (self.offset, self.variance)
        return (self.offset, self.variance, self.state_mean, motion.sxx, motion.sxz)

    def restore(self, snap: tuple[np.ndarray, ...]) -> None:
        """Back to a snapshot; the open sub-block's sums are dropped."""
        self.offset, self.variance = snap[0].copy(), snap[1].copy()
        if self.motion is not None:
            self.state_mean = snap[2].copy()
            self.motion.sxx, self.motion.sxz = snap[3].copy(), snap[4].copy()
            self.motion.solve()
        self._drop()

    def _drop(self) -> None:
        self.pending = np.zeros(self.n)
        self.pending_squares = np.zeros(self.n)
        self.count = 0
        self.pending_x = np.zeros_like(self.pending_x)
        self.pending_xx = np.zeros_like(self.pending_xx)
        self.pending_xz = np.zeros_like(self.pending_xz)

    def apply(
        self, z: np.ndarray, x: np.ndarray | None, frozen: bool, samples: int
    ) -> tuple[np.ndarray, list[tuple[int, tuple[np.ndarray, ...]]]]:
        """``z'`` for the rows of ``z`` (the rows after ``samples`` of the stream), moving
        the reference at every completed sub-block unless ``frozen``; also, for a rewind,
        the local rows from which each state held, with a snapshot of it."""
        motion = self.motion if x is not None else None
        n_rows = z.shape[0]
        out = np.empty_like(z)
        marks = [(0, self.snapshot())]
        stride, scaled = self.stride, self.scale_step > 0.0
        row = 0
        while row < n_rows:
            stop = min(n_rows, row + stride - (samples + row) % stride)
            rows = out[row:stop]
            np.subtract(z[row:stop], self.offset, out=rows)
            if motion is not None:
                assert x is not None
                states = x[row:stop]
                centred = states - self.state_mean
                if not frozen:  # the regression sees the offset-free evidence
                    self.pending_x += states.sum(axis=0)
                    transposed = centred.T
                    self.pending_xx += transposed @ centred
                    self.pending_xz += transposed @ rows
                rows -= centred @ motion.slopes
            if not frozen:
                self.pending += rows.sum(axis=0)
                self.count += stop - row
            if motion is not None:
                spread = np.einsum("ij,jk,ik->i", centred, motion.covariance, centred)
                rows /= np.sqrt(1.0 + motion.inflation * spread)[:, None]
            if scaled:
                if not frozen:
                    squares = np.square(rows)
                    np.minimum(squares, 16.0 * self.variance, out=squares)
                    self.pending_squares += squares.sum(axis=0)
                rows /= np.sqrt(self.variance)
            if not frozen and (samples + stop) % stride == 0:  # sub-block complete
                self._complete(samples + stop)
                marks.append((stop, self.snapshot()))
            row = stop
        return out, marks

    def _complete(self, position: int) -> None:
        start = 1.0 / (self.calibration_samples + position)  # a running mean at first
        if self.step > 0.0 and self.count:
            gain = max(self.step, start)
            limit = self.gate * np.sqrt(self.count * self.variance)
            self.offset = self.offset + gain * np.clip(self.pending, -limit, limit)
        if self.scale_step > 0.0 and self.count:
            gain = max(self.scale_step, start)
            self.variance = self.variance + gain * (
                self.pending_squares - self.count * self.variance
            )
            np.maximum(self.variance, 0.25, out=self.variance)
        if self.motion is not None and self.count:
            gain = max(self.step, start) if self.step > 0.0 else start
            self.state_mean = self.state_mean + gain * (
                self.pending_x - self.count * self.state_mean
            )
            self.motion.update(self.pending_xx, self.pending_xz, self.count)
        self._drop()


@dataclass
class MotionModel:
    """The linear model of the evidence on the tested state (see :class:`_Reference`).

    Attributes
    ----------
    centre : ndarray (p,)
        The state's calibration mean.
    prior_sd : float
        Prior standard deviation of every slope (z units per unit of the state).
    forget : float
        Per-sample forgetting rate of the sufficient statistics (1 / (slope_tau f_s)).
    inflation : float
        k: squared standard deviations of the model's uncertainty added to the variance.
    sxx, sxz : ndarray (p, p), (p, n)
        Sufficient statistics (calibration window first).
    """

    centre: np.ndarray
    prior_sd: float
    forget: float
    inflation: float
    sxx: np.ndarray
    sxz: np.ndarray
    slopes: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    #: ``I / prior_sd^2`` (set by :meth:`solve`)
    prior_precision: np.ndarray | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.solve()

    @classmethod
    def from_calibration(
        cls,
        x: np.ndarray,
        z: np.ndarray,
        prior_sd: float,
        slope_tau_samples: float,
        inflation: float = 16.0,
    ) -> MotionModel:
        """The model fitted on calibration states ``x`` (N, p) and evidence ``z`` (N, n)."""
        centre = x.mean(axis=0)
        centred = x - centre
        return cls(
            centre=centre,
            prior_sd=float(prior_sd),
            forget=0.0 if slope_tau_samples <= 0 else 1.0 / slope_tau_samples,
            inflation=float(inflation),
            sxx=centred.T @ centred,
            sxz=centred.T @ (z - z.mean(axis=0)),
        )

    def solve(self) -> None:
        if self.prior_precision is None:  # (the same floats every time: computed once)
            self.prior_precision = np.eye(self.centre.size) / self.prior_sd**2
        precision = self.sxx + self.prior_precision
        self.covariance = np.linalg.inv(precision)
        self.slopes = self.covariance @ self.sxz

    def update(self, xx: np.ndarray, xz: np.ndarray, samples: int) -> None:
        keep = math.exp(-self.forget * samples)
        self.sxx = keep * self.sxx + xx
        self.sxz = keep * self.sxz + xz
        self.solve()


class CusumBank:
    """Streaming bank of robust CUSUM tests over one sensor type (module docstring).

    The outputs do not depend on how the rows are split into calls (the reference moves on
    sub-blocks aligned on the sample count), up to the rounding of the cumulative sums.

    Parameters
    ----------
    design : CusumDesign
    threshold : float
        h (:func:`budget_threshold`).
    sensitivity : ndarray, shape (n,)
        ``g_i``: z units per SI unit of a step on sensor i (before the long-run factor).
    isolable : ndarray, shape (n,), bool
        Whether sensor i's fault can be told from every other sensor's.
    rate_hz : float
        Nominal sample rate (for the reference's time constant).
    kappa : float
        Long-run variance factor (:func:`long_run_factor`).
    history : int
        Samples of evidence kept to estimate an episode's onset.
    calibration_samples : float
        Samples the biases were estimated from: the reference starts as the running mean
        of the evidence from there (gain ``1 / (N + k)`` after k samples) until that gain
        falls to ``1 / (tau f_s)``, so that the bias estimate's own error (``1 / sqrt(N)``
        of a standard deviation, which a CUSUM of small design shift would accumulate) is
        learnt away in the first seconds.
    motion : MotionModel, optional
        The linear model of the evidence on the tested state (residual scale and
        misalignment errors): ``process`` then takes the state's rows too.
    """

    #: Rows run through the bank at once (an alarm wastes at most this much work).
    SPAN = 2048

    def __init__(
        self,
        design: CusumDesign,
        threshold: float,
        sensitivity: np.ndarray,
        isolable: np.ndarray,
        rate_hz: float,
        kappa: float = 1.0,
        history: int = 512,
        calibration_samples: float = math.inf,
        motion: MotionModel | None = None,
    ) -> None:
        self.design = design
        self.calibration_samples = float(calibration_samples)
        self.threshold = float(threshold)
        self.kappa = float(kappa)
        self.inverse_scale = 1.0 / math.sqrt(self.kappa)
        self.sensitivity = np.asarray(sensitivity, float) * self.inverse_scale
        self.isolable = np.asarray(isolable, bool)
        n = self.sensitivity.size
        self.n = n
        self.shifts = np.asarray(design.shifts, float)
        self.state = np.zeros((self.shifts.size, 2, n))  # S per shift, sign, sensor
        self.step = 0.0 if design.tau_s <= 0 else 1.0 / (design.tau_s * rate_hz)
        #: rows over which the reference stays constant (1 s, at most tau / 10)
        self.stride = max(1, round(rate_hz))
        if design.tau_s > 0:
            self.stride = max(1, min(self.stride, round(design.tau_s * rate_hz / 10)))
        self.ref = _Reference(
            n,
            self.step,
            self.stride,
            design.gate,
            self.calibration_samples,
            motion,
            0.0 if design.scale_tau_s <= 0 else 1.0 / (design.scale_tau_s * rate_hz),
        )
        self.history = np.zeros((0, n))
        self.history_length = int(history)
        self.samples = 0  # rows handled so far
        self.episode: _Episode | None = None
        self.episodes = 0

    @property
    def reference(self) -> np.ndarray:
        """Each column's tracked offset (z units after the long-run factor)."""
        return self.ref.offset

    def _referenced(
        self, z: np.ndarray, x: np.ndarray | None, frozen: bool
    ) -> tuple[np.ndarray, list[tuple[int, tuple[np.ndarray, ...]]]]:
        """``z'`` for the next rows of the stream (:class:`_Reference`)."""
        if not self.ref.active:
            return z, [(0, self.ref.snapshot())]
        return self.ref.apply(z, x, frozen, self.samples)

    def _rewind(self, marks: list[tuple[int, tuple[np.ndarray, ...]]], row: int) -> None:
        """The reference as it was on local row ``row`` (an episode opens there: from then
        on it is frozen, and the sums of the open sub-block are dropped)."""
        value = marks[0][1]
        for start, snap in marks:
            if start <= row:
                value = snap
        self.ref.restore(value)

    # --- processing --------------------------------------------------------------------

    def process(self, z: np.ndarray, x: np.ndarray | None = None) -> Decisions:
        """Decide on the rows of ``z`` (N, n): standardized signed evidence per sensor;
        ``x`` (N, p): the tested state of each row, for the motion model (if any).

        NaN evidence (a sample without a test) counts as 0."""
        z = np.asarray(z, float)
        if z.ndim != 2 or z.shape[1] != self.n:
            raise ValueError(f"evidence must be (N, {self.n}), got {z.shape}")
        if self.inverse_scale != 1.0:
            z = z * self.inverse_scale
        if not np.isfinite(z).all():
            z = np.nan_to_num(z, nan=0.0, posinf=0.0, neginf=0.0)
        n_rows = z.shape[0]
        out = Decisions(
            statistic=np.zeros(n_rows),
            threshold=np.full(n_rows, self.threshold),
            alarm=np.zeros(n_rows, bool),
            isolated=np.full(n_rows, NO_ISOLATION, np.int32),
            amplitude=np.full(n_rows, np.nan),
            scores=np.empty((n_rows, self.n)),  # every row is written
        )
        position = 0
        while position < n_rows:
            rows = z[position : position + self.SPAN]
            states = None if x is None else x[position : position + self.SPAN]
            if self.episode is None:
                position += self._watch(rows, states, position, out)
            else:
                position += self._follow(rows, states, position, out)
        return out

    #: Rows of a sub-chunk in :meth:`_cusums`: its working arrays, a few of (rows, n),
    #: stay in the CPU's cache, which a whole span's do not (about 1.7x faster at 48
    #: sensors).
    SUB_ROWS = 512

    def _cusums(
        self, zr: np.ndarray, best: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Every CUSUM (1)-(2) of the bank over the rows ``zr`` (M, n), from the current
        state: per sensor the largest statistic over the hypotheses (M, n; written into
        ``best`` when given), and every hypothesis' statistic on the last row (2 D, n),
        shift-major then sign (the next state).

        With the one clip of (1), every hypothesis' cumulative log-likelihood ratio is a
        combination of one cumulative sum, ``C_t = s mu Z_t - t mu^2 / 2`` with
        ``Z_t = sum_{j<=t} clip(z'_j)``, and the walk reflected at 0 from ``S_0`` is
        ``S_t = C_t - min_{j<=t} C'_j`` where ``C'`` is C with its first value lowered to
        ``min(C_1, -S_0)``. The rows go through in sub-chunks of :attr:`SUB_ROWS` with
        the cumulative sum and the minima carried across them: the same floats as one
        pass over all the rows (:meth:`_statistics`), with a fraction of the memory
        traffic.
        """
        clip = self.design.clip
        n_rows, n = zr.shape
        if best is None:
            best = np.empty_like(zr)
        hypotheses = 2 * self.shifts.size
        final = np.zeros((hypotheses, n))
        if n_rows == 0:
            return best, final
        sub = min(self.SUB_ROWS, n_rows)
        total, walk, low = np.empty((sub, n)), np.empty((sub, n)), np.empty((sub, n))
        minima = list(-self.state.reshape(hypotheses, n))  # -S_0 seeds each minimum
        running = np.zeros(n)  # the cumulative sum of the clipped evidence so far
        # fmin skips NaN checks: the same floats as minimum here, since a NaN in the
        # evidence stays in the cumulative sum (every statistic after it is NaN either
        # way); only a NaN state would differ
        finite = bool(np.isfinite(self.state).all())
        accumulate = np.fmin.accumulate if finite else np.minimum.accumulate
        for lo in range(0, n_rows, sub):
            hi = min(n_rows, lo + sub)
            rows = hi - lo
            t_sum, t_walk, t_low = total[:rows], walk[:rows], low[:rows]
            np.clip(zr[lo:hi], -clip, clip, out=t_sum)
            if lo:
                t_sum[0] += running
            np.cumsum(t_sum, axis=0, out=t_sum)
            running = t_sum[-1].copy()
            steps = np.arange(lo + 1, hi + 1, dtype=float)[:, None]
            out = best[lo:hi]
            for d, mu in enumerate(self.shifts):
                drift = steps * (0.5 * mu * mu)
                for s, sign in enumerate((1.0, -1.0)):
                    k = 2 * d + s
                    np.multiply(t_sum, sign * mu, out=t_walk)
                    t_walk -= drift  # C
                    first = t_walk[0].copy()
                    np.minimum(first, minima[k], out=t_walk[0])
                    accumulate(t_walk, axis=0, out=t_low)
                    t_walk[0] = first
                    minima[k] = t_low[-1].copy()
                    np.subtract(t_walk, t_low, out=t_low)  # S
                    if k == 0:
                        out[...] = t_low
                    else:
                        np.maximum(out, t_low, out=out)
                    if hi == n_rows:
                        final[k] = t_low[-1]
        return best, final

    def _statistics(self, zr: np.ndarray) -> list[np.ndarray]:
        """Every hypothesis' statistic (list of 2 D arrays (M, n), shift-major) over the
        rows ``zr`` from the current state, in one pass: the same floats as
        :meth:`_cusums` (which keeps only their maximum); an episode's onset needs them on
        the rows up to its alarm."""
        clip = self.design.clip
        total = np.clip(zr, -clip, clip)
        np.cumsum(total, axis=0, out=total)
        steps = np.arange(1, zr.shape[0] + 1, dtype=float)[:, None]
        stats: list[np.ndarray] = []
        for d, mu in enumerate(self.shifts):
            drift = steps * (0.5 * mu * mu)
            for s, sign in enumerate((1.0, -1.0)):
                cumulative = np.multiply(total, sign * mu)
                cumulative -= drift
                first = cumulative[0].copy()
                np.minimum(first, -self.state[d, s], out=cumulative[0])  # seed the minimum
                statistic = np.minimum.accumulate(cumulative, axis=0)
                cumulative[0] = first
                np.subtract(cumulative, statistic, out=statistic)
                stats.append(statistic)
        return stats

    def _keep_state(self, values: np.ndarray) -> None:
        """The statistics (2 D, n: shift-major, then sign) as the next rows' start."""
        self.state.reshape(-1, self.n)[...] = values

    def _watch(self, z: np.ndarray, x: np.ndarray | None, position: int, out: Decisions) -> int:
        """No episode open: run the bank over the rows ``z`` (output rows from
        ``position``) up to the first alarm; returns the number of rows handled."""
        zr, marks = self._referenced(z, x, frozen=False)
        # the rows' scores are written in place; those after an alarm are written again
        best, final = self._cusums(zr, out.scores[position : position + len(zr)])
        top = best.max(axis=1) if self.n else np.zeros(len(zr))
        over = np.flatnonzero(top > self.threshold)
        stop = len(zr) if over.size == 0 else int(over[0]) + 1
        rows = slice(position, position + stop)
        out.statistic[rows] = top[:stop]
        if over.size:
            # every hypothesis up to the alarm row (the onset needs them), from the state
            # this call started from
            stats = self._statistics(zr[:stop])
            self._keep_state(np.array([statistic[-1] for statistic in stats]))
            self._rewind(marks, stop - 1)
            self._open(zr, stats, stop - 1, position, out)
        else:
            self._keep_state(final)
        self._remember(zr[:stop])
        self.samples += stop
        return stop

    def _open(
        self, zr: np.ndarray, stats: list[np.ndarray], row: int, position: int, out: Decisions
    ) -> None:
        """An episode opens at local row ``row`` (output row ``position + row``)."""
        values = np.array([s[row] for s in stats])  # (2 D, n)
        k, sensor = np.unravel_index(int(np.argmax(values)), values.shape)
        shift, sign_index = divmod(int(k), 2)
        sign = 1.0 if sign_index == 0 else -1.0
        evidence = (
            np.concatenate([self.history, zr[: row + 1]]) if self.history.size else zr[: row + 1]
        )
        count = self._onset_rows(
            stats[int(k)][: row + 1, sensor], evidence[:, sensor] * sign, shift
        )
        self.episode = _Episode(
            shift=shift,
            sign=sign,
            sensor=int(sensor),
            onset=self.samples + row + 1 - count,
            sums=evidence[-count:].sum(axis=0),
            count=count,
        )
        self.episodes += 1
        self._mark(out, position + row, values.max(axis=0))

    def _onset_rows(self, statistic: np.ndarray, signed: np.ndarray, shift: int) -> int:
        """Samples from the estimated onset of a hypothesis to its alarm row: the rows after
        the last one where its statistic was 0 (Page's change-point estimate). When it was
        positive since the start of these rows, the hypothesis' CUSUM is run again over the
        kept history (``signed``: its evidence times its sign, history included, ending at
        the alarm row) from 0 at the history's start."""
        zeros = np.flatnonzero(statistic <= 0.0)
        if zeros.size:
            return int(statistic.size - 1 - zeros[-1])
        cumulative = np.cumsum(increments(self.shifts[shift], self.design.clip, signed))
        again = cumulative - np.minimum(np.minimum.accumulate(cumulative), 0.0)
        zeros = np.flatnonzero(again <= 0.0)
        return int(signed.size - 1 - zeros[-1]) if zeros.size else int(signed.size)

    def _mark(self, out: Decisions, row: int, per_sensor: np.ndarray) -> None:
        """The alarm row that opens the episode: isolation and amplitude."""
        episode = self.episode
        assert episode is not None
        out.alarm[row] = True
        sensor = int(np.argmax(per_sensor))
        out.isolated[row] = sensor if self.isolable[sensor] else NOT_ISOLABLE
        if self.isolable[sensor] and episode.count and self.sensitivity[sensor] > 0:
            out.amplitude[row] = episode.sums[sensor] / episode.count / self.sensitivity[sensor]

    def _follow(self, z: np.ndarray, x: np.ndarray | None, position: int, out: Decisions) -> int:
        """An episode is open: keep the bank running over the rows ``z`` (reference
        frozen) and test whether the fault has ended; close the episode and restart every
        statistic when it has. Returns the number of rows handled."""
        episode = self.episode
        assert episode is not None
        zr, _ = self._referenced(z, x, frozen=True)
        best, final = self._cusums(zr, out.scores[position : position + len(zr)])
        # evidence that the fault has ended: the log-likelihood ratio of "no fault" against
        # "the fault as estimated so far" (its mean evidence since the onset, at least the
        # smallest design shift), one design per call, so that a fault between two design
        # shifts is not released while it lasts
        size = episode.sign * episode.sums[episode.sensor] / max(episode.count, 1)
        size = max(float(size), float(self.shifts[0]))
        increment = increments(size, self.design.clip, episode.sign * zr[:, episode.sensor])
        cumulative = np.cumsum(-increment)
        recovery = cumulative - np.minimum(np.minimum.accumulate(cumulative), -episode.recovery)
        ended = np.flatnonzero(recovery > self.threshold)
        stop = len(zr) if ended.size == 0 else int(ended[0]) + 1
        rows = slice(position, position + stop)
        out.statistic[rows] = best[:stop].max(axis=1)
        alarmed = stop if ended.size == 0 else stop - 1  # the row that ends it is quiet
        if alarmed:
            sums = np.cumsum(zr[:alarmed], axis=0)
            sums += episode.sums
            counts = episode.count + np.arange(1, alarmed + 1)
            sensors = np.argmax(best[:alarmed], axis=1)
            isolable = self.isolable[sensors]
            out.alarm[position : position + alarmed] = True
            out.isolated[position : position + alarmed] = np.where(isolable, sensors, NOT_ISOLABLE)
            with np.errstate(divide="ignore", invalid="ignore"):
                amplitude = sums[np.arange(alarmed), sensors] / counts / self.sensitivity[sensors]
            out.amplitude[position : position + alarmed] = np.where(isolable, amplitude, np.nan)
            episode.sums = sums[-1]
            episode.count = int(counts[-1])
        if ended.size:
            self.state[:] = 0.0
            self.episode = None
        else:
            self._keep_state(final)  # (stop is the last row)
            episode.recovery = float(recovery[stop - 1])
        self._remember(zr[:stop])
        self.samples += stop
        return stop

    def _remember(self, zr: np.ndarray) -> None:
        """Keep the last ``history`` rows of referenced evidence (for onsets)."""
        if self.history_length <= 0 or zr.shape[0] == 0:
            return
        if zr.shape[0] >= self.history_length:
            self.history = zr[-self.history_length :].copy()
            return
        joined = np.concatenate([self.history, zr]) if self.history.size else zr
        self.history = joined[-self.history_length :].copy()
