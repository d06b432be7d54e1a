"""The isolated sensor against the others, and the least-squares sizes checked by them.

Explaining an episode works on the isolated sensor ``k`` alone, against the consensus of
the others (leave-one-out least squares, :func:`leave_one_out`)::

    r(t) = y_k(t) - h_k^T x_hat_{-k}(t),      Var r = sigma_k^2 + h_k^T (H_{-k}^T W H_{-k})^{-1} h_k

so ``r`` is the sensor's own error, whatever the motion.

The least-squares sizes (step, drift, scale) are linear estimates ``w^T r``; their variance
propagates the noise (estimated from the fit's own residuals, with their autocorrelation,
Newey & West 1994), and the calibrated bias taken out of ``r`` (a constant estimated from
n_cal samples). The other sensors (:class:`Reference`), each against a consensus without
``k``, give the same estimate where there is no fault: when they spread significantly more
than white noise says (a chi-square test at 95 % with the white variance each has in the
window, and their correlation), the interval is widened to their
dispersion (:func:`_linear_fit`); when they still spread too much, or the sensor's own
residual carries the motion, the motion-dependent errors (scale, misalignment: linear in
the sensed vector) are fitted alongside over the whole window (:func:`_motion_fit`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from imufdi_cli.episodes.fault_fit import FaultFit
from imufdi_cli.episodes.numerics import _chi2_quantile, _f_quantile, _t_quantile
from imufdi_cli.maths.parity import check_measurement_matrix, least_squares_matrix


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
        Calibrated white-noise variance of each residual, sigma_j^2 + consensus variance
        (SI^2). The healthy sensors' test takes only ``offset_var / variance`` from it and
        measures each residual's white variance in the window (:attr:`white_variance`).
    offset_var : ndarray, shape (m,)
        Variance of the calibrated bias taken out of each (SI^2; zeros when none was).
    motion : ndarray, shape (L, 3), optional
        The consensus of the sensors other than the isolated one (x_hat_{-k}).
    correlation_sq : float, optional
        ``tr R^2``, R the correlation matrix of the m residuals under white noise
        (:func:`correlation_sq`); None: uncorrelated (m).
    """

    residuals: np.ndarray
    variance: np.ndarray
    offset_var: np.ndarray
    #: (L, 3) the consensus estimate of the sensed vector without the isolated sensor,
    #: less its calibration-window mean (SI), for the motion-dependent errors of
    #: :func:`_linear_fit`; None: not modelled
    motion: np.ndarray | None = None
    correlation_sq: float | None = None

    @functools.cached_property
    def white_variance(self) -> np.ndarray:
        """(m,) white variance of each residual over the window, SI^2: from its successive
        differences (:func:`successive_variance`), so the outliers the window holds are in
        it and slow errors (bias wander, motion errors) are not."""
        return np.asarray(successive_variance(self.residuals), dtype=np.float64)

    @functools.cached_property
    def offset_share(self) -> np.ndarray:
        """(m,) ``offset_var / variance`` (0 where the variance is not positive): the
        calibrated offset's share in :func:`_dispersion`, computed once per episode."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.variance > 0, self.offset_var / self.variance, 0.0)


def successive_variance(x: np.ndarray) -> Any:
    """``sum_i (x_{i+1} - x_i)^2 / (2 (L - 1))`` along axis 0 of x (L, ...): the white
    variance of a series without what varies slowly (von Neumann 1941)."""
    d = x[1:] - x[:-1]  # np.diff(x, axis=0), without its Python overhead
    return np.einsum("i...,i...->...", d, d) / (2 * max(x.shape[0] - 1, 1))


def correlation_sq(A: np.ndarray, sigma: np.ndarray) -> float:
    """``tr R^2`` of the residuals ``window @ A`` (A (n, m)) under independent white noise
    of standard deviations ``sigma`` (n,): R is ``C = A^T diag(sigma^2) A`` normalised by its
    diagonal. Equal to m when the residuals are uncorrelated; 50.2 for the 47 leave-two-out
    residuals of 16 co-aligned triads (44 = m - 3 effective degrees of freedom)."""
    sigma = np.asarray(sigma, dtype=np.float64)
    C = (A.T * sigma**2) @ A
    scale = np.sqrt(np.diag(C))
    return float(np.sum((C / np.outer(scale, scale)) ** 2))


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
    constant: bool = False,
) -> FaultFit:
    """Least squares ``y = X c + e`` after the onset; the size is ``c[0] + shift``
    (``constant``: X is one column of ones, n >= 1, whose weights are 1 / n).

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
    the same samples (:func:`_dispersion`). Under the white-noise model ``Q = sum_j est_j^2
    / v_j`` (v_j their predicted variance, as above with the white variance each residual
    has in the window) is a scaled chi-square with ``d = m^2 / tr R^2`` degrees of freedom
    (R their correlation). Only when Q exceeds its ``DISPERSION_LEVEL`` quantile (the
    healthy sensors spread significantly more than white noise explains: bias wander since
    calibration, unmodelled motion) is the variance raised to ``Q / m`` times the
    white-noise variance of this sensor's estimate (its own white variance, measured the
    same way), with a t quantile on d degrees of freedom (a quasi-likelihood dispersion
    estimate, McCullagh & Nelder 1989 §4.5). The interval is the t interval
    ``c0 +- t_{(1 + confidence)/2} sqrt(var)``.
    """
    n, p = X.shape
    if constant:
        # X a column of ones: the normal equation is [n] (a sum of ones, exact), and
        # LAPACK's solve of it, 1 / n or 1 x (1 / n) for every sample, is the rounded 1 / n
        weights = np.full((1, n), 1.0 / n)
    else:
        gram = X.T @ X  # p <= 2 columns: the normal equations are well within precision
        if not np.isfinite(gram).all() or abs(float(np.linalg.det(gram))) <= 1e-300:
            return FaultFit(model, math.nan, -math.inf, math.inf, onset, bic)
        weights = np.linalg.solve(gram, X.T)  # (p, n): coef = weights @ y
    coef = weights @ y
    w = weights[0]
    size = float(coef[0]) + shift
    dof = n - p
    if dof < 1:
        return FaultFit(model, size, -math.inf, math.inf, onset, bic)
    fitted = X @ coef
    e = y - fitted
    sw2, sw = float(w @ w), float(np.add.reduce(w))
    quantile = _t_quantile(0.5 + confidence / 2, dof)
    extra: dict[str, float] = {}
    curve = (fitted, var0)
    widened = None
    if reference is not None and reference.residuals.shape[1] >= 2:
        # the sensor's own white variance, measured as the healthy sensors' is: successive
        # differences of the window before the onset and of the fit's residuals after it
        pre = window[: window.shape[0] - n] if window is not None else y[:0]
        white_var = float(successive_variance(pre)) * max(pre.shape[0] - 1, 0) + float(
            successive_variance(e)
        ) * (n - 1)
        white_var /= max(pre.shape[0] + n - 2, 1)
        dispersion, widened = _dispersion(
            w,
            reference,
            white_var,
            offset_var / var0 if var0 > 0 else 0.0,
            confidence,
            sums=(sw2, sw),
        )
        extra["dispersion"] = dispersion
        if window is not None and reference.motion is not None:
            # the motion-dependent errors: fitted when the healthy sensors spread too much
            # or the sensor's own residual carries them (partial F test, both at 95 %)
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
    variance = s2 * _autocorrelation_factor(e, w, sw2) * sw2 + offset_var * sw**2
    if widened is not None and widened[0] > variance:
        variance, quantile = widened
    half = quantile * math.sqrt(max(variance, 0.0))
    return FaultFit(model, size, size - half, size + half, onset, bic, extra, curve=curve)


def _dispersion(
    w: np.ndarray,
    reference: Reference,
    white_var: float,
    offset_ratio: float,
    confidence: float,
    sums: tuple[float, float] | None = None,
) -> tuple[float, tuple[float, float] | None]:
    """The healthy sensors' check of the noise model for the linear estimate ``w^T r``
    over the window's last ``len(w)`` samples: their dispersion ``Q / m``, and the widened
    (variance, quantile) of this sensor's estimate when Q exceeds its DISPERSION_LEVEL
    quantile (None otherwise). See :func:`_linear_fit`.

    Each healthy estimate ``est_j = w^T r_j`` is compared with the variance white noise of
    its own window predicts, ``v_j (w^T w + rho_j (sum w)^2)``: v_j the white variance of
    r_j over the window (:attr:`Reference.white_variance`: the outliers the window holds
    are in it, as they are in the faulty sensor's own s^2; the calibrated sigma leaves
    them out, and its own sampling error would add to Q), rho_j the calibrated offset's
    share (offset variance over white variance). The m estimates are correlated (each
    residual carries the others' noise through its consensus), so Q is a weighted sum of
    chi-square(1) terms with mean m and variance ``2 tr R^2``; its reference is the
    scaled chi-square with those two moments, ``(tr R^2 / m) chi2(d)``, ``d = m^2 / tr
    R^2`` (Satterthwaite 1946; exact for co-aligned triads, where d = m - 3). A widened
    interval takes ``Q / m`` times this sensor's white variance ``white_var (w^T w +
    offset_ratio (sum w)^2)`` and a t quantile on d degrees of freedom.

    Parameters
    ----------
    w : ndarray, shape (n,)
        Weights of the estimate over the window's last n samples.
    reference : Reference
    white_var : float
        White variance of this sensor's residual (SI^2), measured as ``v_j``.
    offset_ratio : float
        Variance of its calibrated offset over its white variance (1 / n_cal; 0: none).
    confidence : float
        Level of the interval.
    sums : (float, float), optional
        ``(w^T w, sum w)`` when the caller has them (the same floats).
    """
    n = w.shape[0]
    sw2, sw = (float(w @ w), float(np.add.reduce(w))) if sums is None else sums
    estimates = w @ reference.residuals[-n:]
    predicted = reference.white_variance * (sw2 + reference.offset_share * sw**2)
    m = estimates.shape[0]
    q = float(np.add.reduce(estimates**2 / predicted))
    tr_r2 = float(m if reference.correlation_sq is None else reference.correlation_sq)
    dof = m * m / tr_r2
    if not q > tr_r2 / m * _chi2_quantile(DISPERSION_LEVEL, dof):
        return q / m, None
    white = q / m * white_var * (sw2 + offset_ratio * sw**2)
    return q / m, (white, _t_quantile(0.5 + confidence / 2, dof))


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
    only if it is still significant), except for the calibrated bias's variance:
    ``offset_var / var0`` (1 / n_cal) times the white variance of the fit's residuals
    (:func:`successive_variance`), not ``offset_var``. The offset taken out of r is r's
    calibration mean; with M relative to its calibration mean, the motion part of that
    mean is in ``M c``, so what is left of the offset's error is the mean of n_cal white
    samples. ``var0`` (the calibrated sigma's) also holds the motion errors of a
    calibration window that spans the start of a motion (conical6, seeds 100-129: 1.56
    times the white variance on average, 0.99-2.30), and the offset is most of a step's
    variance (71 % on 352 diagnostic conical6 steps, seeds 100-219), so with
    ``offset_var`` the step intervals were too wide (94.6 % coverage there, 90.1 % now).
    The healthy sensors' check predicts their offsets' errors the same way
    (:func:`_dispersion`). It is used when ``force`` (the healthy sensors
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
    p = X.shape[1]
    design = np.zeros((length, p + M.shape[1]))  # [X zero before the onset, M]
    design[onset:, :p] = X
    design[:, p:] = M
    scale = np.sqrt(np.add.reduce(design * design, axis=0))  # np.linalg.norm(design, axis=0)
    if not np.isfinite(design).all() or (scale <= 0).any():
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
    sw2, sw = float(w @ w), float(np.add.reduce(w))
    white = float(successive_variance(e))
    offset_ratio = offset_var / var0 if var0 > 0 else 0.0
    # the calibrated offset's error: what is left of the calibration window once M (taken
    # relative to its calibration mean) holds the motion errors, i.e. the mean of n_cal
    # samples of white noise, offset_ratio = 1 / n_cal times the white variance; the
    # healthy sensors' check below predicts their offsets' error the same way
    offset = offset_ratio * white if var0 > 0 else offset_var
    variance = float(e @ e) / dof * _autocorrelation_factor(e, w, sw2) * sw2 + offset * sw**2
    quantile = _t_quantile(0.5 + confidence / 2, dof)
    dispersion, widened = _dispersion(w, reference, white, offset_ratio, confidence, sums=(sw2, sw))
    if widened is not None and widened[0] > variance:
        variance, quantile = widened
    return float(coef[0]), quantile * math.sqrt(max(variance, 0.0)), dispersion


def _pinv_from_svd(u: np.ndarray, singular: np.ndarray, vt: np.ndarray) -> np.ndarray:
    """``numpy.linalg.pinv(a)`` (default cut-off) from ``svd(a, full_matrices=False)``:
    the same operations on the same factors, so the same floats (checked against numpy in
    tests/episodes/test_episodes_identical.py), without a second decomposition.

    Parameters
    ----------
    u : ndarray, shape (L, k)
    singular : ndarray, shape (k,)
        In descending order, as the SVD returns them (the cut is relative to the first).
    vt : ndarray, shape (k, k)

    Returns
    -------
    ndarray, shape (k, L)
    """
    large = singular > 1e-15 * singular[0]  # LAPACK sorts them: singular[0] is the max
    if large.all():  # (nothing cut: the same division, without the masks)
        inverse = np.divide(1, singular)
    else:
        inverse = np.divide(1, singular, where=large, out=singular.copy())
        inverse[~large] = 0
    return vt.T @ (inverse[:, np.newaxis] * u.T)


def _autocorrelation_factor(e: np.ndarray, w: np.ndarray, sw2: float | None = None) -> float:
    """``Var(w^T e) / (s^2 w^T w)`` for a stationary e: ``1 + 2 sum_k kappa_k rho_k
    sum_i w_i w_{i+k} / w^T w`` with the sample autocorrelation rho_k of ``e`` and Bartlett
    weights ``kappa_k = 1 - k / (L + 1)`` up to ``L = floor(4 (n/100)^(2/9))`` (Newey &
    West 1994), which keep it non-negative; 1 for white noise (up to its sampling error,
    about ``2 sqrt(L / 3 n)``). Floored at 0.1. ``sw2``: ``w^T w`` when the caller has it."""
    n = e.shape[0]
    lags = min(n - 2, int(4 * (n / 100) ** (2 / 9)))
    e0 = e - np.add.reduce(e) / n  # e.mean(), without its Python overhead
    c0 = float(e0 @ e0)
    if sw2 is None:
        sw2 = float(w @ w)
    if lags < 1 or c0 <= 0 or sw2 <= 0:
        return 1.0
    total = 1.0
    for k in range(1, lags + 1):
        rho = float(e0[:-k] @ e0[k:]) / c0
        total += 2 * (1 - k / (lags + 1)) * rho * float(w[:-k] @ w[k:]) / sw2
    return max(total, 0.1)


# --- the consensus matrices of a calibration (cached by the builder) -----------------------


def downdated_gain(H: np.ndarray, sigma: np.ndarray, k: int) -> tuple[np.ndarray, float]:
    """:func:`_consensus_gain` of sensor k, from the information matrix downdated by k's
    own term (one 3x3 solve instead of a pseudo-inverse).

    Parameters
    ----------
    H : ndarray, shape (n, 3)
    sigma : ndarray, shape (n,)
        Per-sensor white-noise standard deviation, SI.
    k : int

    Returns
    -------
    gain : ndarray, shape (n,)
        Weights of the prediction of sensor k from the others (0 for k).
    consensus_sigma : float
        Standard deviation of that prediction, SI.

    Raises
    ------
    ValueError
        When the other sensors do not span 3 axes.
    """
    sigma = np.asarray(sigma, dtype=np.float64)
    weights = 1.0 / sigma**2
    M = (H.T * weights) @ H
    M_k = M - np.outer(H[k], H[k]) * weights[k]
    if float(np.linalg.eigvalsh(M_k)[0]) <= 1e-9 * float(np.linalg.eigvalsh(M)[-1]):
        raise ValueError(f"sensor {k}: the other sensors do not span 3 axes")
    solved = np.linalg.solve(M_k, H[k])
    gain = (H @ solved) * weights
    gain[k] = 0.0
    return gain, float(np.sqrt(H[k] @ solved))


def estimator_without(H: np.ndarray, sigma: np.ndarray, k: int) -> np.ndarray:
    """(n, 3) ``B`` with ``window @ B`` the weighted least-squares estimate of the sensed
    vector from the sensors other than k (row k is zero); H (n, 3), sigma (n,) SI."""
    sigma = np.asarray(sigma, dtype=np.float64)
    weights = 1.0 / sigma**2
    M = (H.T * weights) @ H - np.outer(H[k], H[k]) * weights[k]
    found = (H * weights[:, None]) @ np.linalg.inv(M)
    found[k] = 0.0
    return found


def leave_two_out(
    H: np.ndarray,
    sigma: np.ndarray,
    k: int,
    calibration_mean: np.ndarray | None,
    calibration_samples: int | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """``A`` (n, m) with ``window @ A`` the residuals of the m sensors j != k whose
    leave-two-out consensus exists, their calibrated offsets, white variances and
    offset variances (the arrays of a :class:`Reference`; None with fewer than two such
    sensors). All m consensuses at once from the information matrix
    ``M = H^T W H`` by downdating: ``M_{-jk} = M - h_k h_k^T / s_k^2 - h_j h_j^T / s_j^2``,
    gain ``g_{j,i} = h_j^T M_{-jk}^{-1} h_i / s_i^2`` (i not j, k) and consensus
    variance ``h_j^T M_{-jk}^{-1} h_j``. ``calibration_mean`` (n,) gives the offsets,
    ``calibration_samples`` their variances (zeros without)."""
    sigma = np.asarray(sigma, dtype=np.float64)
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
    if calibration_mean is not None:
        offset = calibration_mean @ A
        if calibration_samples:
            offset_var = variance / calibration_samples
    return A, offset, variance, offset_var
