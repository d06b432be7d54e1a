"""Fitting the fault models to an episode's residual, with unknown onset and end.

Over an analysis window (the episode plus a margin before it) the fault models of
``imufdi inject`` are fitted to the isolated sensor's residual ``r``
(:func:`~imufdi_cli.episodes.reference.leave_one_out`) with an unknown onset ``tau``
(profile likelihood over every sample of the margin and the episode's first part) and,
when the detector's alarms outlast the fault, an end (:func:`_fault_end`):

======  ==============================================  =====================================
model   r(t) for t >= tau (before: N(0, sigma_r^2))     size (90 % interval)
======  ==============================================  =====================================
step    a + e                                           amp: t interval (:func:`_linear_fit`)
drift   b (t - t_f) + e, t_f between two samples        rate: t interval of the LS slope
noise   gamma o + e, Var e = f^2 sigma_k^2 + sigma_c^2  factor: successive differences, F
scale   beta o(t) + e, o the consensus prediction       factor: 1 + beta_hat, t interval
spikes  gamma o + e + s A on a fraction p of samples    amp A (t interval), rate (Poisson)
stuck   y_k(t) = y_k(tau - 1) exactly                   value (exact)
======  ==============================================  =====================================

The models are ranked by BIC (Schwarz 1978): the Gaussian log-likelihood of the whole
window minus half the number of free parameters times ln n. Under motion a healthy sensor's
residual already carries a motion-dependent error (calibrated scale and misalignment
residue); its projection on o, ``gamma o`` over the whole window, is a nuisance of the
noise and spikes models, and the scale model is ranked with ``beta_0 o`` before its onset
(:func:`_fit_window`), so that noise growth on a turning array is not taken for a scale
factor (docs/episodes.md, "Noise growth or scale factor on a turning array"). ``none``
(no fault: the residual is the calibrated noise throughout) is ranked with them, so an
episode that no fault model explains better than chance is called a false alarm, with its
evidence.
``stuck`` is not a Gaussian model (a frozen output has no noise at all): it is declared
when the raw output repeats exactly on at least ``stuck_share`` of the samples after the
onset (a healthy sensor always carries its own noise, so long exact repeats do not
happen), and then ranks first.

The sizes and intervals of the linear models are :func:`_linear_fit`'s (in
:mod:`~imufdi_cli.episodes.reference`), those of noise, spikes and stuck
:mod:`~imufdi_cli.episodes.model_fits`'.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from imufdi_cli.episodes.fault_fit import MODELS, FaultFit, WhiteNoise
from imufdi_cli.episodes.model_fits import (
    SPIKE_CUT,
    _local_level,
    _noise_fit,
    _spike_fit,
    _stuck_fit,
    _white_noise_fit,
)
from imufdi_cli.episodes.numerics import _gaussian_nll, _median, _prefix, _suffix, _suffixes
from imufdi_cli.episodes.reference import Reference, _linear_fit


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
    if end is not None:
        for _ in range(2):  # the end found by the best model on the whole window, refined once
            refined = _fault_end(fit_until(end, None), r[:end], var0)
            if refined is None or refined == end:
                break
            end = refined
    # the end is a parameter of every fault model, not only of the best one: the runner-up
    # model with a curve proposes its own end too (a scale fault that ended inside the
    # window is fitted badly to the window's end, and a model with a free variance can then
    # rank above it before its end is found); each model keeps the candidate end (or none,
    # when the best model found none) that gives it the lowest BIC
    curved = [f for f in fits if f.curve is not None]
    runner_end = None
    if len(curved) > 1 and fits[0].model != "stuck":
        runner_end = _fault_end(fits, r, var0, curved[1].model)
    variants = [fits if end is None else _cut(fits, end, r, var0, reference, fit_until)]
    if runner_end is not None and runner_end != end:
        variants.append(_cut(fits, runner_end, r, var0, reference, fit_until))
    if len(variants) == 1:
        return variants[0]
    chosen: dict[str, FaultFit] = {}
    for variant in variants:
        for f in variant:
            if f.model not in chosen or f.bic < chosen[f.model].bic:
                chosen[f.model] = f
    out = list(chosen.values())
    out.sort(key=lambda f: (f.bic, MODELS.index(f.model)))  # stuck (-inf) stays first
    return out


def _cut(
    fits: list[FaultFit],
    end: int,
    r: np.ndarray,
    var0: float,
    reference: Reference | None,
    fit_until: Any,
) -> list[FaultFit]:
    """The fits on the window's samples up to ``end`` (``fit_until``), with the healthy
    tail after it and the end's BIC penalty added; ``fits`` when nothing fits there."""
    # the fault ended before the window did (the detector's alarms outlast it): refit on
    # the samples up to its end; the healthy tail adds the same to every model's -2 log L,
    # and the end is one more parameter of each fault model
    tail = float(
        2 * _gaussian_nll(float(np.add.reduce(r[end:] ** 2)), float(r.shape[0] - end), var0)
    )
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


