"""Sequential decisions on a noise growth under a false-alarm budget: a variance CUSUM bank.

The companion of :mod:`imufdi_cli.maths.sequential` (which tests mean shifts) for faults
that keep a sensor's output unbiased and make it noisier. A detector hands in, per term t
and sensor i, standardized evidence ``z_t,i``: independent N(0, 1) without a fault, and
N(0, rho_i) when sensor i's noise grows (``rho_i`` the variance ratio that growth puts into
column i). Terms are independent by construction
(:class:`~imufdi_cli.maths.contrasts.HelmertContrasts`), so the run lengths below are those
of the exact increment distribution, not of an approximation.

**The bank.** For every sensor i and design variance ratio ``K_d``
(:attr:`VarianceDesign.ratios`), Page's CUSUM of the log-likelihood ratio of
"variance K_d" against "variance 1" of the clipped evidence (Page, Biometrika 41, 1954;
Basseville & Nikiforov, *Detection of Abrupt Changes*, 1993, §2.2)::

    l_t = 1/2 (1 - 1/K_d) min(z'_t,i^2, c^2) - 1/2 ln K_d                (1)
    S_t = max(0, S_{t-1} + l_t)                                           (2)

The clip c bounds what one outlier (or the transient of a bias step) adds:
``1/2 (1 - 1/K) c^2 - 1/2 ln K``. An episode starts at the first term where any
``S > h`` (n D hypotheses); its isolated sensor is that of the largest S. While it lasts,
the bank tests "the noise is back to nominal" on that sensor: a CUSUM of ``-l_t`` for the
variance ratio estimated since the onset (at least the smallest design; unclipped, so that
a lasting fault is ended by mistake with probability ~exp(-h) only); when that reaches
h the episode ends and every statistic restarts from 0 (a renewal: each false episode
costs one average run length).

**The threshold.** h makes the union bound of the bank's false episodes per term
``sum_d n / ARL_d(h)`` equal to the budget's share per term, with ``ARL_d`` from the
Markov chain of Brook & Evans (Biometrika 59, 1972) on the exact distribution of (1):
``z^2 ~ s^2 chi2(1)`` clipped, with s the sigma error of the calibration (averaged over
its distribution by Gauss-Hermite quadrature, as for CUSUM charts with estimated
parameters: Jones, Champ & Rigdon, Technometrics 43, 2001) and a share of outliers beyond
the clip seen in calibration. A variance test is far more sensitive to a sigma error than a
mean test (a variance 10 % low is the start of a growth: at h ~ 15 it raises about ten
times the false alarms), so each column's variance is tracked: a running mean of the
winsorized squared evidence from the calibration window on (the estimate's error falls as
``sqrt(2 / terms)``), then an exponential average of time constant ``scale_tau``, updated
once per sub-block of about a second and frozen while an episode is open (the sub-block
in which an episode opens is dropped, so a fault detected within it is not absorbed). The
threshold follows the estimate's error as it shrinks (:func:`threshold_schedule`): at every
moment it holds the budget for the error then, 23 in the first seconds after a 2 s
calibration against 14 once the variance is learnt (48 sensors, 1/h at 100 Hz).

**Reference delay.** A variance ratio rho per term carries the Kullback-Leibler
information ``1/2 (rho - 1 - ln rho)``; no test with an average run length gamma among K
hypotheses detects it faster, asymptotically, than ``ln(gamma K) / I`` terms (Lorden 1971):
:func:`lorden_variance_terms`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from imufdi_cli.maths.sequential import NO_ISOLATION, NOT_ISOLABLE, Decisions
from imufdi_cli.maths.sequential.thresholds import (
    chain_run_lengths,
    scale_points,
    threshold_root,
)

#: Winsorizing level of the tracked variance (squared evidence above 16 variances counts 16).
WINSOR = 16.0


@dataclass(frozen=True)
class VarianceDesign:
    """The variance bank's fixed design.

    Attributes
    ----------
    ratios : tuple of float
        Design variance ratios ``K_d > 1``: each is optimal for a growth of that variance
        ratio (a noise standard deviation times ``sqrt(K_d)``).
    clip : float
        z is clipped at ``+-clip`` in (1).
    scale_tau_s : float
        Time constant of each column's tracked variance after its running-mean start,
        seconds (0: the calibrated variance is kept).
    """

    ratios: tuple[float, ...] = (3.0, 9.0)
    clip: float = 4.0
    scale_tau_s: float = 600.0


def variance_increments(ratio: float, clip: float, z: np.ndarray) -> np.ndarray:
    """The increments (1) of design ``ratio`` for evidence ``z`` (any shape)."""
    squares = np.minimum(np.square(z), clip * clip)
    return 0.5 * (1.0 - 1.0 / ratio) * squares - 0.5 * math.log(ratio)


def _erf(x: np.ndarray) -> np.ndarray:
    """scipy's erf (imported when a threshold is computed, not on import)."""
    from scipy.special import erf

    return np.asarray(erf(x), dtype=float)


