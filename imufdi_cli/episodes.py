"""Alarm episodes and what they mean: which sensor, which kind of fault, how big, and why.

An **episode** is a run of alarms of one detector on one sensor type. Alarms are merged
across gaps of at most ``merge_gap`` quiet samples (0.1 s: a detector at its nominal
false-alarm level flickers inside a fault; a gap that short is not a recovery), whatever
they isolate. Such a run is then joined to the previous episode of the **same isolated
sensor** when at most ``join_gap`` (1 s) separates them: a fault that a detector sees in
fragments (noise growth, spikes) is one fault, and is explained over its whole span,
quiet gaps included, instead of over the fragments where the statistic happened to be
highest. Its start and end are the first and last alarmed samples; the decision times are
those of the status rows.

Explaining an episode works on the isolated sensor ``k`` alone, against the consensus of
the others (leave-one-out least squares, :func:`leave_one_out`)::

    r(t) = y_k(t) - h_k^T x_hat_{-k}(t),      Var r = sigma_k^2 + h_k^T (H_{-k}^T W H_{-k})^{-1} h_k

so ``r`` is the sensor's own error, whatever the motion. Over an analysis window (the
episode plus a margin before it) the fault models of ``imufdi inject`` are fitted to ``r``
with an unknown onset ``tau`` (profile likelihood over every sample of the margin and the
episode's first part) and, when the detector's alarms outlast the fault, an end
(:func:`_fault_end`):

======  ==========================================  ==================================
model   r(t) for t >= tau (before: N(0, sigma_r^2))  size (90 % interval)
======  ==========================================  ==================================
step    a + e                                        amp: t interval (:func:`_linear_fit`)
drift   b (t - t_f) + e, t_f between two samples     rate: t interval of the LS slope
noise   e, Var e = f^2 sigma_k^2 + sigma_c^2         factor: successive differences, F
scale   beta o(t) + e, o the consensus prediction    factor: 1 + beta_hat, t interval
spikes  e + s A on a fraction p of samples           amp A (t interval), rate (Poisson)
stuck   y_k(t) = y_k(tau - 1) exactly                value (exact)
======  ==========================================  ==================================

The models are ranked by BIC (Schwarz 1978): the Gaussian log-likelihood of the whole
window minus half the number of free parameters times ln n. ``none`` (no fault: the
residual is the calibrated noise throughout) is ranked with them, so an episode that no
fault model explains better than chance is called a false alarm, with its evidence.
``stuck`` is not a Gaussian model (a frozen output has no noise at all): it is declared
when the raw output repeats exactly on at least ``stuck_share`` of the samples after the
onset (a healthy sensor always carries its own noise, so long exact repeats do not
happen), and then ranks first.

The least-squares sizes (step, drift, scale) are linear estimates ``w^T r``; their variance
propagates the noise (estimated from the fit's own residuals, with their autocorrelation,
Newey & West 1994), and the calibrated bias taken out of ``r`` (a constant estimated from
n_cal samples). The other sensors, each against a consensus without ``k``, give the same
estimate where there is no fault: when they spread significantly more than that variance
says (chi-square test at 95 %), the interval is widened to their dispersion
(:func:`_linear_fit`); when they still spread too much, or the sensor's own residual
carries the motion, the motion-dependent errors (scale, misalignment: linear in the
sensed vector) are fitted alongside over the whole window (:func:`_motion_fit`). The noise
factor is sized from successive differences against the white part of the calibrated
noise (:func:`white_sigma`), F(nu, nu_cal) (:func:`_white_noise_fit`): slow errors and
shifts of the consensus do not enter it.

A frozen output on a motion the sensor tracks exactly (a constant-rate turntable) loses
only its noise, which no mean-shift detector sees: :class:`VarianceDropMonitor`, a
one-sided successive-difference variance test, raises episodes of its own under the name
``variance-drop`` (one builder per sensor type runs it). Coverage and false episodes are
measured in ``tests/test_episodes.py``, ``benchmarks/bench_episodes.py`` and
docs/episodes.md.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from imufdi_cli.detectors.parity import (
    check_measurement_matrix,
    least_squares_matrix,
    residual_projector,
)

#: ``(sigma_k, consensus_sigma, dof)`` or ``(sigma_k, consensus_sigma, dof, (A, B, D))``:
#: the white noise of a sensor and its consensus, and how well the calibration knows them
#: (:func:`fit_models`, :func:`white_sigma_spread`)
WhiteNoise = tuple[float, float, float] | tuple[float, float, float, tuple[float, float, float]]

#: fault models an episode is explained by, in tie-break order
MODELS = ("none", "step", "drift", "noise", "scale", "spikes", "stuck")
#: what the size of each model is
SIZE_NAMES = {
    "none": "",
    "step": "amp",
    "drift": "rate",
    "noise": "factor",
    "scale": "factor",
    "spikes": "amp",
    "stuck": "value",
}
#: residuals beyond this many sigma_r count as spikes
SPIKE_CUT = 4.0


@dataclass(frozen=True)
class FaultFit:
    """One fault model fitted to an episode's residual.

    Attributes
    ----------
    model : str
        One of :data:`MODELS`.
    size : float
        Step amplitude, drift rate (per second), noise or scale factor, spike amplitude, or
        stuck value; SI units of the sensor type (factors are dimensionless).
    low, high : float
        Confidence interval of ``size`` at the fit's confidence level.
    onset_index : int
        Index in the analysis window where the fitted fault starts.
    bic : float
        Schwarz criterion ``-2 log L + k ln n`` (lower is better; ``-inf`` for stuck).
    extra : dict
        Model-specific figures (spikes: ``rate_hz`` with its interval).
    """

    model: str
    size: float
    low: float
    high: float
    onset_index: int
    bic: float
    extra: dict[str, float] = field(default_factory=dict)
    #: index in the analysis window where the fitted fault ends (exclusive; None: it lasts
    #: to the window's end)
    end_index: int | None = None
    #: fitted mean and variance of the residual from the onset on (for the end search; not
    #: serialised)
    curve: tuple[np.ndarray, float] | None = field(default=None, repr=False, compare=False)

    @property
    def size_name(self) -> str:
        return SIZE_NAMES[self.model]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (non-finite numbers become None)."""
        out = _finite(
            {
                "model": self.model,
                "size": self.size,
                "low": self.low,
                "high": self.high,
                "onset_index": self.onset_index,
                "end_index": self.end_index,
                "bic": self.bic,
                "extra": dict(self.extra),
            }
        )
        out["size_name"] = self.size_name
        return out


def _finite(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None, recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


# --- episodes from status rows ---------------------------------------------------------


def find_episodes(alarm: np.ndarray, merge_gap: int = 0) -> list[tuple[int, int]]:
    """Runs of alarms merged across gaps of at most ``merge_gap`` quiet samples.

    Parameters
    ----------
    alarm : array_like, shape (N,), bool
    merge_gap : int
        Longest run of quiet samples that does not end an episode.

    Returns
    -------
    list of (start, stop)
        Index ranges ``[start, stop)``; ``alarm[start]`` and ``alarm[stop - 1]`` are set.
    """
    alarm = np.asarray(alarm, dtype=bool)
    if merge_gap < 0:
        raise ValueError("merge_gap must be >= 0")
    padded = np.concatenate(([False], alarm, [False]))
    edges = np.flatnonzero(np.diff(padded.astype(np.int8)))
    starts, stops = edges[0::2], edges[1::2]
    if starts.size == 0:
        return []
    keep = np.concatenate(([True], starts[1:] - stops[:-1] > merge_gap))
    merged_starts = starts[keep]
    merged_stops = np.concatenate((stops[:-1][keep[1:]], stops[-1:]))
    return [(int(a), int(b)) for a, b in zip(merged_starts, merged_stops)]


# --- the isolated sensor against the others ---------------------------------------------


def leave_one_out(
    H: np.ndarray, measurements: np.ndarray, sigma: np.ndarray | float, k: int
) -> tuple[np.ndarray, np.ndarray, float]:
    """Sensor ``k`` against the weighted least-squares consensus of the other sensors.

    Parameters
    ----------
    H : array_like, shape (n, 3)
        Measurement matrix of the sensor type.
    measurements : array_like, shape (N, n)
        SI units.
    sigma : float or array_like, shape (n,)
        Per-sensor white-noise standard deviation, SI.
    k : int
        Sensor index.

    Returns
    -------
    residual : ndarray, shape (N,)
        ``y_k - h_k^T x_hat_{-k}``.
    prediction : ndarray, shape (N,)
        ``h_k^T x_hat_{-k}``: what the others say sensor k should read.
    consensus_sigma : float
        Standard deviation of the prediction error, ``sqrt(h_k^T (H_{-k}^T W H_{-k})^{-1} h_k)``.
    """
    gain, consensus_sigma = _consensus_gain(H, sigma, k)
    m = np.asarray(measurements, dtype=np.float64)
    prediction = m @ gain
    return m[:, k] - prediction, prediction, consensus_sigma


def _consensus_gain(
    H: np.ndarray, sigma: np.ndarray | float, k: int, exclude: int | None = None
) -> tuple[np.ndarray, float]:
    """(n,) weights of the prediction of sensor k from the others (0 for k itself and for
    ``exclude``), and the prediction's standard deviation."""
    H = check_measurement_matrix(H)
    n = H.shape[0]
    sigma_arr = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (n,))
    others = np.flatnonzero(
        (np.arange(n) != k) & (np.arange(n) != (-1 if exclude is None else exclude))
    )
    H_o = H[others]
    if np.linalg.matrix_rank(H_o) < 3:
        raise ValueError(f"sensor {k}: the other sensors do not span 3 axes")
    gain = np.zeros(n)
    gain[others] = H[k] @ least_squares_matrix(H_o, sigma_arr[others])
    return gain, float(np.sqrt(np.sum((gain * sigma_arr) ** 2)))


# --- fitting the fault models -------------------------------------------------------------


# Quantiles through scipy.special's inverse distribution functions (ufuncs: microseconds a
# call, where scipy.stats' ppf checks its arguments for milliseconds, and every episode
# length is a new degree of freedom); cached for the lengths that repeat.


@functools.lru_cache(maxsize=4096)
def _chi2_quantile(p: float, dof: int) -> float:
    """Chi-square quantile: ``chdtri`` inverts the upper tail."""
    from scipy.special import chdtri

    return float(chdtri(dof, 1.0 - p))


@functools.lru_cache(maxsize=4096)
def _f_quantile(p: float, dof1: float, dof2: float) -> float:
    """F(dof1, dof2) quantile."""
    from scipy.special import fdtri

    return float(fdtri(dof1, dof2, p))


@functools.lru_cache(maxsize=4096)
def _t_quantile(p: float, dof: int) -> float:
    """Student t quantile."""
    from scipy.special import stdtrit

    return float(stdtrit(dof, p))


def _gaussian_nll(ss: Any, n: Any, var: Any) -> Any:
    """-log L of n samples with sum of squares ss about their model, variance var."""
    return 0.5 * (ss / var + n * np.log(2 * math.pi * var))


def _suffix(values: np.ndarray) -> np.ndarray:
    """S[j] = sum(values[j:]), shape (L + 1,)."""
    out = np.zeros(values.shape[0] + 1)
    out[:-1] = np.cumsum(values[::-1])[::-1]
    return out