def _fault_end(
    fits: list[FaultFit], r: np.ndarray, var0: float, model: str | None = None
) -> int | None:
    """Where the fault ends, when it ends clearly before the window does: by the best
    fitted model with a fitted curve (step, drift, noise, scale; or ``model``'s fit when
    given), the end maximises its
    log-likelihood ratio against the calibrated noise summed from the onset to the end
    (the samples after it are better explained as healthy). None when the best model is a
    frozen output (stuck: the repeats say where it ends), no model has a curve, or the end
    does not earn its BIC penalty."""
    if fits and fits[0].model == "stuck":
        return None
    best = next((f for f in fits if f.curve is not None and model in (None, f.model)), None)
    if best is None or best.curve is None or best.onset_index < 0:
        return None
    mean, variance = best.curve
    segment = r[best.onset_index : best.onset_index + mean.shape[0]]
    llr = -0.5 * ((segment - mean) ** 2 / variance + math.log(variance)) + 0.5 * (
        segment**2 / var0 + math.log(var0)
    )
    cumulative = np.cumsum(llr)
    j = int(cumulative.argmax())
    end = best.onset_index + j + 1
    # the end is one more parameter: it must earn its BIC penalty (ln n) in -2 log L
    gain = 2 * float(cumulative[j] - cumulative[-1])
    if end - best.onset_index < 4 or gain <= math.log(r.shape[0]):
        return None
    return end


@dataclass(frozen=True)
class _Window:
    """An analysis window and its sums at each candidate onset ``tau`` (``taus``, shape
    (T,)): what every fault model's profile likelihood is built from.

    ``r``, ``o``, ``t``: the residual, the consensus prediction and the times, shape (L,);
    ``healthy_before`` the sum of ``r**2`` before each tau and ``nll_before`` its Gaussian
    -log L at ``var0``; ``s_r``, ``s_rr``, ``s_oo``, ``s_or`` the sums of r, r², o², o r
    from each tau on; ``n_after`` the samples from each tau on (float)."""

    r: np.ndarray
    o: np.ndarray
    t: np.ndarray
    lo: int
    taus: np.ndarray
    n_after: np.ndarray
    ln_n: float
    sigma_k: float
    consensus_sigma: float
    var0: float
    healthy_before: np.ndarray
    nll_before: np.ndarray
    s_r: np.ndarray
    s_rr: np.ndarray
    s_oo: np.ndarray
    s_or: np.ndarray

    def motion_variance(self, coefficient: Any) -> Any:
        """The variance of ``r - coefficient * o``: o = x + e_c carries the consensus
        error, so with r = beta x + e_k - e_c, r - beta o = e_k - (1 + beta) e_c has
        variance sigma_k^2 + (1 + beta)^2 sigma_c^2 (var0 at beta = 0)."""
        return self.sigma_k**2 + (1 + coefficient) ** 2 * self.consensus_sigma**2


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
    taus = np.arange(lo, hi)
    n_after = (length - taus).astype(np.float64)
    ln_n = math.log(float(length))

    # prefix: healthy samples before tau; suffix sums after tau (of r, r², t, t², t r, o²,
    # o r: one accumulation for the seven)
    series = np.empty((7, length))
    series[0] = r
    sq = np.multiply(r, r, out=series[1])
    series[2] = t
    np.multiply(t, t, out=series[3])
    np.multiply(t, r, out=series[4])
    np.multiply(o, o, out=series[5])
    np.multiply(o, r, out=series[6])
    s_r, s_rr, s_t, s_tt, s_tr, s_oo, s_or = _suffixes(series, lo, hi)
    healthy_before = _prefix(sq)[taus]
    nll_before = _gaussian_nll(healthy_before, taus.astype(np.float64), var0)
    w = _Window(
        r=r,
        o=o,
        t=t,
        lo=lo,
        taus=taus,
        n_after=n_after,
        ln_n=ln_n,
        sigma_k=sigma_k,
        consensus_sigma=consensus_sigma,
        var0=var0,
        healthy_before=healthy_before,
        nll_before=nll_before,
        s_r=s_r,
        s_rr=s_rr,
        s_oo=s_oo,
        s_or=s_or,
    )
    fits: list[FaultFit] = []
    linear: dict[str, Any] = {
        "var0": var0,
        "offset_var": offset_var or 0.0,
        "confidence": confidence,
        "reference": reference,
        "window": r,
    }

    # step: r = a + e
    a = s_r / n_after
    total = nll_before + _gaussian_nll(s_rr - n_after * a**2, n_after, var0)
    j = int(total.argmin())
    bic = float(2 * total[j] + 2 * ln_n)  # a, the onset
    onset = lo + j
    ones = np.ones((length - onset, 1))
    fits.append(_linear_fit("step", r[onset:], ones, onset, bic, constant=True, **linear))

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

    fits.append(_noise_model(w, a, white, confidence, calibration_samples))
    scale = _scale_model(w, linear)
    if scale is not None:
        fits.append(scale)

    # none: the residual is the sensor's calibrated noise over the whole window (a false
    # alarm of chance: no fault model earns its extra parameters)
    nll_healthy = float(_gaussian_nll(np.add.reduce(sq), float(length), var0))
    fits.append(FaultFit("none", math.nan, math.nan, math.nan, -1, 2 * nll_healthy))

    spikes = _spikes_model(w, confidence)
    if spikes is not None:
        fits.append(spikes)
    fits.sort(key=lambda f: (f.bic, MODELS.index(f.model)))

    stuck = _stuck_fit(raw, lo, hi, stuck_share)
    if stuck is not None:
        fits.insert(0, stuck)
    return fits