def _increment_cdf(
    ratio: float,
    clip: float,
    x: np.ndarray,
    scale: np.ndarray | float = 1.0,
    contamination: float = 0.0,
) -> np.ndarray:
    """CDF of (1) at ``x`` for z ~ N(0, scale^2) with probability 1 - p and an outlier
    beyond the clip with probability p = ``contamination`` (``scale`` broadcasts with
    ``x``)."""
    gain = 0.5 * (1.0 - 1.0 / ratio)
    offset = 0.5 * math.log(ratio)
    level = (np.asarray(x, float) + offset) / gain  # l <= x  <=>  min(z^2, c^2) <= level
    root = np.sqrt(np.maximum(level, 0.0)) / (np.asarray(scale, float) * math.sqrt(2.0))
    inside = _erf(root)  # P(|z| <= sqrt(level))
    top = level >= clip * clip
    gaussian = np.where(level < 0.0, 0.0, np.where(top, 1.0, inside))
    if contamination <= 0:
        return gaussian
    return (1.0 - contamination) * gaussian + contamination * top


@lru_cache(maxsize=4096)
def _run_lengths(
    ratio: float,
    clip: float,
    threshold: float,
    scales: tuple[float, ...],
    contamination: float,
    states: int,
) -> tuple[float, ...]:
    width = 2.0 * threshold / (2 * states - 1)
    offsets = np.arange(-states, states + 1)[None, :]
    values = _increment_cdf(
        ratio, clip, (offsets - 0.5) * width, np.asarray(scales)[:, None], contamination
    )
    return tuple(float(v) for v in chain_run_lengths(values, states))


def variance_run_length(
    ratio: float,
    clip: float,
    threshold: float,
    states: int = 100,
    scale: float = 1.0,
    contamination: float = 0.0,
) -> float:
    """Average run length (terms) of one CUSUM (1)-(2) without fault, from S = 0, when the
    evidence has standard deviation ``scale`` and a share ``contamination`` of outliers
    beyond the clip (Brook & Evans' Markov chain, :func:`chain_run_lengths`). With
    ``scale`` above 1 it is the mean delay of a growth by the variance ratio ``scale^2``
    from a zero start."""
    if threshold <= 0:
        return 1.0
    return _run_lengths(ratio, clip, threshold, (float(scale),), contamination, states)[0]


def variance_false_alarm_rate(
    design: VarianceDesign,
    sensors: int,
    threshold: float,
    scale_variance: float = 0.0,
    contamination: float = 0.0,
) -> float:
    """Union bound of the bank's false alarm episodes per term at threshold ``h``.

    ``scale_variance``: the variance of ``sigma_hat^2 / sigma^2`` of each column's
    variance estimate (``2 / nu`` for nu degrees of freedom); the rate is averaged over
    that error (Gauss-Hermite). ``contamination``: the share of terms that are outliers
    beyond the clip."""
    if threshold <= 0:
        return float(sensors * len(design.ratios))
    points = scale_points(scale_variance, 5)
    scales = tuple(scale for scale, _ in points)
    weights = np.array([weight for _, weight in points])
    total = 0.0
    for ratio in design.ratios:
        lengths = np.array(
            _run_lengths(ratio, design.clip, threshold, scales, round(contamination, 7), 100)
        )
        total += sensors * float(weights @ (1.0 / lengths))
    return total


