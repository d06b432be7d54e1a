"""The fits of the noise, spikes and stuck models (step, drift and scale are linear least
squares: :func:`~imufdi_cli.episodes.reference._linear_fit`).

The noise factor is sized from successive differences against the white part of the
calibrated noise (:func:`~imufdi_cli.episodes.white_noise.white_sigma`), F(nu, nu_cal)
(:func:`_white_noise_fit`): slow errors and shifts of the consensus do not enter it.
Spikes are samples far from the residual's local level (:func:`_spike_fit`); a frozen
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
    _suffix,
    _t_quantile,
)
from imufdi_cli.episodes.white_noise import _calibration_dof, successive_difference_dof

#: residuals beyond this many sigma_r count as spikes
SPIKE_CUT = 4.0


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
    sized: np.ndarray | None = None,
) -> FaultFit | None:
    """Sparse spikes: samples further than SPIKE_CUT sigma_r from their local level (a
    running median of five, :func:`_local_level`: slow motion-dependent errors of the
    residual are not spikes), the amplitude as their mean absolute residual (the
    local level itself is biased towards a neighbouring spike), and the Poisson rate. The quiet samples have a variance of their own, bounded below by the
    calibrated one (one more parameter): under motion the residual carries scale and
    misalignment errors, which would otherwise be charged to the spike model and make the
    noise model win; so do the spikes' distances from amp.

    ``sized`` (shape of r, default r) is the residual the amplitude and its interval are
    taken from, at the samples flagged in r: :func:`~imufdi_cli.episodes.fits.fit_models`
    ranks the model on r less the motion nuisance and sizes it on the residual itself
    (with random signs, the motion error at the spikes averages out of the mean of |r|,
    and the interval's spread carries it)."""
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
    j = int(np.argmax(lengths))
    onset = int(starts[j])
    if lengths[j] < share * (raw.shape[0] - onset):
        return None
    value = float(raw[onset - 1])
    return FaultFit("stuck", value, value, value, onset, -math.inf)