def fit_models(
    residual: np.ndarray,
    prediction: np.ndarray,
    t_s: np.ndarray,
    sigma_k: float,
    consensus_sigma: float,
    *,
    onset_range: tuple[int, int],
    confidence: float = 0.9,
    stuck_share: float = 0.9,
    raw: np.ndarray | None = None,
    calibration_samples: int | None = None,
    offset_var: float | None = None,
    reference: Reference | None = None,
    white: WhiteNoise | None = None,
) -> list[FaultFit]:
    """Fit every fault model to one sensor's residual over an analysis window.

    Parameters
    ----------
    residual, prediction : ndarray, shape (L,)
        From :func:`leave_one_out`, over the analysis window (SI units).
    t_s : ndarray, shape (L,)
        Sample times, seconds.
    sigma_k : float
        Calibrated white-noise standard deviation of sensor k (SI).
    consensus_sigma : float
        Standard deviation of the consensus prediction error (SI).
    onset_range : (int, int)
        Onset candidates ``[lo, hi)`` (indices into the window); the fault is assumed to
        last from its onset to the end of the window.
    confidence : float
        Level of the size intervals.
    stuck_share : float
        Share of exactly repeated raw outputs after the onset that means "stuck".
    raw : ndarray, shape (L,), optional
        The sensor's own output (for "stuck": exact repeats); default ``residual +
        prediction``, which rounding may keep from repeating exactly.
    calibration_samples : int, optional
        Samples ``sigma_k`` was estimated from; the noise factor's interval then accounts
        for that estimate (F instead of chi-square).
    offset_var : float, optional
        Variance of the bias taken out of the residual (its calibration estimate); it is
        propagated into the step, drift and scale intervals (:func:`_linear_fit`).
    reference : Reference, optional
        The other sensors' residuals over the same window: the same estimators applied to
        them check the noise model, and widen the step, drift and scale intervals when the
        healthy sensors spread significantly more than it predicts.
    white : (float, float, float) or (float, float, float, (float, float, float)), optional
        ``(sigma_k, consensus_sigma, dof[, spread])``: the white-noise part of the
        calibrated noise (from successive differences, :func:`white_sigma`) and the
        degrees of freedom of that estimate; ``spread`` (:func:`white_sigma_spread`), when
        given, replaces ``dof`` by the calibration's actual degrees of freedom for this
        sensor's factor (:func:`_calibration_dof`). The noise factor is then sized from
        the successive differences of the residual (:func:`_noise_fit`), which slow
        motion-dependent errors (scale and misalignment under motion) and a shift of the
        consensus do not enter.

    Returns
    -------
    list of FaultFit
        Best first (stuck when detected, then by BIC).
    """
    r = np.asarray(residual, dtype=np.float64)
    o = np.asarray(prediction, dtype=np.float64)
    t = np.asarray(t_s, dtype=np.float64)
    options: dict[str, Any] = {
        "sigma_k": sigma_k,
        "consensus_sigma": consensus_sigma,
        "confidence": confidence,
        "stuck_share": stuck_share,
        "calibration_samples": calibration_samples,
        "offset_var": offset_var,
        "white": white,
    }
    raw_arr = r + o if raw is None else np.asarray(raw, dtype=np.float64)
    var0 = sigma_k**2 + consensus_sigma**2

    def fit_until(end: int, ref: Reference | None) -> list[FaultFit]:
        """The window's fits on its samples up to ``end`` (the fault's fitted end)."""
        return _fit_window(
            r[:end],
            o[:end],
            t[:end],
            raw_arr[:end],
            (onset_range[0], min(onset_range[1], end - 2)),
            ref,
            **options,
        )

    fits = _fit_window(r, o, t, raw_arr, onset_range, reference, **options)
    end = _fault_end(fits, r, var0)
    if end is None:
        return fits
    for _ in range(2):  # the end found by the best model on the whole window, refined once
        refined = _fault_end(fit_until(end, None), r[:end], var0)
        if refined is None or refined == end:
            break
        end = refined
    # the fault ended before the window did (the detector's alarms outlast it): refit on
    # the samples up to its end; the healthy tail adds the same to every model's -2 log L,
    # and the end is one more parameter of each fault model
    tail = float(2 * _gaussian_nll(float(np.sum(r[end:] ** 2)), float(r.shape[0] - end), var0))
    ln_n = math.log(r.shape[0])
    reference_cut = (
        None
        if reference is None
        else replace(
            reference,
            residuals=reference.residuals[:end],
            motion=None if reference.motion is None else reference.motion[:end],
        )
    )
    cut = fit_until(end, reference_cut)
    if not cut:
        return fits
    out = [
        replace(f, bic=f.bic + tail + ln_n, end_index=end)
        if f.model != "none"
        else replace(f, bic=f.bic + tail)
        for f in cut
    ]
    out.sort(key=lambda f: (f.bic, MODELS.index(f.model)))  # stuck (-inf) stays first
    return out


def _fault_end(fits: list[FaultFit], r: np.ndarray, var0: float) -> int | None:
    """Where the fault ends, when it ends clearly before the window does: by the best
    fitted model with a fitted curve (step, drift, noise, scale), the end maximises its
    log-likelihood ratio against the calibrated noise summed from the onset to the end
    (the samples after it are better explained as healthy). None when the best model is a
    frozen output (stuck: the repeats say where it ends), no model has a curve, or the end
    does not earn its BIC penalty."""
    if fits and fits[0].model == "stuck":
        return None
    best = next((f for f in fits if f.curve is not None), None)
    if best is None or best.curve is None or best.onset_index < 0:
        return None
    mean, variance = best.curve
    segment = r[best.onset_index : best.onset_index + mean.shape[0]]
    llr = -0.5 * ((segment - mean) ** 2 / variance + math.log(variance)) + 0.5 * (
        segment**2 / var0 + math.log(var0)
    )
    cumulative = np.cumsum(llr)
    j = int(np.argmax(cumulative))
    end = best.onset_index + j + 1
    # the end is one more parameter: it must earn its BIC penalty (ln n) in -2 log L
    gain = 2 * float(cumulative[j] - cumulative[-1])
    if end - best.onset_index < 4 or gain <= math.log(r.shape[0]):
        return None
    return end


def _fit_window(
    r: np.ndarray,
    o: np.ndarray,
    t: np.ndarray,
    raw: np.ndarray,
    onset_range: tuple[int, int],
    reference: Reference | None,
    *,
    sigma_k: float,
    consensus_sigma: float,
    confidence: float,
    stuck_share: float,
    calibration_samples: int | None,
    offset_var: float | None,
    white: WhiteNoise | None,
) -> list[FaultFit]:
    """:func:`fit_models` with every fault lasting to the window's end."""
    length = r.shape[0]
    lo, hi = max(0, int(onset_range[0])), min(length - 2, int(onset_range[1]))
    if length < 4 or hi <= lo:
        return []
    var0 = sigma_k**2 + consensus_sigma**2
    sigma_r = math.sqrt(var0)
    taus = np.arange(lo, hi)
    n_after = (length - taus).astype(np.float64)
    n_total = float(length)
    ln_n = math.log(n_total)

    # prefix: healthy samples before tau; suffix sums after tau
    sq = r**2
    healthy_before = np.concatenate(([0.0], np.cumsum(sq)))[taus]
    nll_before = _gaussian_nll(healthy_before, taus.astype(np.float64), var0)
    s_r, s_rr = _suffix(r)[taus], _suffix(sq)[taus]
    s_t, s_tt, s_tr = _suffix(t)[taus], _suffix(t * t)[taus], _suffix(t * r)[taus]
    s_oo, s_or = _suffix(o * o)[taus], _suffix(o * r)[taus]
    fits: list[FaultFit] = []

    def best(nll_after: np.ndarray, k_params: int) -> tuple[int, float]:
        total = nll_before + nll_after
        j = int(np.argmin(total))
        return j, float(2 * total[j] + (k_params + 1) * ln_n)  # +1: the onset

    linear: dict[str, Any] = {
        "var0": var0,
        "offset_var": offset_var or 0.0,
        "confidence": confidence,
        "reference": reference,
        "window": r,
    }

    # step: r = a + e
    a = s_r / n_after
    j, bic = best(_gaussian_nll(s_rr - n_after * a**2, n_after, var0), 1)
    onset = lo + j
    fits.append(_linear_fit("step", r[onset:], np.ones((length - onset, 1)), onset, bic, **linear))

    # drift: r = b (t - t_f) + e from an onset t_f between samples tau - 1 and tau, i.e.
    # r = b (u + lam) with u = t - t_tau and lam = t_tau - t_f in [0, dt]: the offset
    # lam is fitted per tau (interior least squares, else the better bound)
    drift = _drift_search(t, taus, n_after, s_r, s_rr, s_t, s_tt, s_tr, nll_before, var0, ln_n)
    if drift is not None:
        j, lam, bic = drift
        onset = lo + j
        u = t[onset:] - t[onset]
        X = np.stack([u, np.ones_like(u)], axis=1) if lam is None else (u + lam)[:, None]
        fits.append(_linear_fit("drift", r[onset:], X, onset, bic, **linear))

    # noise: r ~ N(0, f^2 sigma_k^2 + sigma_c^2); variance fitted (bounded below by var0).
    # The class is decided with a zero mean (a noise fault has none; a free mean would nest
    # the step model). The factor is sized from the spread about the mean: a fault on a
    # sensor of the consensus (another detector's, or one too small to alarm) shifts r,
    # and that shift is not noise.
    var_hat = np.maximum(s_rr / n_after, var0)
    j, bic = best(_gaussian_nll(s_rr, n_after, var_hat), 1)
    if white is None:
        fits.append(
            _noise_fit(
                float(max(s_rr[j] - n_after[j] * a[j] ** 2, 0.0)),
                int(n_after[j]),
                float(a[j]),
                sigma_k,
                consensus_sigma,
                confidence,
                lo + j,
                bic,
                calibration_samples,
                ranking_var=float(var_hat[j]),
            )
        )
    else:
        fits.append(
            _white_noise_fit(
                r[lo + j :], float(a[j]), white, confidence, lo + j, bic, var0, float(var_hat[j])
            )
        )

    # scale: r = beta o + e
    with np.errstate(divide="ignore", invalid="ignore"):
        beta = np.where(s_oo > 0, s_or / s_oo, 0.0)
    j, bic = best(_gaussian_nll(s_rr - beta * s_or, n_after, var0), 1)
    onset = lo + j
    if s_oo[j] > 0:
        fits.append(
            _linear_fit("scale", r[onset:], o[onset:, None], onset, bic, shift=1.0, **linear)
        )

    # none: the residual is the sensor's calibrated noise over the whole window (a false
    # alarm of chance: no fault model earns its extra parameters)
    nll_healthy = float(_gaussian_nll(np.sum(sq), n_total, var0))
    fits.append(FaultFit("none", math.nan, math.nan, math.nan, -1, 2 * nll_healthy))

    spikes = _spike_fit(r, t, sigma_r, taus, nll_before, ln_n, confidence)
    if spikes is not None:
        fits.append(spikes)
    fits.sort(key=lambda f: (f.bic, MODELS.index(f.model)))

    stuck = _stuck_fit(raw, lo, hi, stuck_share)
    if stuck is not None:
        fits.insert(0, stuck)
    return fits