def _noise_model(
    w: _Window,
    a: np.ndarray,
    white: WhiteNoise | None,
    confidence: float,
    calibration_samples: int | None,
) -> FaultFit:
    """The noise model: r = gamma o + e over the whole window, e ~ N(0, var_gamma) before
    the onset and N(0, v) after it, v >= var_gamma fitted (v = f^2 sigma_k^2 + sigma_c^2 at
    gamma = 0). ``a``: the step model's mean after each onset, shape (T,)."""
    # gamma o is a nuisance: the motion-dependent error a healthy sensor carries under motion
    # (its calibrated scale and misalignment residue, projected on o), before the fault as
    # after it; without it the noise model charged that error to its variance, and the
    # scale model (whose beta absorbs it) won on noise growth under motion (conical6).
    # gamma is the least-squares coefficient over the window (the noise is independent of
    # o, so it is unbiased; the profile likelihood with it is a lower bound of the maximum).
    # No free mean: a noise fault has none, and a free mean would nest the step model.
    r, o, taus, n_after = w.r, w.o, w.taus, w.n_after
    s_oo_all = float(np.dot(o, o))
    gamma = float(np.dot(o, r)) / s_oo_all if s_oo_all > 0 else 0.0
    var_gamma = w.motion_variance(gamma)
    sq_g = (r - gamma * o) ** 2
    before_g = _prefix(sq_g)[taus]
    after_g = _suffix(sq_g)[taus]
    var_hat = np.maximum(after_g / n_after, var_gamma)
    nll_before_g = _gaussian_nll(before_g, taus.astype(np.float64), var_gamma)
    total_g = nll_before_g + _gaussian_nll(after_g, n_after, var_hat)
    j = int(total_g.argmin())
    bic = float(2 * total_g[j] + 3 * w.ln_n)  # gamma, v, onset
    # the factor is sized from the successive differences (white path: gamma o varies
    # slowly and drops out of them) or from the spread about the mean: a fault on a sensor
    # of the consensus (another detector's, or one too small to alarm) shifts r, and that
    # shift is not noise
    if white is None:
        return _noise_fit(
            float(max(w.s_rr[j] - n_after[j] * a[j] ** 2, 0.0)),
            int(n_after[j]),
            float(a[j]),
            w.sigma_k,
            w.consensus_sigma,
            confidence,
            w.lo + j,
            bic,
            calibration_samples,
            ranking_var=float(var_hat[j]),
        )
    return _white_noise_fit(
        r[w.lo + j :], float(a[j]), white, confidence, w.lo + j, bic, w.var0, float(var_hat[j])
    )


def _scale_model(w: _Window, linear: dict[str, Any]) -> FaultFit | None:
    """The scale model: r = beta o + e from the onset on (None when o is zero there)."""
    # The onset is where the residual turns from the calibrated noise to beta o + e
    # (profile likelihood, as for step and drift); the class is decided with the
    # likelihood of r = beta_0 o + e before that onset and beta o + e after it: beta_0 o is
    # the same nuisance as the noise model's gamma o (the healthy motion error), so neither
    # model is charged for what the other explains, and both have three parameters
    # (beta_0, beta and the onset; gamma, v and the onset). (With the onset fitted on the
    # two-coefficient likelihood too, a coefficient change at a fault's end would pass for
    # an onset.) Each part's noise: :meth:`_Window.motion_variance`.
    r, o, s_oo, s_or = w.r, w.o, w.s_oo, w.s_or
    with np.errstate(divide="ignore", invalid="ignore"):
        beta = np.where(s_oo > 0, s_or / s_oo, 0.0)
    sse_1 = np.maximum(w.s_rr - beta * s_or, 0.0)
    nll_1 = _gaussian_nll(sse_1, w.n_after, w.motion_variance(beta))
    j = int((w.nll_before + nll_1).argmin())
    tau = int(w.taus[j])
    p_oo, p_or = float(np.dot(o[:tau], o[:tau])), float(np.dot(o[:tau], r[:tau]))
    beta_0 = p_or / p_oo if p_oo > 0 else 0.0
    nll_0 = _gaussian_nll(
        max(float(w.healthy_before[j]) - beta_0 * p_or, 0.0),
        float(tau),
        w.motion_variance(beta_0),
    )
    # beta_0, beta, onset; beta_0 only when there are samples before the onset (a window
    # that starts inside the fault has r = beta o + e throughout: then a noise model whose
    # nuisance gamma o takes up beta o and whose variance stays at its bound ties with it,
    # with no evidence of noise growth at all)
    bic = float(2 * (nll_0 + nll_1[j]) + (2 + (tau > 0)) * w.ln_n)
    onset = w.lo + j
    if not s_oo[j] > 0:
        return None
    return _linear_fit("scale", r[onset:], o[onset:, None], onset, bic, shift=1.0, **linear)


