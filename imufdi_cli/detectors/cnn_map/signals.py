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


def _excursion_ratio(series: np.ndarray) -> np.ndarray:
    """Per-column motion excursion over the white-noise level, (c,) for (N, c) series.

    Noise from second differences (``Var(D^2 x) = 6 sigma^2`` for white noise, smooth
    motion cancels to O(Te^2)); excursion = the standard deviation left after the noise.
    """
    noise = MAD_TO_STD * np.median(np.abs(np.diff(series, n=2, axis=0)), axis=0) / np.sqrt(6.0)
    spread = np.sqrt(np.maximum(series.var(axis=0) - noise**2, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(noise > 0, spread / noise, np.where(spread > 0, np.inf, 0.0))


def check_motion(reference: np.ndarray, body: np.ndarray) -> dict[str, list[float]]:
    """Refuse a calibration window without the motion the mapping needs.

    The mapping learns the body rate from windows of specific force: the window must
    rotate (reference rate) and move the specific force, each by at least
    ``MIN_MOTION_RATIO`` times its noise on one body axis.

    Parameters
    ----------
    reference : ndarray, shape (N, 3), rad/s
    body : ndarray, shape (N, m, 3), m/s^2

    Returns
    -------
    dict
        ``rate`` and ``specific_force``: excursion / noise per body axis (for metadata).

    Raises
    ------
    CalibrationError
        Neither ratio reaches ``MIN_MOTION_RATIO`` on any axis; the message names which.
    """
    rate = _excursion_ratio(reference)
    force = _excursion_ratio(body.mean(axis=1))
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