def _median(values: np.ndarray) -> float:
    """``float(np.median(values))`` of a 1-D array, sorted directly (the middle value, or
    the mean of the middle two as numpy takes it: their sum halved); numpy's own for
    non-finite values."""
    n = values.shape[0]
    if n == 0 or not math.isfinite(float(np.add.reduce(values))):
        return float(np.median(values))
    ordered = np.sort(values)
    if n % 2:
        return float(ordered[n // 2])
    return (float(ordered[n // 2 - 1]) + float(ordered[n // 2])) / 2


def _drift_search(
    t: np.ndarray,
    taus: np.ndarray,
    n: np.ndarray,
    s_r: np.ndarray,
    s_rr: np.ndarray,
    s_t: np.ndarray,
    s_tt: np.ndarray,
    s_tr: np.ndarray,
    nll_before: np.ndarray,
    var0: float,
    ln_n: float,
) -> tuple[int, float | None, float] | None:
    """Onset of a ramp starting between two samples, by profile likelihood: returns the
    onset (index into ``taus``), the sub-sample offset ``lam`` (None: free, fitted as an
    intercept) and the BIC; None when no onset fits."""
    dt = _median(np.diff(t)) if t.shape[0] > 1 else 0.0
    t0 = t[taus]
    s_u = s_t - n * t0
    s_uu = s_tt - 2 * t0 * s_t + n * t0**2
    s_ur = s_tr - t0 * s_r
    det = n * s_uu - s_u**2
    with np.errstate(divide="ignore", invalid="ignore"):
        b_free = (n * s_ur - s_u * s_r) / det
        lam_free = (s_r - b_free * s_u) / n / b_free
    best: tuple[float, int, float | None] | None = None
    for lam in (None, 0.0, dt):
        if lam is None:
            b = b_free
            sse = s_rr - (s_r - b * s_u) / n * s_r - b * s_ur
            # a free offset is a sub-sample onset; at the window's first sample it may also
            # be a ramp already in progress (an episode that starts mid-fault, after an
            # earlier alarm episode of the same fault)
            in_progress = (taus == 0) & (det > 0)
            valid = ((det > 0) & (lam_free >= 0) & (lam_free <= dt)) | in_progress
        else:
            s_vv = s_uu + 2 * lam * s_u + n * lam**2
            s_vr = s_ur + lam * s_r
            with np.errstate(divide="ignore", invalid="ignore"):
                b = s_vr / s_vv
            sse = s_rr - b * s_vr
            valid = s_vv > 0
        total = np.where(valid, nll_before + _gaussian_nll(sse, n, var0), np.inf)
        j = int(np.argmin(total))
        if np.isfinite(total[j]) and (best is None or total[j] < best[0]):
            best = (float(total[j]), j, lam)
    if best is None:
        return None
    total_nll, j, lam = best
    return j, lam, 2 * total_nll + 3 * ln_n  # rate, offset, onset


@dataclass(frozen=True)
class Reference:
    """The other sensors over an episode's window: what the estimators give on sensors
    that are not faulty (:meth:`EpisodeBuilder` builds it).

    Attributes
    ----------
    residuals : ndarray, shape (L, m)
        Residual of each of m other sensors against the consensus of the sensors other than
        itself and the isolated one (a fault on the isolated sensor does not leak into
        them), with its calibrated bias taken out; SI.
    variance : ndarray, shape (m,)
        White-noise variance of each residual, sigma_j^2 + consensus variance (SI^2).
    offset_var : ndarray, shape (m,)
        Variance of the calibrated bias taken out of each (SI^2; zeros when none was).
    motion : ndarray, shape (L, 3), optional
        The consensus of the sensors other than the isolated one (x_hat_{-k}).
    """

    residuals: np.ndarray
    variance: np.ndarray
    offset_var: np.ndarray
    #: (L, 3) the consensus estimate of the sensed vector without the isolated sensor,
    #: less its calibration-window mean (SI), for the motion-dependent errors of
    #: :func:`_linear_fit`; None: not modelled
    motion: np.ndarray | None = None


#: level of the test that the healthy sensors spread more than the noise model says
DISPERSION_LEVEL = 0.95


def _linear_fit(
    model: str,
    y: np.ndarray,
    X: np.ndarray,
    onset: int,
    bic: float,
    *,
    var0: float,
    offset_var: float,
    confidence: float,
    reference: Reference | None,
    window: np.ndarray | None = None,
    shift: float = 0.0,
) -> FaultFit:
    """Least squares ``y = X c + e`` after the onset; the size is ``c[0] + shift``.

    The size is a linear estimate ``c0 = w^T y`` (w the first row of ``X^+``), and its
    variance is propagated from everything ``y`` carries:

    * the noise, ``s^2 sum_i sum_j w_i w_j rho_|i-j|``: s^2 = SSE / (n - p) from the fit's
      own residuals (outliers and a calibrated sigma that is off are in it) and rho their
      autocorrelation, Bartlett-weighted up to the Newey & West (1994) lag
      ``floor(4 (n/100)^(2/9))`` (:func:`_autocorrelation_factor`): coloured noise has
      fewer independent samples than it has samples;
    * the calibrated bias taken out of ``y`` (a constant with variance ``offset_var``):
      ``offset_var (sum_i w_i)^2`` (1 for a step, 0 when X has an intercept).

    With a ``reference``, the same ``w`` is applied to the m other sensors' residuals over
    the same samples. Under the white-noise model ``Q = sum_j est_j^2 / v_j`` (v_j their
    predicted variance, as above with their calibrated sigma) is chi-square with m degrees
    of freedom. Only when Q exceeds its ``DISPERSION_LEVEL`` quantile (the healthy sensors
    spread significantly more than white noise explains: bias wander since calibration,
    unmodelled motion) is the variance raised to ``Q / m`` times the white-noise variance of
    this sensor's estimate, with a t quantile on m degrees of freedom (a quasi-likelihood
    dispersion estimate, McCullagh & Nelder 1989 §4.5). The interval is the t interval
    ``c0 +- t_{(1 + confidence)/2} sqrt(var)``.
    """
    n, p = X.shape
    gram = X.T @ X  # p <= 2 columns: the normal equations are well within precision
    if not np.all(np.isfinite(gram)) or abs(float(np.linalg.det(gram))) <= 1e-300:
        return FaultFit(model, math.nan, -math.inf, math.inf, onset, bic)
    weights = np.linalg.solve(gram, X.T)  # (p, n): coef = weights @ y
    coef = weights @ y
    w = weights[0]
    size = float(coef[0]) + shift
    dof = n - p
    if dof < 1:
        return FaultFit(model, size, -math.inf, math.inf, onset, bic)
    e = y - X @ coef
    sw2, sw = float(w @ w), float(np.sum(w))
    quantile = _t_quantile(0.5 + confidence / 2, dof)
    extra: dict[str, float] = {}
    curve = (X @ coef, var0)
    widened = None
    if reference is not None and reference.residuals.shape[1] >= 2:
        dispersion, widened = _dispersion(w, reference, var0, offset_var, confidence)
        extra["dispersion"] = dispersion
        if window is not None and reference.motion is not None:
            # the motion-dependent errors: fitted when the healthy sensors spread too much
            # or the sensor's own residual carries them (partial F test, both at 95 %)
            pre = window[: window.shape[0] - n]
            motion = _motion_fit(
                window,
                X,
                onset,
                reference,
                var0,
                offset_var,
                confidence,
                sse_without=float(pre @ pre + e @ e),
                force=widened is not None,
            )
            if motion is not None:
                size, half, extra["motion_dispersion"] = motion
                size += shift
                return FaultFit(
                    model, size, size - half, size + half, onset, bic, extra, curve=curve
                )
    # (the noise variance is needed only without the motion fit)
    s2 = float(e @ e) / dof
    variance = s2 * _autocorrelation_factor(e, w) * sw2 + offset_var * sw**2
    if widened is not None and widened[0] > variance:
        variance, quantile = widened
    half = quantile * math.sqrt(max(variance, 0.0))
    return FaultFit(model, size, size - half, size + half, onset, bic, extra, curve=curve)


def _dispersion(
    w: np.ndarray, reference: Reference, var0: float, offset_var: float, confidence: float
) -> tuple[float, tuple[float, float] | None]:
    """The healthy sensors' check of the noise model for the linear estimate ``w^T r``
    over the window's last ``len(w)`` samples: their dispersion ``Q / m``, and the widened
    (variance, quantile) of this sensor's estimate when Q exceeds its DISPERSION_LEVEL
    chi-square quantile (None otherwise). See :func:`_linear_fit`."""
    n = w.shape[0]
    sw2, sw = float(w @ w), float(np.sum(w))
    estimates = w @ reference.residuals[-n:]
    predicted = reference.variance * sw2 + reference.offset_var * sw**2
    m = estimates.shape[0]
    q = float(np.sum(estimates**2 / predicted))
    if q <= _chi2_quantile(DISPERSION_LEVEL, m):
        return q / m, None
    white = q / m * (var0 * sw2 + offset_var * sw**2)
    return q / m, (white, _t_quantile(0.5 + confidence / 2, m))


def _motion_fit(
    r: np.ndarray,
    X: np.ndarray,
    onset: int,
    reference: Reference,
    var0: float,
    offset_var: float,
    confidence: float,
    *,
    sse_without: float,
    force: bool,
) -> tuple[float, float, float] | None:
    """The size with the motion-dependent errors of the residual fitted alongside.

    Scale-factor and misalignment errors of the sensor and of the consensus make the
    residual carry ``c^T omega(t)``, linear in the sensed vector; the healthy sensors
    then spread beyond white noise (the dispersion test of :func:`_linear_fit`), each
    with its own c. Over the whole window (the margin before the onset identifies c) the
    model is ``r = X_f c_f + M c + e``, with the fault columns ``X_f`` zero before the
    onset and ``M`` the consensus estimate of the sensed vector less its mean over the
    calibration window (``reference.motion``: the calibrated offset taken out of r holds
    ``c^T`` times that mean).
    The size is ``w^T r`` with w the fault row of the least-squares pseudo-inverse, which
    is orthogonal to M: every sensor's motion error drops out of its estimate, the healthy
    sensors' too. Its variance and the healthy sensors' check follow :func:`_linear_fit`
    (noise with its autocorrelation, the calibrated bias, widening by their dispersion
    only if it is still significant). It is used when ``force`` (the healthy sensors
    spread too much without it) or when M explains the sensor's own residual
    significantly (partial F test at DISPERSION_LEVEL against ``sse_without``, the sum of
    squares of the margin and the fault model's residuals). Returns (size without shift,
    half-width, the healthy sensors' dispersion), or None when it is not used or M adds
    nothing the fault columns do not already span (a constant rate)."""
    assert reference.motion is not None
    length = r.shape[0]
    M = reference.motion[:length]
    dof = length - X.shape[1] - M.shape[1]
    if dof < 2:
        return None
    full = np.zeros((length, X.shape[1]))
    full[onset:] = X
    design = np.concatenate([full, M], axis=1)
    scale = np.linalg.norm(design, axis=0)
    if not np.all(np.isfinite(design)) or np.any(scale <= 0):
        return None
    normalised = design / scale
    u, singular, vt = np.linalg.svd(normalised, full_matrices=False)  # pinv's own
    if abs(singular[-1] - 1e-6 * singular[0]) <= 1e-10 * singular[0]:
        # at the cut itself, decide on the singular values computed alone (with the
        # vectors their last bits may differ; both are within about 1e-15 of singular[0])
        alone = np.linalg.svd(normalised, compute_uv=False)
        if alone[-1] <= 1e-6 * alone[0]:
            return None
    elif singular[-1] <= 1e-6 * singular[0]:
        return None
    pinv = _pinv_from_svd(u, singular, vt) / scale[:, None]  # (p + 3, L)
    w = pinv[0]
    coef = pinv @ r
    e = r - design @ coef
    sse = float(e @ e)
    # partial F test of the motion columns against the fit without them (``sse_without``:
    # the healthy margin and the fault model's residuals)
    f_stat = (sse_without - sse) / M.shape[1] / (sse / dof) if sse > 0 else math.inf
    if not force and f_stat <= _f_quantile(DISPERSION_LEVEL, M.shape[1], dof):
        return None
    sw2, sw = float(w @ w), float(np.sum(w))
    variance = float(e @ e) / dof * _autocorrelation_factor(e, w) * sw2 + offset_var * sw**2
    quantile = _t_quantile(0.5 + confidence / 2, dof)
    dispersion, widened = _dispersion(w, reference, var0, offset_var, confidence)
    if widened is not None and widened[0] > variance:
        variance, quantile = widened
    return float(coef[0]), quantile * math.sqrt(max(variance, 0.0)), dispersion


def _pinv_from_svd(u: np.ndarray, singular: np.ndarray, vt: np.ndarray) -> np.ndarray:
    """``numpy.linalg.pinv(a)`` (default cut-off) from ``svd(a, full_matrices=False)``:
    the same operations on the same factors, so the same floats (checked against numpy in
    tests/test_episodes.py), without a second decomposition.

    Parameters
    ----------
    u : ndarray, shape (L, k)
    singular : ndarray, shape (k,)
    vt : ndarray, shape (k, k)

    Returns
    -------
    ndarray, shape (k, L)
    """
    large = singular > 1e-15 * np.max(singular)
    inverse = np.divide(1, singular, where=large, out=singular.copy())
    inverse[~large] = 0
    return np.matmul(np.transpose(vt), np.multiply(inverse[:, np.newaxis], np.transpose(u)))


def _autocorrelation_factor(e: np.ndarray, w: np.ndarray) -> float:
    """``Var(w^T e) / (s^2 w^T w)`` for a stationary e: ``1 + 2 sum_k kappa_k rho_k
    sum_i w_i w_{i+k} / w^T w`` with the sample autocorrelation rho_k of ``e`` and Bartlett
    weights ``kappa_k = 1 - k / (L + 1)`` up to ``L = floor(4 (n/100)^(2/9))`` (Newey &
    West 1994), which keep it non-negative; 1 for white noise (up to its sampling error,
    about ``2 sqrt(L / 3 n)``). Floored at 0.1."""
    n = e.shape[0]
    lags = min(n - 2, int(4 * (n / 100) ** (2 / 9)))
    e0 = e - np.add.reduce(e) / n  # e.mean(), without its Python overhead
    c0 = float(e0 @ e0)
    sw2 = float(w @ w)
    if lags < 1 or c0 <= 0 or sw2 <= 0:
        return 1.0
    total = 1.0
    for k in range(1, lags + 1):
        rho = float(e0[:-k] @ e0[k:]) / c0
        total += 2 * (1 - k / (lags + 1)) * rho * float(w[:-k] @ w[k:]) / sw2
    return max(total, 0.1)


def _noise_fit(
    ss: float,
    n: int,
    mean: float,
    sigma_k: float,
    consensus_sigma: float,
    confidence: float,
    onset: int,
    bic: float,
    calibration_samples: int | None = None,
    ranking_var: float | None = None,
) -> FaultFit:
    """Noise factor f with Var r = f^2 sigma_k^2 + sigma_c^2 from the sum of squares ``ss``
    of n residuals about their mean: ss / Var r is chi-square with n - 1 degrees of freedom,
    and with sigma_k estimated from ``calibration_samples`` the variance ratio is F(n - 1,
    n_cal) distributed; the interval is that of Var r mapped through f."""

    def factor(var: float) -> float:
        return math.sqrt(max(var - consensus_sigma**2, 0.0)) / sigma_k

    tail = (1 - confidence) / 2
    dof = max(n - 1, 1)
    var_hat = ss / dof
    if calibration_samples:
        low = factor(var_hat / _f_quantile(1 - tail, dof, calibration_samples))
        high = factor(var_hat / _f_quantile(tail, dof, calibration_samples))
    else:
        low = factor(ss / _chi2_quantile(1 - tail, dof))
        high = factor(ss / _chi2_quantile(tail, dof))
    # the model the class was ranked with: zero mean, variance ranking_var
    var0 = sigma_k**2 + consensus_sigma**2
    curve = (np.zeros(n), max(var0, ranking_var if ranking_var is not None else ss / n))
    extra = {"mean": mean}
    return FaultFit("noise", factor(var_hat), low, high, onset, bic, extra, curve=curve)


def successive_difference_dof(n: int) -> float:
    """Degrees of freedom of the successive-difference variance estimate of n white samples.

    ``q = sum_i (e_{i+1} - e_i)^2 / 2`` has mean ``(n - 1) sigma^2`` and variance
    ``(3 n - 4) sigma^4`` (neighbouring differences correlate with -1/2; von Neumann
    1941); a scaled chi-square with the same two moments has ``nu = 2 (n - 1)^2 / (3 n -
    4)`` degrees of freedom (Satterthwaite 1946), about 2 n / 3.
    """
    return 2.0 * (n - 1) ** 2 / max(3 * n - 4, 1)


def _calibration_dof(
    var_hat: float,
    sigma_k: float,
    consensus_sigma: float,
    spread: tuple[float, float, float],
    default: float,
) -> float:
    """Degrees of freedom of the calibration's part of the noise factor's F interval.

    The factor is ``f^2 = (v - c^2) / s_k`` with ``s = sigma_hat^2`` the white variances
    of the calibration (``c^2 = sum_j g_j^2 s_j`` the consensus's) and v the episode's.
    Their errors enter ``log f^2`` with the gradient ``-(g^2 / (v - c^2) + e_k / s_k)``,
    so the calibration adds ``kappa = A / u^2 + 2 B / (u s_k) + D / s_k^2`` to its
    variance (``u = v - c^2``; A, B, D from :func:`white_sigma_spread`). F(nu, nu_cal)
    puts ``a^2 2 / nu_cal`` there (``a = v / u``: the interval is mapped through
    ``v -> sqrt(v - c^2)``), so ``nu_cal = 2 a^2 / kappa`` matches the second moment
    (Satterthwaite 1946). Two things make it differ from the successive-difference
    dof of n_cal samples: each sensor's variance is solved from parity residuals that
    carry the other sensors' noise (non-negative least squares in :func:`white_sigma`:
    1.14 times the variance for 16 co-aligned IMUs), and the consensus's variance, taken
    off, errs with the other sensors' estimates (negatively correlated with sensor k's
    when few sensors share the residuals: the errors partly cancel). ``default`` when
    ``v <= c^2`` or the spread is degenerate.
    """
    a_term, b_term, d_term = spread
    u = var_hat - consensus_sigma**2
    if u <= 0 or sigma_k <= 0:
        return default
    s_k = sigma_k**2
    kappa = a_term / u**2 + 2 * b_term / (u * s_k) + d_term / s_k**2
    if not math.isfinite(kappa) or kappa <= 0:
        return default
    return max(2 * (var_hat / u) ** 2 / kappa, 1.0)


def _white_noise_fit(
    r: np.ndarray,
    mean: float,
    white: WhiteNoise,
    confidence: float,
    onset: int,
    bic: float,
    var0: float,
    ranking_var: float,
) -> FaultFit:
    """Noise factor from the successive differences of the residual after the onset.

    The white part of ``Var r`` is ``f^2 sigma_k^2 + sigma_c^2`` (``white`` holds sigma_k,
    sigma_c, the degrees of freedom of their calibration estimate and optionally its
    spread). Its estimate ``q / (n - 1)`` with ``q = sum (r_{i+1} - r_i)^2 / 2`` (von
    Neumann 1941) leaves out what varies slowly: motion-dependent scale and misalignment
    errors (at 0.5 Hz a sample step of 0.01 s changes them by 3 %) and a shift of the
    consensus. Against the calibration's white variance, estimated the same way, the ratio
    is F(nu, nu_cal) distributed, nu from :func:`successive_difference_dof` and nu_cal from
    :func:`_calibration_dof` (the calibration estimate's actual spread) when ``white``
    carries it; the interval is that of the variance mapped through f.
    """
    sigma_k, consensus_sigma, dof_cal = white[0], white[1], white[2]
    n = r.shape[0]
    if n < 3 or sigma_k <= 0:
        return FaultFit("noise", math.nan, -math.inf, math.inf, onset, bic, {"mean": mean})

    def factor(var: float) -> float:
        return math.sqrt(max(var - consensus_sigma**2, 0.0)) / sigma_k

    var_hat = float(np.sum(np.diff(r) ** 2)) / (2 * (n - 1))
    dof = successive_difference_dof(n)
    extra: dict[str, Any] = {"mean": mean}
    if len(white) == 4:
        dof_cal = _calibration_dof(var_hat, sigma_k, consensus_sigma, white[3], dof_cal)
        extra["calibration_dof"] = dof_cal
    tail = (1 - confidence) / 2
    low = factor(var_hat / _f_quantile(1 - tail, dof, dof_cal))
    high = factor(var_hat / _f_quantile(tail, dof, dof_cal))
    curve = (np.zeros(n), max(var0, ranking_var))
    return FaultFit("noise", factor(var_hat), low, high, onset, bic, extra, curve=curve)


def _local_level(r: np.ndarray) -> np.ndarray:
    """Running median of five samples (two each side; fewer at the ends): the residual's
    slowly varying level, which single-sample spikes do not move (one or two of five)."""
    n = r.shape[0]
    if n >= 5 and math.isfinite(float(np.sum(r))):
        # every value finite (a sum is finite only then, or on overflow, which takes the
        # general path below): the median of five is one of them, chosen by a min/max
        # selection network (exact); the four ends from their three or four values, the
        # mean of the middle two of four as numpy's median takes it
        a, b, c, d, e = r[:-4], r[1:-3], r[2:-2], r[3:-1], r[4:]
        low = np.maximum(np.minimum(a, b), np.minimum(c, d))
        high = np.minimum(np.maximum(a, b), np.maximum(c, d))
        level = np.empty(n)
        level[2:-2] = np.maximum(np.minimum(e, low), np.minimum(np.maximum(e, low), high))
        head, tail = r[:4].tolist(), r[-4:].tolist()
        first, second = sorted(head[:3]), sorted(head)
        last, before_last = sorted(tail[1:]), sorted(tail)
        level[0], level[-1] = first[1], last[1]
        level[1] = (second[1] + second[2]) / 2
        level[-2] = (before_last[1] + before_last[2]) / 2
        return level
    padded = np.concatenate((np.full(2, np.nan), r, np.full(2, np.nan)))
    window = np.stack([padded[i : i + n] for i in range(5)])
    level = np.zeros(n)
    if n >= 5:  # full windows: a plain median (nanmedian is ten times slower)
        level[2:-2] = np.median(np.lib.stride_tricks.sliding_window_view(r, 5), axis=1)
    edges = np.flatnonzero(np.isnan(window).any(axis=0) | ~np.isfinite(level))
    if edges.size:
        with np.errstate(all="ignore"):
            level[edges] = np.nanmedian(window[:, edges], axis=0)
    return np.where(np.isfinite(level), level, 0.0)


def _spike_fit(
    r: np.ndarray,
    t: np.ndarray,
    sigma_r: float,
    taus: np.ndarray,
    nll_before: np.ndarray,
    ln_n: float,
    confidence: float,
) -> FaultFit | None:
    """Sparse spikes: samples further than SPIKE_CUT sigma_r from their local level (a
    running median of five, :func:`_local_level`: slow motion-dependent errors of the
    residual are not spikes), the amplitude as their mean absolute residual (the
    local level itself is biased towards a neighbouring spike), and the Poisson rate. The quiet samples have a variance of their own, bounded below by the
    calibrated one (one more parameter): under motion the residual carries scale and
    misalignment errors, which would otherwise be charged to the spike model and make the
    noise model win; so do the spikes' distances from amp."""
    d = r - _local_level(r)
    flagged = np.abs(d) > SPIKE_CUT * sigma_r
    count_after = _suffix(flagged.astype(np.float64))[taus]
    if count_after.max(initial=0.0) < 1:
        return None
    abs_after = _suffix(np.where(flagged, np.abs(r), 0.0))[taus]
    sq_quiet_after = _suffix(np.where(flagged, 0.0, r**2))[taus]
    n_after = (r.shape[0] - taus).astype(np.float64)
    n_quiet = np.maximum(n_after - count_after, 1.0)
    p = np.clip(count_after / n_after, 1e-12, 1 - 1e-12)
    amp = np.where(count_after > 0, abs_after / np.maximum(count_after, 1), 0.0)
    sq_spikes_after = _suffix(np.where(flagged, r**2, 0.0))[taus]
    # spikes about +-amp, quiet samples about 0, each group with its
    # own variance (at least sigma_r^2: two spikes within two samples, or one at the
    # window's edge, move the local level); mixture weights p
    ss_spikes = np.maximum(sq_spikes_after - count_after * amp**2, 0.0)
    var_quiet = np.maximum(sq_quiet_after / n_quiet, sigma_r**2)
    var_spikes = np.maximum(ss_spikes / np.maximum(count_after, 1.0), sigma_r**2)
    nll_after = (
        _gaussian_nll(sq_quiet_after, n_after - count_after, var_quiet)
        + _gaussian_nll(ss_spikes, count_after, var_spikes)
        - (count_after * np.log(p / 2) + (n_after - count_after) * np.log(1 - p))
    )
    total = nll_before + nll_after
    j = int(np.argmin(total))
    bic = float(2 * total[j] + 5 * ln_n)  # amplitude, rate, two variances, onset
    onset = int(taus[j])
    spikes = np.abs(r[onset:][flagged[onset:]])
    m = spikes.shape[0]
    tail = (1 - confidence) / 2
    if m >= 2:
        se = float(spikes.std(ddof=1)) / math.sqrt(m)
        q = _t_quantile(1 - tail, m - 1)
        low, high = float(spikes.mean() - q * se), float(spikes.mean() + q * se)
    else:
        low, high = -math.inf, math.inf
    duration = float(t[-1] - t[onset]) + (float(t[1] - t[0]) if t.shape[0] > 1 else 0.0)
    rate_low = 0.5 * _chi2_quantile(tail, 2 * m) / duration if m > 0 else 0.0
    rate_high = 0.5 * _chi2_quantile(1 - tail, 2 * m + 2) / duration
    extra = {"rate_hz": m / duration, "rate_low_hz": rate_low, "rate_high_hz": rate_high}
    size = float(spikes.mean()) if m else math.nan
    return FaultFit("spikes", size, low, high, onset, bic, extra)


def _stuck_fit(raw: np.ndarray, lo: int, hi: int, share: float) -> FaultFit | None:
    """A frozen output: the longest run of exactly repeated raw values that starts in
    [lo - 1, hi) covers at least ``share`` of the samples from its start to the window's
    end. The onset is the first repeated sample (the frozen value is the one before it)."""
    repeat = np.concatenate(([False], np.diff(raw) == 0))
    if not repeat.any():
        return None  # (no run below)
    padded = np.concatenate(([False], repeat, [False]))
    edges = np.flatnonzero(np.diff(padded.astype(np.int8)))
    starts, stops = edges[0::2], edges[1::2]
    inside = (starts >= max(lo, 1)) & (starts < hi) & (stops - starts >= 3)
    if not inside.any():
        return None
    lengths = np.where(inside, stops - starts, 0)
    j = int(np.argmax(lengths))
    onset = int(starts[j])
    if lengths[j] < share * (raw.shape[0] - onset):
        return None
    value = float(raw[onset - 1])
    return FaultFit("stuck", value, value, value, onset, -math.inf)


# --- one explained episode ---------------------------------------------------------------


@dataclass
class Episode:
    """One alarm episode of one detector on one sensor type, explained.

    Times are nanoseconds (log time of the samples); ``fits`` are best first.
    """

    detector: str
    sensor_type: str
    start_ns: int
    end_ns: int
    decided_start_ns: int
    decided_end_ns: int
    alarms: int
    sensors: list[str]
    peak_ratio: float
    runner_up: str | None = None
    runner_up_share: float | None = None
    fits: list[FaultFit] = field(default_factory=list)
    isolated_by: str = "detector"
    invalid_samples: int = 0
    fragments: int = 1
    #: the detector's own amplitude estimate of ``sensors[0]`` (median over the episode's
    #: alarms isolating it, from the status' per-sensor amplitudes), SI; None (and no
    #: ``amplitude`` key in :meth:`to_dict`) when none
    amplitude: float | None = None

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) * 1e-9

    @property
    def fault_class(self) -> str | None:
        return self.fits[0].model if self.fits else None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (non-finite numbers become None)."""
        skip = {"fits"} | ({"amplitude"} if self.amplitude is None else set())
        out = _finite({k: v for k, v in vars(self).items() if k not in skip})
        out["duration_s"] = self.duration_s
        out["fault_class"] = self.fault_class
        out["fits"] = [f.to_dict() for f in self.fits]
        return out


def _sensor_amplitude(
    pairs: list[tuple[np.ndarray, np.ndarray]], sensor_ids: Sequence[str], names: list[str]
) -> float | None:
    """Median of the detector's amplitudes of the episode's sensor ``names[0]`` (``pairs``:
    (sensor index, amplitude) arrays of its alarms), or None."""
    if not names or not pairs:
        return None
    k = sensor_ids.index(names[0])
    values = np.concatenate([v[c == k] for c, v in pairs])
    return _median(values) if values.size else None


def isolation_summary(
    isolated: np.ndarray, sensor_ids: Sequence[str]
) -> tuple[list[str], str | None, float | None]:
    """Sensors isolated during an episode, most often first, and the runner-up's share.

    Parameters
    ----------
    isolated : ndarray, shape (M,), int
        Isolated index per alarmed row (negative: none).
    """
    valid = isolated[isolated >= 0]
    if valid.size == 0:
        return [], None, None
    counts = np.bincount(valid, minlength=len(sensor_ids))
    order = [int(i) for i in np.argsort(-counts, kind="stable") if counts[i] > 0]
    names = [sensor_ids[i] for i in order]
    if len(order) < 2:
        return names, None, 0.0
    return names, names[1], float(counts[order[1]] / valid.size)


# --- a detection of its own: the variance drop of a frozen output ------------------------

#: name under which variance-drop episodes are written (``detector`` field)
VARIANCE_DROP = "variance-drop"


@dataclass
class _Rows:
    """Status rows in the shape :meth:`EpisodeBuilder.rows` reads (a DetectionBlock's
    alarm, isolated, statistic and threshold)."""

    alarm: np.ndarray
    isolated: np.ndarray
    statistic: np.ndarray
    threshold: np.ndarray


class VarianceDropMonitor:
    """One-sided test that a sensor's white noise has dropped: a frozen (stuck) output.

    A frozen output on a motion the sensor would have tracked exactly (a constant-rate
    turntable) equals the truth plus its bias; only its noise is gone, so the mean-shift
    tests of the detectors cannot see it. Against the consensus of the others its
    residual ``r_k`` (:func:`leave_one_out`) then carries only the consensus noise. Over
    the last ``W`` successive differences, ``q_k = sum (r_{k,i+1} - r_{k,i})^2 / (2 W)``
    estimates the white variance of ``r_k`` (slow motion errors do not enter it) and is
    compared with its calibrated value ``v_k = sigma_k^2 + sigma_c^2`` (white parts,
    :func:`white_sigma`). Both are successive-difference estimates, so ``q_k / v_k`` is
    about F(nu_W, nu_cal) (:func:`successive_difference_dof`); the test alarms when the
    smallest ratio over the sensors falls below the F quantile at ``alpha``, and isolates
    that sensor. The test is one-sided: more noise, outliers and unmodelled motion only
    raise ``q_k``.

    The status row of a sample is decided at that sample (no look-ahead); ``statistic``
    is ``-ln(min ratio)`` and ``threshold`` ``-ln(quantile)`` (an alarm when statistic >
    threshold). Memory: the last W differences per sensor.

    Parameters
    ----------
    residual_matrix : ndarray, shape (n, n)
        ``measurements @ residual_matrix`` are the leave-one-out residuals of all sensors
        (column k: ``e_k - g_k``); sensors without a consensus have a zero column.
    white_variance : ndarray, shape (n,)
        Calibrated white variance of each residual, SI^2 (inf: never tested).
    window : int
        W, successive differences per test.
    alpha : float
        Probability that one healthy sensor's window falls below the threshold.
    calibration_dof : float
        Degrees of freedom of the white variance's calibration estimate.
    """

    def __init__(
        self,
        residual_matrix: np.ndarray,
        white_variance: np.ndarray,
        *,
        window: int,
        alpha: float,
        calibration_dof: float,
    ) -> None:
        self.A = np.asarray(residual_matrix, dtype=np.float64)
        self.variance = np.asarray(white_variance, dtype=np.float64)
        self.window = int(window)
        self.quantile = _f_quantile(
            alpha, successive_difference_dof(self.window + 1), calibration_dof
        )
        self._last: np.ndarray | None = None  # last residual row
        self._tail = np.zeros((0, self.A.shape[1]))  # last W half squared differences

    def update(self, measurements: np.ndarray) -> _Rows:
        """Status rows of the next N samples (N, n) in SI units."""
        r = np.asarray(measurements, dtype=np.float64) @ self.A
        n = r.shape[0]
        previous = r[:1] if self._last is None else self._last[None, :]
        half_sq = 0.5 * np.diff(np.concatenate([previous, r]), axis=0) ** 2
        if self._last is None and n:
            half_sq = half_sq[1:]  # the first sample has no difference
        # an invalid sample gives no evidence either way: its difference counts as expected
        half_sq = np.where(np.isfinite(half_sq), half_sq, self.variance)
        if n:
            self._last = r[-1]
        held, fresh = self._tail.shape[0], half_sq.shape[0]
        joined = np.concatenate([self._tail, half_sq])
        cumulative = np.concatenate([np.zeros((1, joined.shape[1])), np.cumsum(joined, axis=0)])
        stop = np.arange(held + 1, held + fresh + 1)  # window of the j-th new difference
        ready = stop >= self.window
        if held + 1 >= self.window:  # every window complete: the same rows as slices
            sums = (
                cumulative[held + 1 : held + fresh + 1]
                - cumulative[held + 1 - self.window : held + fresh + 1 - self.window]
            )
        else:
            sums = cumulative[stop] - cumulative[np.maximum(stop - self.window, 0)]
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = sums / self.window / self.variance
        ratio = np.where(np.isfinite(ratio), ratio, np.inf)
        worst = np.argmin(ratio, axis=1) if ratio.shape[0] else np.zeros(0, np.int64)
        lowest = ratio[np.arange(ratio.shape[0]), worst]
        alarm = ready & (lowest < self.quantile)
        statistic = np.where(ready, -np.log(np.maximum(lowest, 1e-300)), -np.inf)
        self._tail = joined[-self.window :]
        pad = n - half_sq.shape[0]  # the very first sample of the log: no test yet
        return _Rows(
            alarm=np.concatenate([np.zeros(pad, bool), alarm]),
            isolated=np.concatenate([np.full(pad, -1), np.where(alarm, worst, -1)]).astype(
                np.int64
            ),
            statistic=np.concatenate([np.full(pad, -np.inf), statistic]),
            threshold=np.full(n, -math.log(self.quantile)),
        )


# --- streaming: episodes of one detector on one sensor type, explained as they close ----


class EpisodeBuilder:
    """Builds explained episodes from a detector's status rows while a log streams by.

    The builder keeps the last ``margin`` samples of the sensor type's measurements (the
    fault usually starts before its first alarm: a drift is detected late) and, while an
    episode is open, its samples up to ``max_window``; an episode closes once ``merge_gap``
    quiet rows follow it, and is then explained (:func:`fit_models` on the isolated
    sensor). Memory is bounded by ``margin + max_window`` samples whatever the log length.

    Parameters
    ----------
    detector, sensor_type : str
    H : ndarray, shape (n, 3)
        Measurement matrix of the sensor type.
    sensor_ids : sequence of str, length n
    sigma : ndarray, shape (n,)
        Calibrated per-sensor white-noise standard deviation (SI), e.g. from
        :func:`imufdi_cli.detectors.parity.residual_sigma` on the calibration window.
    rate_hz : float
        Nominal sample rate.
    merge_gap_s, join_gap_s, margin_s, max_window_s : float
        Quiet time that does not end an episode; longer quiet time (at least
        ``merge_gap_s``) across which an alarm run that isolates the same sensor as the
        episode is joined to it as a fragment of the same fault; analysis margin before the
        first alarm (onset candidates); longest stretch of an episode kept for the fit.
    confidence : float
        Level of the size intervals.
    explain : bool
        Fit the fault models; False (too few sensors for a consensus, or no calibrated
        sigma) gives the episodes with their evidence but no fault class.
    calibration_samples : int, optional
        Samples ``sigma`` was estimated from (widens the noise factor's interval).
    calibration_mean : ndarray, shape (n,), optional
        Mean measurements of the calibration window: each sensor's bias against the
        consensus is taken out of its residual (a fault is what changed since).
    white_sigma : ndarray, shape (n,), optional
        The white part of each sensor's noise (:func:`white_sigma`, SI), estimated from
        ``calibration_samples`` samples; the noise factor is then sized against it from
        successive differences (:func:`_white_noise_fit`).
    white_excess : float
        How much more the white variances spread than Gaussian white noise says
        (:func:`white_sigma_excess`: outliers that pass the cut, heavy tails); it scales
        :func:`white_sigma_covariance` and so lowers the calibration's degrees of freedom
        in the noise factor's interval.
    variance_drop : bool
        Also run the :class:`VarianceDropMonitor` on the measurements and return its
        explained episodes (``detector`` :data:`VARIANCE_DROP`) with this builder's: a
        detection of its own, for frozen outputs the detectors cannot see. Needs
        ``white_sigma`` and ``calibration_samples``.
    variance_drop_window_s, variance_drop_alpha : float
        The monitor's window and the probability that one healthy sensor's window falls
        below its threshold.
    """

    def __init__(
        self,
        detector: str,
        sensor_type: str,
        H: np.ndarray,
        sensor_ids: Sequence[str],
        sigma: np.ndarray,
        rate_hz: float,
        *,
        merge_gap_s: float = 0.1,
        join_gap_s: float = 1.0,
        margin_s: float = 2.0,
        max_window_s: float = 30.0,
        confidence: float = 0.9,
        explain: bool = True,
        calibration_samples: int | None = None,
        calibration_mean: np.ndarray | None = None,
        white_sigma: np.ndarray | None = None,
        white_excess: float = 1.0,
        variance_drop: bool = False,
        variance_drop_window_s: float = 1.0,
        variance_drop_alpha: float = 1e-7,
    ) -> None:
        self.detector = detector
        self.sensor_type = sensor_type
        self.H = check_measurement_matrix(H)
        self.sensor_ids = list(sensor_ids)
        self.sigma = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (self.H.shape[0],))
        self.merge_gap = max(0, round(merge_gap_s * rate_hz))
        self.join_gap = max(self.merge_gap, round(join_gap_s * rate_hz))
        self.margin = max(2, round(margin_s * rate_hz))
        self.max_window = max(4, round(max_window_s * rate_hz))
        self.confidence = confidence
        self.explain = explain
        self.calibration_samples = calibration_samples
        self.calibration_mean = (
            None if calibration_mean is None else np.asarray(calibration_mean, np.float64)
        )
        # what another detector's builder is made from (for_detector)
        self._arguments = (sensor_type, H, sensor_ids, sigma, rate_hz)
        self._options: dict[str, Any] = {
            "merge_gap_s": merge_gap_s,
            "join_gap_s": join_gap_s,
            "margin_s": margin_s,
            "max_window_s": max_window_s,
            "confidence": confidence,
            "explain": explain,
            "calibration_samples": calibration_samples,
            "calibration_mean": calibration_mean,
            "white_sigma": white_sigma,
            "white_excess": white_excess,
            "variance_drop_window_s": variance_drop_window_s,
            "variance_drop_alpha": variance_drop_alpha,
        }
        self.white_sigma = (
            None
            if white_sigma is None
            else np.broadcast_to(np.asarray(white_sigma, np.float64), (self.H.shape[0],))
        )
        self._gains: dict[int, tuple[np.ndarray, float]] = {}
        self._references: dict[int, Any] = {}  # k -> _reference_matrix(k)
        self.white_excess = float(white_excess)
        self._white_cov: np.ndarray | None = None  # white_sigma_covariance, once
        self._estimators: dict[int, np.ndarray] = {}  # k -> _estimator(k)
        self._pending: list[np.ndarray] = []  # measurements fed but not yet paired with rows
        self._history: np.ndarray = np.zeros((0, self.H.shape[0]))  # last `margin` rows
        self._history_t: np.ndarray = np.zeros(0, np.int64)
        self._open: dict[str, Any] | None = None  # the alarm run under way
        self._waiting: dict[int, dict[str, Any]] = {}  # sensor -> episode awaiting fragments
        self._pos = 0
        self._monitor_issued = False  # for_detector: the first builder gets the monitor
        self._drop: tuple[VarianceDropMonitor, EpisodeBuilder] | None = None
        if variance_drop and self.white_sigma is not None and calibration_samples and explain:
            window = max(2, round(variance_drop_window_s * rate_hz))
            self._drop = (
                self._variance_monitor(window, variance_drop_alpha),
                EpisodeBuilder(VARIANCE_DROP, *self._arguments, **self._options),
            )

    # measurements arrive with the input blocks, rows when the detector emits them
    def feed(self, measurements: np.ndarray) -> None:
        """Measurements (N, n) of the next N input samples, SI."""
        self._pending.append(np.asarray(measurements, dtype=np.float64))

    def _take(self, count: int) -> np.ndarray:
        parts, need = [], count
        while need > 0:
            head = self._pending[0]
            if head.shape[0] <= need:
                parts.append(self._pending.pop(0))
                need -= head.shape[0]
            else:
                parts.append(head[:need])
                self._pending[0] = head[need:]
                need = 0
        return np.concatenate(parts) if parts else np.zeros((0, self.H.shape[0]))

    def rows(self, t_ns: np.ndarray, decided_ns: np.ndarray, out: Any) -> list[Episode]:
        """Status rows (a DetectionBlock ``out`` with sample and decision times, in order);
        returns the episodes that closed within them (ordered by their decision time)."""
        n = len(t_ns)
        t_ns = np.asarray(t_ns, dtype=np.int64)
        m = self._take(n)
        alarm = np.asarray(out.alarm, dtype=bool)
        isolated_rows = np.asarray(out.isolated)
        amplitudes = out.amplitude_set() if hasattr(out, "amplitude_set") else None
        idx = np.flatnonzero(alarm)
        groups = np.split(idx, np.flatnonzero(np.diff(idx) - 1 > self.merge_gap) + 1)
        closed: list[Episode] = []
        self._pos = 0  # next row of this block not yet appended to the open states
        for group in groups if idx.size else []:
            first, last = int(group[0]), int(group[-1])
            self._advance(m, t_ns, first, closed)
            state = self._open
            if state is not None and state["quiet"] > self.merge_gap:
                self._run_closed(state, closed)
                state = self._open = None
            if state is None:
                # only the last `margin` rows before the alarm are kept: copy no more
                tail = max(0, first - self.margin)
                history = np.concatenate([self._history, m[tail:first]])[-self.margin :]
                history_t = np.concatenate([self._history_t, t_ns[tail:first]])[-self.margin :]
                state = self._open = {
                    "start_ns": int(t_ns[first]),
                    "decided_start_ns": int(decided_ns[first]),
                    "window": [history],
                    "window_t": [history_t],
                    "kept": history.shape[0],
                    "alarm_index": history.shape[0],
                    "alarms": 0,
                    "isolated": [],
                    "amplitudes": [],  # (sensor, amplitude) of alarms with an estimate
                    "counts": np.zeros(len(self.sensor_ids), np.int64),
                    "fragments": 1,
                    "peak": -math.inf,
                    "quiet": 0,
                    # episodes this run may still join: they wait until it has ended
                    "may_join": set(self._waiting),
                }
            self._advance(m, t_ns, last + 1, closed, alarmed=True)
            group_isolated = isolated_rows[group]
            state["end_ns"] = int(t_ns[last])
            state["decided_end_ns"] = int(decided_ns[last])
            state["quiet"] = 0
            state["alarms"] += int(group.size)
            state["isolated"].append(group_isolated)
            if amplitudes is not None:
                found = np.nonzero(np.isfinite(amplitudes[group]))
                state["amplitudes"].append((found[1], amplitudes[group][found]))
            valid = group_isolated[(group_isolated >= 0) & (group_isolated < len(self.sensor_ids))]
            state["counts"] += np.bincount(valid, minlength=len(self.sensor_ids))
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.asarray(out.statistic)[group] / np.asarray(out.threshold)[group]
            ratio = ratio[np.isfinite(ratio)]
            if ratio.size:
                state["peak"] = max(state["peak"], float(ratio.max()))
        self._advance(m, t_ns, n, closed)
        state = self._open
        if state is not None and state["quiet"] > self.merge_gap:
            self._run_closed(state, closed)
            self._open = None
        tail = max(0, n - self.margin)
        self._history = np.concatenate([self._history, m[tail:]])[-self.margin :]
        self._history_t = np.concatenate([self._history_t, t_ns[tail:]])[-self.margin :]
        if self._drop is not None:
            monitor, builder = self._drop
            builder._gains, builder._references = self._gains, self._references
            builder.feed(m)
            closed.extend(builder.rows(t_ns, t_ns, monitor.update(m)))
        closed.sort(key=lambda e: e.decided_end_ns)
        return closed

    def _variance_monitor(self, window: int, alpha: float) -> VarianceDropMonitor:
        """The :class:`VarianceDropMonitor` of this sensor type (white sigma, leave-one-out
        gains of every sensor with a consensus)."""
        assert self.white_sigma is not None and self.calibration_samples
        n = self.H.shape[0]
        A = np.zeros((n, n))
        variance = np.full(n, np.inf)
        for k in range(n):
            try:
                gain, _ = self._gain(k)
            except ValueError:
                continue
            A[:, k] = -gain
            A[k, k] += 1.0
            variance[k] = self.white_sigma[k] ** 2 + float(np.sum((gain * self.white_sigma) ** 2))
        return VarianceDropMonitor(
            A,
            variance,
            window=window,
            alpha=alpha,
            calibration_dof=successive_difference_dof(self.calibration_samples),
        )

    def _advance(
        self,
        m: np.ndarray,
        t_ns: np.ndarray,
        stop: int,
        closed: list[Episode],
        alarmed: bool = False,
    ) -> None:
        """Append rows ``[pos, stop)`` of the block to the open run and to every episode
        waiting for a fragment; count them as quiet (unless they are the open run's
        alarms); explain the waiting episodes that have waited ``join_gap`` in vain."""
        lo = self._pos
        if stop <= lo:
            return
        self._pos = stop
        if self._open is not None:
            self._append(self._open, m, t_ns, lo, stop)
            if not alarmed:
                self._open["quiet"] += stop - lo
        held = set() if self._open is None else self._open["may_join"]
        for sensor, waiting in list(self._waiting.items()):
            self._append(waiting, m, t_ns, lo, stop)
            waiting["quiet"] += stop - lo
            if sensor not in held:
                self._expire(sensor, closed)

    def _expire(self, sensor: int, closed: list[Episode]) -> None:
        """Explain the episode waiting on ``sensor`` if it has waited ``join_gap`` in vain."""
        waiting = self._waiting[sensor]
        if waiting["quiet"] > self.join_gap:
            del self._waiting[sensor]
            closed.append(self._close(waiting))

    def _run_closed(self, run: dict[str, Any], closed: list[Episode]) -> None:
        """An alarm run has ended (``merge_gap`` quiet rows follow it). With an isolated
        sensor it joins that sensor's waiting episode when one ended at most ``join_gap``
        rows before it (the waiting episode already holds every row since), or starts to
        wait itself; without one it is explained at once."""
        if not run["counts"].any():
            closed.append(self._close(run))
            for other in list(self._waiting):  # no longer held by this run
                self._expire(other, closed)
            return
        sensor = int(np.argmax(run["counts"]))
        waiting = self._waiting.get(sensor)
        if waiting is not None:
            # the rows of the run, and its quiet rows since, are in the waiting window
            waiting["end_ns"] = run["end_ns"]
            waiting["decided_end_ns"] = run["decided_end_ns"]
            waiting["quiet"] = run["quiet"]
            waiting["alarms"] += run["alarms"]
            waiting["isolated"].extend(run["isolated"])
            waiting["amplitudes"].extend(run["amplitudes"])
            waiting["counts"] += run["counts"]
            waiting["fragments"] += run["fragments"]
            waiting["peak"] = max(waiting["peak"], run["peak"])
        else:
            self._waiting[sensor] = run
        for other in list(self._waiting):  # no longer held by this run
            self._expire(other, closed)

    def _append(
        self, state: dict[str, Any], m: np.ndarray, t_ns: np.ndarray, lo: int, hi: int
    ) -> None:
        hi = min(hi, lo + max(0, self.max_window - state["kept"]))
        if hi > lo:
            state["window"].append(m[lo:hi])
            state["window_t"].append(t_ns[lo:hi])
            state["kept"] += hi - lo

    def finish(self) -> list[Episode]:
        """The episodes still open or waiting at the end of the log, explained."""
        closed: list[Episode] = []
        if self._open is not None:
            self._run_closed(self._open, closed)
            self._open = None
        for waiting in self._waiting.values():
            closed.append(self._close(waiting))
        self._waiting.clear()
        if self._drop is not None:
            closed.extend(self._drop[1].finish())
        closed.sort(key=lambda e: e.decided_end_ns)
        return closed

    def _close(self, state: dict[str, Any]) -> Episode:
        window = np.concatenate(state["window"])
        window_t = np.concatenate(state["window_t"])
        # drop the quiet rows after the last alarm (they are not part of the fault)
        last = int(np.searchsorted(window_t, state["end_ns"], side="right"))
        window, window_t = window[:last], window_t[:last]
        isolated = np.concatenate([np.zeros(0, np.int64), *state["isolated"]]).astype(np.int64)
        names, runner_up, share = isolation_summary(isolated, self.sensor_ids)
        episode = Episode(
            detector=self.detector,
            sensor_type=self.sensor_type,
            start_ns=state["start_ns"],
            end_ns=state["end_ns"],
            decided_start_ns=state["decided_start_ns"],
            decided_end_ns=state["decided_end_ns"],
            alarms=state["alarms"],
            sensors=names,
            peak_ratio=state["peak"],
            runner_up=runner_up,
            runner_up_share=share,
            fragments=state["fragments"],
            amplitude=_sensor_amplitude(state["amplitudes"], self.sensor_ids, names),
        )
        if not self.explain or window.shape[0] < 4:
            return episode
        k = self.sensor_ids.index(names[0]) if names else self._loudest(window)
        if not names:
            episode.sensors = [self.sensor_ids[k]]
            episode.isolated_by = "residual"
        try:
            gain, consensus_sigma = self._gain(k)
        except ValueError:
            return episode
        prediction = window @ gain
        residual = window[:, k] - prediction
        offset_var = None
        if self.calibration_mean is not None:
            # the sensor's own bias against the consensus, as calibrated: a fault is what
            # changed since (its estimate's variance widens the step interval)
            residual = residual - (self.calibration_mean[k] - self.calibration_mean @ gain)
            if self.calibration_samples:
                offset_var = (self.sigma[k] ** 2 + consensus_sigma**2) / self.calibration_samples
        t_s = (window_t - window_t[0]).astype(np.float64) * 1e-9
        alarm_index = min(state["alarm_index"], max(len(window_t) - 2, 0))
        episode.fits = fit_models(
            residual,
            prediction,
            t_s,
            float(self.sigma[k]),
            consensus_sigma,
            # the onset may precede the first alarm (a drift is detected late) or follow
            # it (a chance alarm just before the fault merges into its episode)
            onset_range=(0, alarm_index + 1 + (len(window_t) - alarm_index) // 2),
            confidence=self.confidence,
            raw=window[:, k],
            calibration_samples=self.calibration_samples,
            offset_var=offset_var,
            reference=self._reference(k, window),
            white=self._white(k, gain),
        )
        return episode

    def _white(self, k: int, gain: np.ndarray) -> WhiteNoise | None:
        """(sigma_k, consensus sigma, dof, spread) of the white noise for
        :func:`fit_models` (spread: :func:`white_sigma_spread`, left out when the
        calibration's variances are not identifiable one by one)."""
        if self.white_sigma is None or not self.calibration_samples:
            return None
        consensus = float(np.sqrt(np.sum((gain * self.white_sigma) ** 2)))
        dof = successive_difference_dof(self.calibration_samples)
        if self._white_cov is None:
            self._white_cov = self.white_excess * white_sigma_covariance(
                self.H, self.white_sigma, self.calibration_samples
            )
        if self._white_cov.size == 0:
            return float(self.white_sigma[k]), consensus, dof
        spread = white_sigma_spread(self._white_cov, gain, k)
        return float(self.white_sigma[k]), consensus, dof, spread

    def _reference(self, k: int, window: np.ndarray) -> Reference | None:
        """The other sensors' residuals over ``window`` (:class:`Reference`), each against
        the consensus of the sensors other than itself and ``k``."""
        if k not in self._references:
            self._references[k] = self._reference_matrix(k)
        cached = self._references[k]
        if cached is None:
            return None
        A, offset, variance, offset_var = cached
        # the sensed vector relative to its calibration mean: the calibrated offsets taken
        # out of the residuals hold the motion errors of the calibration window too
        motion = window @ self._estimator(k)
        if self.calibration_mean is not None:
            motion = motion - self.calibration_mean @ self._estimator(k)
        return Reference(window @ A - offset, variance, offset_var, motion)

    def _reference_matrix(
        self, k: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """``A`` (n, m) with ``window @ A`` the residuals of the m sensors j != k whose
        leave-two-out consensus exists, their calibrated offsets, white variances and
        offset variances. All m consensuses at once from the information matrix
        ``M = H^T W H`` by downdating: ``M_{-jk} = M - h_k h_k^T / s_k^2 - h_j h_j^T / s_j^2``,
        gain ``g_{j,i} = h_j^T M_{-jk}^{-1} h_i / s_i^2`` (i not j, k) and consensus
        variance ``h_j^T M_{-jk}^{-1} h_j``."""
        H, sigma = self.H, np.asarray(self.sigma, dtype=np.float64)
        n = H.shape[0]
        weights = 1.0 / sigma**2
        outer = np.einsum("ia,ib->iab", H, H) * weights[:, None, None]
        others = np.flatnonzero(np.arange(n) != k)
        M = outer.sum(axis=0) - outer[k] - outer[others]  # (m, 3, 3)
        eig = np.linalg.eigvalsh(M)
        scale = float(np.max(np.linalg.eigvalsh(outer.sum(axis=0))))
        spans = eig[:, 0] > 1e-9 * scale
        others, M = others[spans], M[spans]
        if others.size < 2:
            return None
        solved = np.linalg.solve(M, H[others][:, :, None])[:, :, 0]  # M^-1 h_j, (m, 3)
        gains = (H @ solved.T) * weights[:, None]  # (n, m): g_{j,i} in column j
        gains[k] = 0.0
        gains[others, np.arange(others.size)] = 0.0
        consensus_var = np.einsum("ma,ma->m", H[others], solved)
        A = -gains
        A[others, np.arange(others.size)] += 1.0
        variance = sigma[others] ** 2 + consensus_var
        offset = np.zeros(others.size)
        offset_var = np.zeros(others.size)
        if self.calibration_mean is not None:
            offset = self.calibration_mean @ A
            if self.calibration_samples:
                offset_var = variance / self.calibration_samples
        return A, offset, variance, offset_var

    def _estimator(self, k: int) -> np.ndarray:
        """(n, 3) ``B`` with ``window @ B`` the weighted least-squares estimate of the
        sensed vector from the sensors other than k (cached)."""
        found = self._estimators.get(k)
        if found is None:
            H, sigma = self.H, np.asarray(self.sigma, dtype=np.float64)
            weights = 1.0 / sigma**2
            M = (H.T * weights) @ H - np.outer(H[k], H[k]) * weights[k]
            found = (H * weights[:, None]) @ np.linalg.inv(M)
            found[k] = 0.0
            self._estimators[k] = found
        return found

    def _gain(self, k: int) -> tuple[np.ndarray, float]:
        """:func:`_consensus_gain` of sensor k, from the information matrix downdated by k's
        own term (cached; one 3x3 solve instead of a pseudo-inverse)."""
        found = self._gains.get(k)
        if found is None:
            H, sigma = self.H, np.asarray(self.sigma, dtype=np.float64)
            weights = 1.0 / sigma**2
            M = (H.T * weights) @ H
            M_k = M - np.outer(H[k], H[k]) * weights[k]
            if float(np.linalg.eigvalsh(M_k)[0]) <= 1e-9 * float(np.linalg.eigvalsh(M)[-1]):
                raise ValueError(f"sensor {k}: the other sensors do not span 3 axes")
            solved = np.linalg.solve(M_k, H[k])
            gain = (H @ solved) * weights
            gain[k] = 0.0
            found = self._gains[k] = (gain, float(np.sqrt(H[k] @ solved)))
        return found

    def for_detector(self, detector: str) -> EpisodeBuilder:
        """A fresh builder with the same calibration, for another detector (it shares the
        consensus gains, which depend only on the calibration)."""
        # the variance-drop monitor is a detection of its own: one builder runs it
        monitor = not self._monitor_issued
        self._monitor_issued = True
        builder = EpisodeBuilder(detector, *self._arguments, **self._options, variance_drop=monitor)
        builder._gains = self._gains
        builder._references = self._references
        return builder

    def _loudest(self, window: np.ndarray) -> int:
        """For detectors that do not isolate: the sensor with the largest normalised
        leave-one-out residual energy over the episode."""
        energies = []
        for k in range(self.H.shape[0]):
            try:
                gain, c = self._gain(k)
            except ValueError:
                energies.append(-math.inf)
                continue
            r = window[:, k] - window @ gain
            energies.append(float(np.sum(r**2)) / (self.sigma[k] ** 2 + c**2))
        return int(np.argmax(energies))


def white_sigma(H: np.ndarray, measurements: np.ndarray) -> np.ndarray:
    """Per-sensor white-noise sigma from successive differences of a fault-free window.

    :func:`~imufdi_cli.detectors.parity.residual_sigma` of the differenced measurements,
    divided by sqrt(2): differencing white noise doubles its variance, and what varies
    slowly (motion-dependent scale and misalignment errors, bias wander) nearly vanishes,
    where the parity residuals of the measurements themselves carry it (on conical6, whose
    calibration window spans the start of the motion: 0.041 deg/s against a white 0.030).

    Parameters
    ----------
    H : array_like, shape (n, 3)
    measurements : array_like, shape (N, n), N >= 3, SI

    Returns
    -------
    ndarray, shape (n,), SI
    """
    from imufdi_cli.detectors.parity import residual_sigma

    m = np.asarray(measurements, dtype=np.float64)
    return residual_sigma(H, np.diff(m, axis=0)) / math.sqrt(2.0)


def white_sigma_covariance(H: np.ndarray, sigma: np.ndarray, n_samples: int) -> np.ndarray:
    """Covariance of the white variances :func:`white_sigma` estimates, SI^4.

    :func:`~imufdi_cli.detectors.parity.residual_sigma` solves ``M s = v`` for the
    variances s, ``M = (I - S)∘(I - S)``, v the variances of the parity residuals (here of
    the differenced samples, halved). For Gaussian white noise ``Cov(v) = 2/nu (C∘C)``
    with ``C = (I - S) diag(sigma^2) (I - S)^T`` (Isserlis) and nu the
    successive-difference degrees of freedom of n_samples (:func:`successive_difference_dof`),
    so ``Cov(s) = M^-1 Cov(v) M^-T`` (the same propagation as
    :func:`~imufdi_cli.detectors.parity.sigma_estimate_variance`, with nu for N - 1, and
    kept whole: the off-diagonal terms are what the consensus variance shares with
    sigma_k^2).

    Parameters
    ----------
    H : ndarray, shape (n, q)
    sigma : ndarray, shape (n,), SI
        The estimated white sigmas (plugged in for the true ones).
    n_samples : int
        Calibration samples.

    Returns
    -------
    ndarray, shape (n, n); shape (0, 0) without parity residuals, with fewer than 3
    samples, or when M is singular (e.g. six single-axis gyros on a cone: residual_sigma
    then returns one common sigma; its pooled degrees of freedom, about (n - q) times
    more, made conical6's intervals too narrow in the episodes, whose windows carry motion
    errors the calibration does not, so the successive-difference dof of n_samples stays).
    """
    H = np.asarray(H, dtype=np.float64)
    n, q = H.shape
    if n_samples < 3 or n <= q:
        return np.zeros((0, 0))
    projector = residual_projector(H)
    mixing = projector**2
    sig = np.asarray(sigma, dtype=np.float64)
    covariance = projector @ np.diag(sig**2) @ projector.T
    spread = 2.0 / successive_difference_dof(n_samples) * covariance**2  # Cov(v)
    singular = np.linalg.svd(mixing, compute_uv=False)
    if not singular[-1] > 1e-8 * singular[0]:
        return np.zeros((0, 0))
    inverse = np.linalg.inv(mixing)
    return inverse @ spread @ inverse.T


def white_sigma_excess(
    H: np.ndarray, measurements: np.ndarray, *, outlier_cut: float = 4.0
) -> float:
    """How much more the white variances of :func:`white_sigma` spread than Gaussian white
    noise says, measured on the calibration window itself (>= 1).

    :func:`white_sigma_covariance` assumes Gaussian white noise. The variances are
    ``s = M^-1 v`` (:func:`white_sigma_covariance`), v the means of ``x_t = r_t^2`` (the
    squared parity residuals of the differenced samples), so each ``s_k`` is the mean of
    the series ``z_t = (M^-1 x_t)_k``, whose mean has the variance ``(g0 + 2 g1) / N'``
    (autocovariances of z to lag 1: neighbouring differences correlate, the others do
    not). Under Gaussian white noise ``g0 + 2 g1 = 3 w^T (C∘C) w`` (w the row k of
    ``M^-1``, C the covariance of the differenced residuals; Isserlis, neighbouring
    differences correlating with -1/2). Outliers that pass the 4-sigma cut once
    differenced (each spreads over two differences, at 1/sqrt(2) of its size; on
    paper-table4 about a quarter of them) and heavy-tailed noise make the measured value
    larger. The factor is the measured over the Gaussian value, averaged over the sensors
    (one window then estimates it to a few per cent), times ``N_diff / N'`` for the rows
    the cut left out (the same cut as
    :func:`~imufdi_cli.detectors.parity.residual_sigma`); floored at 1, the Gaussian value.

    Parameters
    ----------
    H : array_like, shape (n, 3)
    measurements : array_like, shape (N, n), N >= 4, fault-free, SI

    Returns
    -------
    float
        1 for Gaussian white noise (up to its sampling error), more with outliers; 1 when
        the per-sensor variances are not identifiable (singular M) or too few samples.
    """
    from imufdi_cli.detectors.parity import residuals

    H = np.asarray(H, dtype=np.float64)
    m = np.asarray(measurements, dtype=np.float64)
    n, q = H.shape
    if m.ndim != 2 or m.shape[0] < 4 or n <= q:
        return 1.0
    projector = residual_projector(H)
    mixing = projector**2
    singular = np.linalg.svd(mixing, compute_uv=False)
    if not singular[-1] > 1e-8 * singular[0]:
        return 1.0
    inverse = np.linalg.inv(mixing)
    r = residuals(H, np.diff(m, axis=0))
    centre = np.median(r, axis=0)
    robust_std = 1.4826 * np.median(np.abs(r - centre), axis=0)
    inlier = np.all(np.abs(r - centre) <= outlier_cut * robust_std, axis=1)
    kept = r[inlier] if np.count_nonzero(inlier) >= max(2, r.shape[0] // 2) else r
    if kept.shape[0] < 3:
        return 1.0
    z = (kept**2) @ inverse.T  # (N', n): z_t,k has mean s_k (differenced: 2 sigma_k^2)
    variance = np.clip(z.mean(axis=0), 0.0, None)
    zc = z - z.mean(axis=0)
    measured = np.mean(zc**2, axis=0) + 2 * np.sum(zc[1:] * zc[:-1], axis=0) / z.shape[0]
    covariance = projector @ np.diag(variance) @ projector.T
    gaussian = 3 * np.einsum("ki,ij,kj->k", inverse, covariance**2, inverse)
    use = gaussian > 0
    if not np.any(use):
        return 1.0
    ratio = float(np.mean(measured[use] / gaussian[use]))
    factor = max(ratio, 1.0) * r.shape[0] / kept.shape[0]
    return factor if math.isfinite(factor) else 1.0


def white_sigma_spread(cov: np.ndarray, gain: np.ndarray, k: int) -> tuple[float, float, float]:
    """``(A, B, D)`` for :func:`_calibration_dof`: with ``g2 = gain^2`` (the consensus
    weights of sensor k, :func:`leave_one_out`) and ``cov`` from
    :func:`white_sigma_covariance`, ``A = g2^T cov g2`` (the consensus variance's),
    ``B = (cov g2)_k`` (shared with sigma_k^2) and ``D = cov_kk`` (sigma_k^2's), SI^4."""
    g2 = np.asarray(gain, dtype=np.float64) ** 2
    shared = cov @ g2
    return float(g2 @ shared), float(shared[k]), float(cov[k, k])


def episode_builders(calibration: Any, array: Any, **options: Any) -> dict[str, EpisodeBuilder]:
    """One builder per sensor type of ``array`` present in the calibration block (an
    :class:`~imufdi_cli.log.ImuBlock`), with per-sensor sigma from its parity residuals
    (:func:`~imufdi_cli.detectors.parity.residual_sigma`). Types with fewer than 4 sensors
    (no leave-one-out consensus) get episodes without explanation. Use
    :meth:`EpisodeBuilder.for_detector` to get each detector its own builder."""
    from imufdi_cli.detectors.parity import residual_sigma
    from imufdi_cli.errors import ArrayConfigError, CalibrationError

    builders = {}
    for sensor_type in array.sensor_types():
        triads = calibration.get(sensor_type)
        if triads is None:
            continue
        H = array.measurement_matrix(sensor_type)
        try:
            check_measurement_matrix(H)
        except ArrayConfigError:
            continue  # the detectors say what is wrong with such a geometry; no episodes
        explain = H.shape[0] >= 4
        sigma = np.ones(H.shape[0])
        n_cal: int | None = None
        mean: np.ndarray | None = None
        white: np.ndarray | None = None
        excess = 1.0
        if explain:
            measurements = array.select(triads, sensor_type)
            finite = np.all(np.isfinite(measurements), axis=1)
            n_cal = int(np.count_nonzero(finite))
            mean = measurements[finite].mean(axis=0) if n_cal else None
            try:
                sigma = residual_sigma(H, measurements[finite])
                white = white_sigma(H, measurements[finite])
                excess = white_sigma_excess(H, measurements[finite])
            except CalibrationError:
                explain = False
            explain = explain and bool(np.all(np.isfinite(sigma)) and np.all(sigma > 0))
        builders[sensor_type] = EpisodeBuilder(
            "",
            sensor_type,
            H,
            array.sensor_ids(sensor_type),
            sigma,
            array.rate_hz,
            explain=explain,
            calibration_samples=n_cal if explain else None,
            calibration_mean=mean if explain else None,
            white_sigma=white if explain else None,
            white_excess=excess,
            **options,
        )
    return builders


# --- scoring against injected truth -------------------------------------------------------

#: the fault parameter each model's size estimates (faults.py keys, SI)
TRUTH_SIZE_KEYS = {
    "step": "amp",
    "drift": "rate",
    "noise": "factor",
    "scale": "factor",
    "spikes": "amp",
}


def truth_size(fault: dict[str, Any]) -> float | None:
    """The size an explanation of ``fault`` (a :meth:`Fault.to_dict`) should find, or None
    (stuck, or a noise fault given by sigma without a factor)."""
    key = TRUTH_SIZE_KEYS.get(str(fault.get("model")))
    value = None if key is None else fault.get("params", {}).get(key)
    return None if value is None else float(value)


def match_episodes(
    episodes: Sequence[dict[str, Any]], faults: Sequence[dict[str, Any]]
) -> list[dict[str, Any]]:
    """Match each episode (:meth:`Episode.to_dict`) to the injected fault it explains.

    ``faults`` hold ``id``, ``model``, ``sensors``, ``params`` and absolute ``start_ns`` /
    ``end_ns`` (None: to the end of the log). An episode matches a fault when its first
    isolated sensor is one of the fault's sensors and its alarms overlap the fault's
    window; it is ``wrong_sensor`` when it overlaps a fault on another sensor of its type,
    and ``false`` otherwise. Returns one record per episode: ``{"match": "fault" |
    "wrong_sensor" | "false", "fault_id", "true_class", "class_right", "true_size",
    "covered"}``.
    """
    out = []
    for episode in episodes:
        sensors = episode.get("sensors") or []
        first = sensors[0] if sensors else None
        kind, hit = "false", None
        for fault in faults:
            end = fault.get("end_ns")
            overlaps = episode["end_ns"] >= fault["start_ns"] and (
                end is None or episode["start_ns"] < end
            )
            same_type = any(
                s.split(".")[1] == episode["sensor_type"] for s in fault.get("sensors", [])
            )
            if not overlaps or not same_type:
                continue
            if first in fault["sensors"]:
                kind, hit = "fault", fault
                break
            kind = "wrong_sensor"
        record: dict[str, Any] = {"match": kind, "fault_id": None if hit is None else hit["id"]}
        if hit is not None:
            fits = episode.get("fits") or []
            best = fits[0] if fits else {}
            size = truth_size(hit)
            record["true_class"] = hit["model"]
            record["class_right"] = best.get("model") == hit["model"]
            record["true_size"] = size
            low, high = best.get("low"), best.get("high")
            record["covered"] = (
                None
                if size is None or not record["class_right"] or low is None or high is None
                else bool(low <= size <= high)
            )
        out.append(record)
    return out


class EpisodeTally:
    """Streaming figures of one detector and sensor type's episodes (bounded memory)."""

    def __init__(self) -> None:
        self.episodes = 0
        self.matched = 0
        self.wrong_sensor = 0
        self.false = 0
        self.calibration = 0  # in the calibration window: in sample, not scored
        self.per_model: dict[str, dict[str, int]] = {}

    def add(self, match: dict[str, Any]) -> None:
        """Count one episode with its :func:`match_episodes` record."""
        self.episodes += 1
        if match["match"] == "false":
            self.false += 1
        elif match["match"] == "wrong_sensor":
            self.wrong_sensor += 1
        else:
            self.matched += 1
            row = self.per_model.setdefault(
                match["true_class"], {"episodes": 0, "class_right": 0, "sized": 0, "covered": 0}
            )
            row["episodes"] += 1
            row["class_right"] += bool(match["class_right"])
            if match["covered"] is not None:
                row["sized"] += 1
                row["covered"] += bool(match["covered"])

    def result(self, hours: float | None) -> dict[str, Any]:
        """Episodes, false episodes (per hour of ``hours`` of fault-free log), and for
        matched ones the share classified right and the share of size intervals covering
        the truth, overall and per true fault model (None when undefined)."""
        per_model = {}
        for model, row in sorted(self.per_model.items()):
            per_model[model] = {
                **row,
                "class_accuracy": row["class_right"] / row["episodes"],
                "coverage": row["covered"] / row["sized"] if row["sized"] else None,
            }
        right = sum(r["class_right"] for r in self.per_model.values())
        covered = sum(r["covered"] for r in self.per_model.values())
        sized = sum(r["sized"] for r in self.per_model.values())
        return {
            "episodes": self.episodes,
            "matched": self.matched,
            "wrong_sensor": self.wrong_sensor,
            "false": self.false,
            "in_calibration": self.calibration,
            "false_episodes_per_hour": self.false / hours if hours else None,
            "class_accuracy": right / self.matched if self.matched else None,
            "coverage": covered / sized if sized else None,
            "per_model": per_model,
        }


def score_episodes(matches: Sequence[dict[str, Any]], hours: float | None) -> dict[str, Any]:
    """:class:`EpisodeTally` figures of the :func:`match_episodes` records of a list."""
    tally = EpisodeTally()
    for match in matches:
        tally.add(match)
    return tally.result(hours)


__all__ = [
    "MODELS",
    "VARIANCE_DROP",
    "Episode",
    "EpisodeBuilder",
    "EpisodeTally",
    "FaultFit",
    "VarianceDropMonitor",
    "episode_builders",
    "find_episodes",
    "fit_models",
    "isolation_summary",
    "leave_one_out",
    "match_episodes",
    "score_episodes",
    "successive_difference_dof",
    "truth_size",
    "white_sigma",
    "white_sigma_covariance",
    "white_sigma_excess",
    "white_sigma_spread",
]
