"""The fits of the noise, spikes and stuck models (step, drift and scale are linear least
squares: :func:`~imufdi_cli.episodes.reference._linear_fit`).

The noise factor is sized from successive differences against the white part of the
calibrated noise (:func:`~imufdi_cli.episodes.white_noise.white_sigma`), F(nu, nu_cal)
(:func:`_white_noise_fit`): slow errors and shifts of the consensus do not enter it.
Spikes are samples far from the residual's local level and nearer the spikes' amplitude than 0
(:func:`_spike_set`, :func:`_spike_fit`); a frozen
output repeats its raw value exactly (:func:`_stuck_fit`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from imufdi_cli.episodes.fault_fit import FaultFit, WhiteNoise
from imufdi_cli.episodes.numerics import (
    _chi2_quantile,
    _f_quantile,
    _gaussian_nll,
    _suffixes,
    _t_quantile,
)
from imufdi_cli.episodes.white_noise import _calibration_dof, successive_difference_dof

#: residuals beyond this many sigma_r count as spikes
SPIKE_CUT = 4.0
#: at most this many passes of the spike set's amplitude consistency (:func:`_spike_set`)
SPIKE_SET_PASSES = 4
#: half-width of the running median of the quiet samples in :func:`_spike_set`
SPIKE_SET_HALF_WIDTH = 5


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

    var_hat = float(np.add.reduce((r[1:] - r[:-1]) ** 2)) / (2 * (n - 1))  # np.diff(r)
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
    if n >= 5 and math.isfinite(float(np.add.reduce(r))):
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


def _running_median(x: np.ndarray, half: int) -> np.ndarray:
    """Median of ``x[i - half : i + half + 1]`` (shape of x; fewer samples at the ends)."""
    n, width = x.shape[0], 2 * half + 1
    out = np.empty(n)
    if n >= width:  # an odd count: the median is the middle order statistic (numpy's too)
        windows = np.lib.stride_tricks.sliding_window_view(x, width)
        out[half : n - half] = np.partition(windows, half, axis=1)[:, half]
    # the end windows (fewer samples, x is finite here): at most 2 half of them, sorted as
    # Python floats; the middle value, or the middle two's sum halved (numpy's median)
    values = x.tolist()
    for i in (*range(min(half, n)), *range(max(n - half, half), n)):
        window = sorted(values[max(i - half, 0) : i + half + 1])
        count = len(window)
        out[i] = (window[(count - 1) // 2] + window[count // 2]) / 2
    return out


def _spike_set(r: np.ndarray, sigma_r: float) -> np.ndarray:
    """The spike samples of a residual: the SPIKE_CUT sigma_r cut against the running
    median of five, then made consistent with the spikes' amplitude.

    Parameters
    ----------
    r : ndarray, shape (n,)
        Residual of one sensor axis (rad/s or m/s^2).
    sigma_r : float
        Its calibrated standard deviation (same unit).

    Returns
    -------
    ndarray of bool, shape (n,)
        True at the spike samples.

    Notes
    -----
    The first set is the samples further than SPIKE_CUT sigma_r from
    :func:`_local_level`. The median of five misplaces two kinds of sample: a quiet one
    in the window's last two samples (a median of three or four, moved by a spike beside
    it), and the middle of three spikes of one sign within five samples (the median is
    then a spike, so it is not flagged). The set is then refined: the level is the
    running median of eleven taken over the *quiet* samples only, in their order (the
    set's samples take the level interpolated between their quiet neighbours; spikes
    the cut missed, even a run of three beside a fourth, are a minority of eleven; at
    5 % spikes six of eleven has probability 1e-5; over 0.1 s a motion error is close
    to linear, which a median follows), e = r - level, the amplitude A the
    median |e| over the set, and the new set is ``|e| > max(A / 2, SPIKE_CUT sigma_r)``:
    a flagged sample nearer 0 than A is quiet, an unflagged one nearer A than 0 is a
    spike.

    Why A / 2: a sample is either quiet, |e| about 0, or a spike, |e| about A, each with
    Gaussian spread. With equal variances sigma^2 and prior odds (1 - p) / p of quiet to
    spike, the likelihood-ratio (misclassification-minimising) boundary is
    A / 2 + sigma^2 ln((1 - p) / p) / A; it is the midpoint A / 2 for equal priors, and
    for the reference spikes (A = 3 deg/s, sigma 0.15 deg/s, p = 0.05) the prior term is
    0.02 deg/s, negligible against A / 2. The assumption is equal variances: the spikes'
    own spread (motion error at the spike) is of the order of sigma_r. With the classes
    apart by less than 2 SPIKE_CUT sigma_r (A <= 8 sigma_r: a noise-growth residual whose
    largest samples pass the cut), the midpoint falls inside the noise, so the cut stays
    and the first set is returned unchanged. paper-table4's gyro outliers (1 deg/s,
    about 6.5 sigma_r) pass the cut but lie below A / 2 = 1.5 deg/s beside the 3 deg/s
    reference spikes: they are left out, as they are not the fault's spikes.

    Passes: once the misplaced samples are moved, the quiet level holds no spike and A
    moves by a few per cent, so the second pass moves nothing when the classes are apart
    (the separated case above). The map is not a contraction in general (a sample near
    A / 2 can flip as A moves), so the passes stop at a fixed point or after
    SPIKE_SET_PASSES, and the last set is used.
    """
    return _refined_spike_set(r, np.abs(r - _local_level(r)) > SPIKE_CUT * sigma_r, sigma_r)


def _refined_spike_set(r: np.ndarray, spikes: np.ndarray, sigma_r: float) -> np.ndarray:
    """:func:`_spike_set` from its first set ``spikes`` (the cut against the running
    median of five, bool of r's shape): the set made consistent with the amplitude."""
    if not spikes.any() or not math.isfinite(float(np.add.reduce(r))):
        return spikes
    index = np.arange(r.shape[0])
    cut = SPIKE_CUT * sigma_r
    for _ in range(SPIKE_SET_PASSES):
        quiet = ~spikes
        if not quiet.any():
            break
        # the running median of eleven over the quiet samples in sequence, between
        # them interpolated (a run of spikes the cut missed is a minority of eleven)
        level = _running_median(r[quiet], SPIKE_SET_HALF_WIDTH)
        e = np.abs(r - np.interp(index, index[quiet], level))
        amp = float(np.median(e[spikes]))
        if amp <= 2 * cut:
            break  # the classes overlap: the cut decides
        refined = e > amp / 2
        if np.array_equal(refined, spikes):
            break
        spikes = refined
    return spikes


def _spike_fit(
    r: np.ndarray,
    t: np.ndarray,
    sigma_r: float,
    taus: np.ndarray,
    nll_before: np.ndarray,
    ln_n: float,
    confidence: float,
    sized: np.ndarray | None = None,
) -> FaultFit | None:
    """Sparse spikes: samples further than SPIKE_CUT sigma_r from their local level (a
    running median of five, :func:`_local_level`: slow motion-dependent errors of the
    residual are not spikes) and consistent with the spikes' amplitude (nearer it than 0,
    :func:`_spike_set`; the set is decided once over the window), the amplitude as their mean absolute residual (the
    local level itself is biased towards a neighbouring spike), and the Poisson rate. The quiet samples have a variance of their own, bounded below by the
    calibrated one (one more parameter): under motion the residual carries scale and
    misalignment errors, which would otherwise be charged to the spike model and make the
    noise model win; so do the spikes' distances from amp.

    ``sized`` (shape of r, default r) is the residual the amplitude and its interval are
    taken from, at the samples flagged in r: :func:`~imufdi_cli.episodes.fits.fit_models`
    ranks the model on r less the motion nuisance and sizes it on the residual itself
    (with random signs, the motion error at the spikes averages out of the mean of |r|,
    and the interval's spread carries it)."""
    flagged = _spike_set(r, sigma_r)
    # no flagged sample from the first candidate onset on: every count after is 0 (sums of
    # zeros and ones are exact), so no onset has a spike after it
    if taus.shape[0] == 0 or not flagged[int(taus.min()) :].any():
        return None
    # the four suffix sums in one accumulation (row by row the same floats as one each)
    sq = r * r
    series = np.zeros((4, r.shape[0]))
    series[0] = flagged
    np.abs(r, out=series[1], where=flagged)
    np.copyto(series[2], sq, where=~flagged)
    np.copyto(series[3], sq, where=flagged)
    count_after, abs_after, sq_quiet_after, sq_spikes_after = _suffixes(series, 0, r.shape[0])[
        :, taus
    ]
    n_after = (r.shape[0] - taus).astype(np.float64)
    n_quiet = np.maximum(n_after - count_after, 1.0)
    p = (count_after / n_after).clip(1e-12, 1 - 1e-12)
    amp = np.where(count_after > 0, abs_after / np.maximum(count_after, 1), 0.0)
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
    j = int(total.argmin())
    bic = float(2 * total[j] + 5 * ln_n)  # amplitude, rate, two variances, onset
    onset = int(taus[j])
    spikes = np.abs((r if sized is None else sized)[onset:][flagged[onset:]])
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
    j = int(lengths.argmax())
    onset = int(starts[j])
    if lengths[j] < share * (raw.shape[0] - onset):
        return None
    value = float(raw[onset - 1])
    return FaultFit("stuck", value, value, value, onset, -math.inf)
