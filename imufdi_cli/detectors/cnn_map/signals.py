"""cnn-map signal helpers: constants, CNN input windows, AR prewhitening of the mapping
residual, the calibration motion check and the gamma shape of residual energies.
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from imufdi_cli.detectors.cusum import (
    CusumDesign,
)
from imufdi_cli.errors import (
    CalibrationError,
)
from imufdi_cli.maths.parity import residual_projector

#: Format tag of saved model files.
MODEL_FORMAT = "imufdi-cnn-map-1"
#: Fewest training windows (all IMUs together) for a meaningful fit.
MIN_TRAINING_WINDOWS = 200
#: Scale from the median absolute deviation to the standard deviation of a Gaussian.
MAD_TO_STD = 1.4826
#: The calibration window must rotate, and move the specific force, by at least this
#: multiple of the noise (standard deviations) on one body axis (``check_motion``).
MIN_MOTION_RATIO = 10.0
#: A gyro the GLT screen isolated is re-admitted to the reference this long after its last
#: isolation, seconds.
READMIT_S = 0.5
#: Input test (step 8): design variance ratio K of the CUSUM (a noise growth x3) and clip of
#: the standardized differences, sigma.
INPUT_DESIGN = CusumDesign(ratio=9.0, clip=5.0)
#: Input test: the CUSUM is capped this long (at its null drift) above its threshold, s, so
#: that an alarm ends about this long after the noise returns to nominal.
INPUT_RELEASE_S = 0.25
#: Input test: each leave-one-out residual is compared with the mean of its previous
#: samples over this span, s (8 samples at 100 Hz; :func:`imufdi_cli.detectors.cusum.local_mean_residual`).
INPUT_MEAN_S = 0.08
#: What the mapping test does: ``report`` (computed, exceedances of its threshold counted
#: in the metadata, no alarm), ``alarm`` (alarms, at alpha / 2 beside the input test) or
#: ``off`` (no network is trained).
MAPPING_MODES = ("report", "alarm", "off")


def input_windows(body_accel: np.ndarray, length: int) -> np.ndarray:
    """Every full window of ``length`` samples, per IMU.

    Parameters
    ----------
    body_accel : ndarray, shape (N, m, 3)
    length : int

    Returns
    -------
    ndarray, shape (N - length + 1, m, length, 3) (a view); window i ends at sample
    ``i + length - 1``.
    """
    return np.moveaxis(sliding_window_view(body_accel, length, axis=0), -1, 2)


def fit_autoregression(series: np.ndarray, order: int) -> np.ndarray:
    """Least-squares AR coefficients shared by several series (step 3).

    Parameters
    ----------
    series : ndarray, shape (N, m)
        m series of N samples each, fitted jointly.
    order : int
        p >= 0.

    Returns
    -------
    ndarray, shape (p,): phi with ``x(t) ~ sum_i phi_i x(t - i)``.
    """
    n = series.shape[0]
    if order == 0:
        return np.zeros(0)
    lags = np.stack([series[order - 1 - i : n - 1 - i] for i in range(order)], axis=-1)
    design, target = lags.reshape(-1, order), series[order:].ravel()
    return np.linalg.lstsq(design, target, rcond=None)[0]  # type: ignore[no-any-return]


def whiten(residual: np.ndarray, coefficients: np.ndarray) -> np.ndarray:
    """Apply the AR prewhitening filter per component (step 3).

    Parameters
    ----------
    residual : ndarray, shape (N, m, 3)
    coefficients : ndarray, shape (3, p)
        phi per component.

    Returns
    -------
    ndarray, shape (N - p, m, 3): row i is ``e(i + p) - sum_j phi_j e(i + p - j)``.
    """
    p = coefficients.shape[1]
    n = residual.shape[0]
    out = residual[p:].copy()
    for i in range(p):
        out -= coefficients[:, i] * residual[p - 1 - i : n - 1 - i]
    return out


def _excursion_ratio(series: np.ndarray, across: np.ndarray | None = None) -> np.ndarray:
    """Per-column motion excursion over the white-noise level, (c,) for (N, c) series.

    Two noise estimates, each at least the true white-noise level in expectation, and the
    smaller one is used: second differences (``Var(D^2 x) = 6 sigma^2`` for white noise,
    smooth motion cancels to O(Te^2), but jerky motion sampled slowly does not: hand
    motion at 62.5 Hz puts ~130 deg/s into them) and ``across`` (the spread across the
    redundant sensors, :func:`noise_across_gyros` / :func:`noise_across_accels`: motion
    cancels, chip bias differences and timing jitter do not). Excursion = the standard
    deviation left after the noise.

    Parameters
    ----------
    series : ndarray, shape (N, c)
    across : ndarray, shape (c,), optional
        Noise level of ``series`` from the spread across sensors, same unit.
    """
    noise = MAD_TO_STD * np.median(np.abs(np.diff(series, n=2, axis=0)), axis=0) / np.sqrt(6.0)
    if across is not None:
        noise = np.minimum(noise, across)
    spread = np.sqrt(np.maximum(series.var(axis=0) - noise**2, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(noise > 0, spread / noise, np.where(spread > 0, np.inf, 0.0))


def _parity_variance(residual: np.ndarray, dof: int) -> np.ndarray:
    """Noise variance per sensor from parity residuals: the median over samples of
    ``|P y|^2 / dof``, divided by the median of chi^2_dof / dof (Wilson-Hilferty,
    ``(1 - 2 / (9 dof))^3``) so that white Gaussian noise gives sigma^2 unbiased.

    Parameters
    ----------
    residual : ndarray, shape (N, n, ...)
        Projections ``P y`` of n sensors onto the complement of the common signal.
    dof : int
        Rank of that complement, >= 1.

    Returns
    -------
    ndarray, shape (...)
    """
    per_sample = np.sum(residual**2, axis=1) / dof
    return np.median(per_sample, axis=0) / (1.0 - 2.0 / (9.0 * dof)) ** 3  # type: ignore[no-any-return]


def _complement(design: np.ndarray) -> tuple[np.ndarray, int]:
    """Projector onto the orthogonal complement of ``design``'s columns, and its rank."""
    rank = int(np.linalg.matrix_rank(design))
    return residual_projector(design), design.shape[0] - rank