def _spikes_model(w: _Window, confidence: float) -> FaultFit | None:
    """The spikes model on r - gamma_s o (None when no spikes are found)."""
    # gamma_s o: the noise model's nuisance (one more parameter), so that a slow motion
    # error the nuisance explains is not charged to the spike model's quiet variance while
    # the noise model is let off it. gamma_s is fitted on the samples that are not spikes
    # (the spike model's own quiet samples): with the spikes in, their sign imbalance D
    # moves it, and the amplitudes by about -A D^2 / (N m) (m spikes of N). The amplitude
    # and its interval are still taken from r at the flagged samples (as before the
    # nuisance: calibrated on the diagnostic seeds; on r - gamma_s o conical6's intervals
    # covered 92-96 %)
    r, o = w.r, w.o
    sigma_r = math.sqrt(w.var0)
    quiet = np.abs(r - _local_level(r)) <= SPIKE_CUT * sigma_r
    o_q = o[quiet]
    s_oo_q = float(np.dot(o_q, o_q))
    gamma_s = float(np.dot(o_q, r[quiet])) / s_oo_q if s_oo_q > 0 else 0.0
    r_s = r - gamma_s * o
    nll_before_s = _gaussian_nll(
        _prefix(r_s**2)[w.taus],
        w.taus.astype(np.float64),
        w.motion_variance(gamma_s),
    )
    spikes = _spike_fit(r_s, w.t, sigma_r, w.taus, nll_before_s, w.ln_n, confidence, sized=r)
    return None if spikes is None else replace(spikes, bic=spikes.bic + w.ln_n)


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
    dt = _median(t[1:] - t[:-1]) if t.shape[0] > 1 else 0.0  # np.diff(t)
    t0 = t[taus]
    s_u = s_t - n * t0
    s_uu = s_tt - 2 * t0 * s_t + n * t0**2
    s_ur = s_tr - t0 * s_r
    det = n * s_uu - s_u**2
    with np.errstate(divide="ignore", invalid="ignore"):
        b_free = (n * s_ur - s_u * s_r) / det
        lam_free = (s_r - b_free * s_u) / n / b_free
    # the free offset, then the two bounds lam = 0 and dt stacked (2, T): elementwise the
    # same operations as one bound at a time, so the same floats
    sse_free = s_rr - (s_r - b_free * s_u) / n * s_r - b_free * s_ur
    # a free offset is a sub-sample onset; at the window's first sample it may also
    # be a ramp already in progress (an episode that starts mid-fault, after an
    # earlier alarm episode of the same fault)
    in_progress = (taus == 0) & (det > 0)
    valid_free = ((det > 0) & (lam_free >= 0) & (lam_free <= dt)) | in_progress
    bounds = (0.0, dt)
    offsets = np.array(bounds)[:, None]
    offsets_twice = np.array([2 * bound for bound in bounds])[:, None]
    offsets_sq = np.array([bound**2 for bound in bounds])[:, None]
    s_vv = s_uu + offsets_twice * s_u + n * offsets_sq
    s_vr = s_ur + offsets * s_r
    with np.errstate(divide="ignore", invalid="ignore"):
        b = s_vr / s_vv
    sse_bounds = s_rr - b * s_vr
    fit = nll_before + _gaussian_nll(np.concatenate((sse_free[None, :], sse_bounds)), n, var0)
    total = np.where(np.concatenate((valid_free[None, :], s_vv > 0)), fit, np.inf)
    best: tuple[float, int, float | None] | None = None
    for row, candidate in enumerate((None, *bounds)):
        j = int(total[row].argmin())
        if np.isfinite(total[row, j]) and (best is None or total[row, j] < best[0]):
            best = (float(total[row, j]), j, candidate)
    if best is None:
        return None
    total_nll, j, lam = best
    return j, lam, 2 * total_nll + 3 * ln_n  # rate, offset, onset