def variance_threshold(
    design: VarianceDesign,
    sensors: int,
    per_term: float,
    scale_variance: float = 0.0,
    contamination: float = 0.0,
) -> float:
    """The threshold h whose union-bound false alarm rate is ``per_term`` (episodes per
    term of evidence), with the variance estimate's error and outliers
    (:func:`variance_false_alarm_rate`). ``log rate(h)`` is close to linear in h: secant
    steps, then regula falsi inside the bracket; h is rounded up to 1e-3.

    Raises ValueError for a rate outside (0, 1)."""
    if not 0.0 < per_term < 1.0:
        raise ValueError(f"per-term rate must be in (0, 1), got {per_term!r}")
    target = math.log(per_term)

    def gap(h: float) -> float:
        rate = variance_false_alarm_rate(design, sensors, h, scale_variance, contamination)
        return math.log(rate) - target

    guess = max(1.0, 0.9 * math.log(sensors * len(design.ratios) / per_term))
    try:
        return threshold_root(gap, 0.25, guess, 12)
    except ValueError:
        raise ValueError(f"no threshold meets {per_term:g} per term") from None


def threshold_schedule(
    design: VarianceDesign,
    sensors: int,
    per_term: float,
    calibration_terms: float,
    contamination: float = 0.0,
    tolerance: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """Thresholds for a variance estimate that learns: ``(terms, h)`` with ``h[k]`` the
    :func:`variance_threshold` for an estimate from ``terms[k]`` terms (relative variance
    ``2 / terms[k]``), ``terms[0] = calibration_terms`` doubling until h is within
    ``tolerance`` of the known-variance threshold, which ends the schedule. The bank uses ``h[k]`` once its tracked variance rests on ``terms[k]`` terms
    or more: at every time the rate is at most ``per_term`` for the estimate's error
    then (the first seconds after a short calibration are the dearest: 23.4 against
    14.2 for 150 terms, 48 sensors, 1/h at 100 Hz)."""
    known = variance_threshold(design, sensors, per_term, 0.0, contamination)
    if not math.isfinite(calibration_terms):
        return np.array([0.0]), np.array([known])
    terms, values = [], []
    count = max(float(calibration_terms), 2.0)
    for _ in range(40):
        h = variance_threshold(design, sensors, per_term, 2.0 / count, contamination)
        if h - known <= tolerance:
            break
        terms.append(count)
        values.append(h)
        count *= 2.0
    terms.append(count)
    values.append(known)
    return np.array(terms), np.array(values)


def variance_information(ratio: float) -> float:
    """Kullback-Leibler information per term of a variance ratio ``ratio`` against 1:
    ``1/2 (rho - 1 - ln rho)``."""
    if ratio <= 0:
        return math.inf
    return 0.5 * (ratio - 1.0 - math.log(ratio))


def lorden_variance_terms(ratio: float, run_length: float, hypotheses: int) -> float:
    """``ln(gamma K) / I(rho)``: terms an optimal test needs, asymptotically, to detect a
    variance ratio ``rho`` at an average run length gamma among K hypotheses (Lorden
    1971)."""
    information = variance_information(ratio)
    if not information > 0:
        return math.inf
    return math.log(max(run_length * hypotheses, 1.0)) / information


# --- the streaming bank --------------------------------------------------------------------


@dataclass
class _Episode:
    design: int  # index of the design ratio that raised it
    sensor: int
    onset: int  # estimated onset, absolute row index
    sums: np.ndarray = field(default_factory=lambda: np.zeros(0))  # z'^2 since the onset
    counts: np.ndarray = field(default_factory=lambda: np.zeros(0))  # terms since the onset
    recovery: float = 0.0  # the "noise is back to nominal" CUSUM


class VarianceCusumBank:
    """Streaming bank of variance-growth CUSUMs over one sensor type (module docstring).

    The outputs do not depend on how the rows are split into calls (the tracked variance
    moves once per sub-block of ``stride`` rows aligned on the row count).

    Parameters
    ----------
    design : VarianceDesign
    threshold : float or (ndarray, ndarray)
        h (:func:`variance_threshold`), or a schedule ``(terms, h)``
        (:func:`threshold_schedule`): ``h[k]`` applies once the tracked variance rests on
        ``terms[k]`` terms or more (the calibration's and those learnt since; without
        tracking, the calibration's only).
    isolable : ndarray, shape (n,), bool
        Whether sensor i's growth can be told from every other sensor's.
    rate_hz : float
        Rows per second (the tracked variance's time constant and sub-blocks).
    calibration_terms : float
        Terms each column's variance was calibrated from: the tracked variance starts as
        their running mean (gain ``1 / (N + k)`` after k more terms) until the gain falls
        to that of ``scale_tau``.
    history : int
        Rows of evidence kept to estimate an episode's onset.
    floor : ndarray, shape (n,), optional
        Lowest tracked variance of each column (default 0.25): 1 where the evidence is
        standardized by the top of a healthy range (a noise that changes with the
        orientation), so that learning a quiet stretch does not make the range's top a
        growth.
    """

    #: Rows run through the bank at once at most.
    SPAN = 2048

    def __init__(
        self,
        design: VarianceDesign,
        threshold: float | tuple[np.ndarray, np.ndarray],
        isolable: np.ndarray,
        rate_hz: float,
        calibration_terms: float = math.inf,
        history: int = 512,
        floor: np.ndarray | None = None,
    ) -> None:
        self.design = design
        if isinstance(threshold, tuple):
            self.schedule_terms = np.asarray(threshold[0], float)
            self.schedule = np.asarray(threshold[1], float)
        else:
            self.schedule_terms = np.zeros(1)
            self.schedule = np.array([float(threshold)])
        self.threshold = float(self.schedule[0])
        self.isolable = np.asarray(isolable, bool)
        n = self.isolable.size
        self.n = n
        self.ratios = np.asarray(design.ratios, float)
        self.gains = 0.5 * (1.0 - 1.0 / self.ratios)
        self.offsets = 0.5 * np.log(self.ratios)
        self.state = np.zeros((self.ratios.size, n))
        self.variance = np.ones(n)  # tracked, relative to the calibrated one
        self.floor = np.full(n, 0.25) if floor is None else np.asarray(floor, float)
        self.stride = max(1, round(rate_hz))
        self.scale_step = 0.0 if design.scale_tau_s <= 0 else 1.0 / (design.scale_tau_s * rate_hz)
        self.calibration_terms = float(calibration_terms)
        self.terms_seen = np.zeros(n)
        self.pending = np.zeros(n)
        self.pending_terms = np.zeros(n)
        self.history = np.zeros((0, n))
        self.history_length = int(history)
        self.samples = 0
        self.episode: _Episode | None = None
        self.episodes = 0
        self._schedule()

    def effective_terms(self) -> float:
        """Terms the tracked variance rests on: the calibration's and those averaged since
        while the gain is a running mean's; ``2 / gain`` for the exponential average after
        (its estimate has the relative variance of a mean of that many terms)."""
        seen = float(self.terms_seen.max()) if self.n else 0.0
        count = self.calibration_terms + seen
        if self.scale_step > 0:
            count = min(count, 2.0 / self.scale_step)
        return count

    def _schedule(self) -> None:
        """The threshold in force for the variance estimate as it stands."""
        count = self.effective_terms()
        k = int(np.searchsorted(self.schedule_terms, count, side="right")) - 1
        self.threshold = float(self.schedule[max(k, 0)])

    # --- processing --------------------------------------------------------------------

    def process(self, z: np.ndarray) -> Decisions:
        """Decide on the rows of ``z`` (N, n): standardized terms per sensor (N(0, 1)
        without a fault; NaN: no term on that row)."""
        z = np.asarray(z, float)
        if z.ndim != 2 or z.shape[1] != self.n:
            raise ValueError(f"evidence must be (N, {self.n}), got {z.shape}")
        z = np.where(np.isfinite(z), z, np.nan)
        n_rows = z.shape[0]
        out = Decisions(
            statistic=np.zeros(n_rows),
            threshold=np.full(n_rows, self.threshold),
            alarm=np.zeros(n_rows, bool),
            isolated=np.full(n_rows, NO_ISOLATION, np.int32),
            amplitude=np.full(n_rows, np.nan),
            scores=np.empty((n_rows, self.n)),
        )
        position = 0
        while position < n_rows:
            phase = self.samples % self.stride
            stop = min(n_rows, position + self.stride - phase)
            if self.episode is None:
                position += self._watch(z[position:stop], position, out)
            else:
                position += self._follow(z[position:stop], position, out)
        return out

    def _cusums(self, zr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every CUSUM (1)-(2) over the rows ``zr`` (M, n) from the current state: (D, M, n),
        with Lindley's ``S_t = C_t - min(-S_0, min_{j<=t} C_j)`` of the cumulative
        log-likelihood ratio C; and the squares ``min(z'^2, c^2)`` (M, n; 0 for NaN)."""
        valid = ~np.isnan(zr)
        squares = np.where(
            valid, np.minimum(np.square(np.nan_to_num(zr)), self.design.clip**2), 0.0
        )
        total = np.cumsum(squares, axis=0)
        terms = np.cumsum(valid, axis=0, dtype=float)
        stats = np.empty((self.ratios.size, *zr.shape))
        for d in range(self.ratios.size):
            cumulative = self.gains[d] * total - self.offsets[d] * terms
            floor = np.minimum(np.minimum.accumulate(cumulative, axis=0), -self.state[d][None, :])
            stats[d] = cumulative - floor
        return stats, squares

    def _referenced(self, z: np.ndarray) -> np.ndarray:
        return z / np.sqrt(self.variance)

    def _track(self, z: np.ndarray) -> None:
        """Add the rows ``z`` (calibrated units) to the open sub-block of the tracked
        variance; apply it when the sub-block is complete."""
        if self.scale_step <= 0 and not math.isfinite(self.calibration_terms):
            return
        valid = ~np.isnan(z)
        squares = np.minimum(np.square(np.nan_to_num(z)), WINSOR * self.variance)
        self.pending += np.where(valid, squares, 0.0).sum(axis=0)
        self.pending_terms += valid.sum(axis=0)

    def _complete(self) -> None:
        counted = self.pending_terms > 0
        if counted.any():
            start = 1.0 / (self.calibration_terms + self.terms_seen + self.pending_terms)
            gain = np.maximum(self.scale_step, start) if self.scale_step > 0 else start
            updated = self.variance + gain * (self.pending - self.pending_terms * self.variance)
            self.variance = np.where(counted, np.maximum(updated, self.floor), self.variance)
            self.terms_seen += self.pending_terms
        self.pending = np.zeros(self.n)
        self.pending_terms = np.zeros(self.n)
        self._schedule()

    def _watch(self, z: np.ndarray, position: int, out: Decisions) -> int:
        """No episode open: the bank over the rows ``z`` (at most to the end of the
        sub-block) up to the first alarm; returns the rows handled."""
        zr = self._referenced(z)
        stats, _ = self._cusums(zr)
        best = stats.max(axis=0)
        top = best.max(axis=1) if self.n else np.zeros(len(zr))
        over = np.flatnonzero(top > self.threshold)
        stop = len(zr) if over.size == 0 else int(over[0]) + 1
        rows = slice(position, position + stop)
        out.statistic[rows] = top[:stop]
        out.threshold[rows] = self.threshold
        out.scores[rows] = best[:stop]
        self.state = stats[:, stop - 1].copy()
        if over.size:
            # the open sub-block's sums are dropped: the episode's samples never move it
            self.pending = np.zeros(self.n)
            self.pending_terms = np.zeros(self.n)
            self._open(zr, stats, stop - 1, position, out)
        else:
            self._track(z)
        self._remember(zr[:stop])
        self.samples += stop
        if self.episode is None and self.samples % self.stride == 0:
            self._complete()
        return stop

    def _open(
        self, zr: np.ndarray, stats: np.ndarray, row: int, position: int, out: Decisions
    ) -> None:
        values = stats[:, row]  # (D, n)
        design, sensor = np.unravel_index(int(np.argmax(values)), values.shape)
        evidence = np.concatenate([self.history, zr[: row + 1]])
        count = self._onset_rows(stats[design, : row + 1, sensor], evidence[:, sensor], int(design))
        recent = evidence[-count:]
        valid = ~np.isnan(recent)
        self.episode = _Episode(
            design=int(design),
            sensor=int(sensor),
            onset=self.samples + row + 1 - count,
            sums=np.where(valid, np.square(np.nan_to_num(recent)), 0.0).sum(axis=0),
            counts=valid.sum(axis=0).astype(float),
        )
        self.episodes += 1
        per_sensor = values.max(axis=0)
        best = int(np.argmax(per_sensor))
        out.alarm[position + row] = True
        out.isolated[position + row] = best if self.isolable[best] else NOT_ISOLABLE
        out.amplitude[position + row] = self._amplitude(best)

    def _amplitude(self, sensor: int) -> float:
        """The sensor's standard deviation ratio since the episode's onset."""
        episode = self.episode
        assert episode is not None
        if not self.isolable[sensor] or episode.counts[sensor] <= 0:
            return math.nan
        return math.sqrt(episode.sums[sensor] / episode.counts[sensor])

    def _onset_rows(self, statistic: np.ndarray, terms: np.ndarray, design: int) -> int:
        """Rows from the estimated onset to the alarm row: after the last row where the
        hypothesis' statistic was 0 (Page's estimate), or, when it was positive on every
        row of this call, from its CUSUM run again over the kept history (``terms``:
        history and these rows of its sensor, ending at the alarm row)."""
        zeros = np.flatnonzero(statistic <= 0.0)
        if zeros.size:
            return int(statistic.size - 1 - zeros[-1])
        increments = np.where(
            np.isnan(terms),
            0.0,
            variance_increments(self.ratios[design], self.design.clip, np.nan_to_num(terms)),
        )
        cumulative = np.cumsum(increments)
        again = cumulative - np.minimum(np.minimum.accumulate(cumulative), 0.0)
        zeros = np.flatnonzero(again <= 0.0)
        return int(terms.size - 1 - zeros[-1]) if zeros.size else int(terms.size)

    def _follow(self, z: np.ndarray, position: int, out: Decisions) -> int:
        """An episode is open: the bank keeps running (variance frozen) and tests whether
        the noise is back to nominal; the episode closes, and every statistic restarts,
        when it is. Returns the rows handled."""
        episode = self.episode
        assert episode is not None
        zr = self._referenced(z)
        stats, _ = self._cusums(zr)
        best = stats.max(axis=0)
        sensor = episode.sensor
        size = episode.sums[sensor] / max(episode.counts[sensor], 1.0)
        size = max(float(size), float(self.ratios.min()))
        gain, offset = 0.5 * (1.0 - 1.0 / size), 0.5 * math.log(size)
        # unclipped: a large term is evidence that the fault lasts (the clip guards the
        # other direction), and the exact log-likelihood ratio ends a lasting fault by
        # mistake with probability ~exp(-h) only (Wald)
        own = zr[:, sensor]
        valid = ~np.isnan(own)
        back = np.where(valid, offset - gain * np.square(np.nan_to_num(own)), 0.0)
        cumulative = np.cumsum(back)
        recovery = cumulative - np.minimum(np.minimum.accumulate(cumulative), -episode.recovery)
        ended = np.flatnonzero(recovery > self.threshold)
        stop = len(zr) if ended.size == 0 else int(ended[0]) + 1
        rows = slice(position, position + stop)
        out.statistic[rows] = best[:stop].max(axis=1)
        out.threshold[rows] = self.threshold
        out.scores[rows] = best[:stop]
        alarmed = stop if ended.size == 0 else stop - 1  # the row that ends it is quiet
        if alarmed:
            present = ~np.isnan(zr[:alarmed])
            sums = np.cumsum(np.where(present, np.square(np.nan_to_num(zr[:alarmed])), 0.0), axis=0)
            counts = np.cumsum(present, axis=0, dtype=float)
            sums += episode.sums
            counts += episode.counts
            sensors = np.argmax(best[:alarmed], axis=1)
            isolable = self.isolable[sensors]
            picked = np.arange(alarmed)
            with np.errstate(divide="ignore", invalid="ignore"):
                amplitude = np.sqrt(sums[picked, sensors] / counts[picked, sensors])
            out.alarm[position : position + alarmed] = True
            out.isolated[position : position + alarmed] = np.where(isolable, sensors, NOT_ISOLABLE)
            out.amplitude[position : position + alarmed] = np.where(isolable, amplitude, np.nan)
            episode.sums, episode.counts = sums[-1], counts[-1]
        if ended.size:
            self.state = np.zeros_like(self.state)
            self.episode = None
        else:
            self.state = stats[:, stop - 1].copy()
            episode.recovery = float(recovery[stop - 1])
        self._remember(zr[:stop])
        self.samples += stop
        if self.episode is None and self.samples % self.stride == 0:
            self._complete()
        return stop

    def _remember(self, zr: np.ndarray) -> None:
        if self.history_length <= 0 or zr.shape[0] == 0:
            return
        joined = np.concatenate([self.history, zr]) if self.history.size else zr
        self.history = joined[-self.history_length :].copy()