def noise_across_gyros(gyro: np.ndarray, measurement: np.ndarray) -> np.ndarray | None:
    """Noise of the least-squares body rate from the gyros' disagreement, (3,) rad/s.

    The parity residual ``P y`` (``P = I - H H^+``) holds no rotation whatever the
    motion; with equal white noise sigma on every gyro, ``E|P y|^2 = (n - 3) sigma^2``
    and the least-squares rate has the standard deviations ``sigma sqrt(diag((H^T H)^-1))``.

    Parameters
    ----------
    gyro : ndarray, shape (N, n), rad/s
    measurement : ndarray, shape (n, 3)
        H, sensor axes in the body frame.

    Returns
    -------
    ndarray, shape (3,), or None with fewer than 4 gyros (no redundancy).
    """
    projector, dof = _complement(measurement)
    if dof < 1:
        return None
    sigma2 = float(_parity_variance((gyro @ projector.T)[:, :, None], dof)[0])
    return np.sqrt(sigma2 * np.diag(np.linalg.inv(measurement.T @ measurement)))  # type: ignore[no-any-return]


def noise_across_accels(body: np.ndarray, positions: np.ndarray) -> np.ndarray | None:
    """Noise of the mean specific force over the IMUs from their disagreement, (3,) m/s^2.

    A rigid body's specific force at position r_k is ``f(t) + K(t) r_k`` (K: the angular
    acceleration and centripetal terms), so per body axis the residual of the IMUs after a
    fit on ``[1, r_k]`` holds no rigid motion; its variance per IMU, divided by m, is that
    of the mean over the m IMUs.

    Parameters
    ----------
    body : ndarray, shape (N, m, 3), m/s^2
        Specific force per IMU in the body frame.
    positions : ndarray, shape (m, 3), m

    Returns
    -------
    ndarray, shape (3,), or None when the IMUs leave no residual (m <= 4 off a plane).
    """
    m = body.shape[1]
    design = np.column_stack([np.ones(m), positions - positions.mean(axis=0)])
    projector, dof = _complement(design)
    if dof < 1:
        return None
    residual = np.einsum("jk,nka->nja", projector, body)
    return np.sqrt(_parity_variance(residual, dof) / m)  # type: ignore[no-any-return]


def check_motion(
    reference: np.ndarray,
    body: np.ndarray,
    rate_noise: np.ndarray | None = None,
    force_noise: np.ndarray | None = None,
) -> dict[str, list[float]]:
    """Refuse a calibration window without the motion the mapping needs.

    The mapping learns the body rate from windows of specific force: the window must
    rotate (reference rate) and move the specific force, each by at least
    ``MIN_MOTION_RATIO`` times its noise on one body axis.

    Parameters
    ----------
    reference : ndarray, shape (N, 3), rad/s
    body : ndarray, shape (N, m, 3), m/s^2
    rate_noise, force_noise : ndarray, shape (3,), optional
        Noise of ``reference`` and of ``body.mean(axis=1)`` from the spread across the
        sensors (:func:`noise_across_gyros`, :func:`noise_across_accels`); the noise is
        the smaller of this and the second-difference estimate (``_excursion_ratio``).

    Returns
    -------
    dict
        ``rate`` and ``specific_force``: excursion / noise per body axis (for metadata).

    Raises
    ------
    CalibrationError
        Neither ratio reaches ``MIN_MOTION_RATIO`` on any axis; the message names which.
    """
    rate = _excursion_ratio(reference, rate_noise)
    force = _excursion_ratio(body.mean(axis=1), force_noise)
    missing = [
        f"{what} (excursion {', '.join(f'{v:.2g}' for v in ratio)} x its noise about x, y, z)"
        for what, ratio in (("rotation", rate), ("specific-force change", force))
        if not np.any(ratio >= MIN_MOTION_RATIO)
    ]
    if missing:
        raise CalibrationError(
            "cnn-map: the calibration window lacks the motion the mapping needs: no "
            + " and no ".join(missing)
            + f"; it needs at least {MIN_MOTION_RATIO:g}x on one axis. Calibrate on a window"
            " where the array moves (--calibrate START:END)"
        )
    return {"rate": rate.tolist(), "specific_force": force.tolist()}


def gamma_shape(energies: np.ndarray) -> float:
    """Method-of-moments gamma shape of energies with mean ~1: ``mean^2 / var``."""
    mean = float(np.mean(energies))
    variance = float(np.var(energies, ddof=1))
    if not (variance > 0 and mean > 0):
        raise CalibrationError("cnn-map: held-out residual energies have zero variance")
    return mean * mean / variance
