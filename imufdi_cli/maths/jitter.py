"""Motion-dependent noise: a sampling-time jitter term in the parity tests' covariance.

On a real array the sensors are not sampled at exactly the same instant: a sensor read
``delta t`` late measures ``m(t + delta t) ~ m(t) + delta t dm/dt``. With a random
per-sample ``delta t`` of standard deviation ``sigma_t`` this adds a variance
``sigma_t^2 (dm/dt)^2`` to each measurement, negligible at rest and dominant in fast
motion (on the MIMU4444 board the gyro residual between triads is 0.21 deg/s at rest and
~9 deg/s in hand motion, docs/real-arrays.md).

The model used here is the isotropic form of that term, in whitened units (each sensor
divided by its noise sigma_j)::

    Cov(m_w,t) = (1 + A_t) I,      A_t = sigma_t^2 e_t,
    e_t = max(0, |ydot_w,t|^2 - 2 c / dt^2) / n

with ``ydot_w = F dm_w/dt``, ``F = H_w H_w^+``, the rate of change of the array consensus
prediction of every sensor (the motion, with its lever-arm terms for accelerometers;
faults and most of the noise are projected out) and n the number of sensors: the jitter
variance averaged over the sensors. ``2 c / dt^2`` (c = rank F) is what white unit noise
alone contributes to ``|ydot_w|^2`` in a difference of two samples; removing it keeps
A_t near 0 at rest. The isotropic form keeps the whitened geometry, so the parity statistic
``D_t = |P m_w,t|^2`` is simply ``(1 + A_t) chi2(n - q)`` without a fault, and the tests
divide their statistics by ``1 + A_t`` (glt) or by its mean over the moving window
(pca-parity, whose moving mean of L samples has variance ``sum (1 + A_i) / L^2``).
Measured on the MIMU4444 motion residuals, a per-chip rank-one jitter covariance
(``sigma_{t,k}^2 u_k u_k^T``, u_k the chip's own ``dm/dt``) explains almost none of the
residual (alarm rate 94 % in-sample), while a full learned spatial covariance does no better
than the isotropic one (docs/real-arrays.md): the residual in motion is spatially white.

``dm/dt`` is estimated causally by a backward difference of consecutive samples (actual
time stamps): the row of sample i depends on samples i - 1 and i only. ``sigma_t`` is
fitted by ``imufdi calibrate`` on the motion of a log (:func:`fit_jitter`: by default so
that the per-sample test holds its level alpha = 1 % there, or by moments) and stored per
sensor type in ArrayConfig ``[jitter]``. With
``sigma_t = 0`` nothing is computed and the tests are unchanged (bit-identical).

The price is sensitivity in motion: a step f on sensor j has non-centrality
``(f / sigma_j)^2 P_jj / (1 + A_t)``, so the smallest detectable step grows with
``sqrt(1 + A_t)`` (:func:`minimum_detectable_step`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.maths.quantiles import chi2


def consensus_projector(h_white: np.ndarray) -> np.ndarray:
    """``F = H_w H_w^+`` (n, n): the consensus (least-squares) prediction of every sensor."""
    return np.asarray(h_white @ np.linalg.pinv(h_white))


class MotionInflation:
    """Streaming variance factor ``1 + A_t`` of one sensor type (module docstring).

    Parameters
    ----------
    h_white : ndarray, shape (n, q)
        Whitened design ``H / sigma`` (directions, plus lever-arm columns).
    sigma : ndarray, shape (n,)
        Per-sensor noise sigma, SI.
    jitter_s : float
        ``sigma_t``, seconds (> 0).
    rate_hz : float
        Nominal sample rate: the time step where time stamps do not give one.
    window : int
        Average the factors over this many samples (the variance factor of a moving mean
        of the measurements over that window); 1: per sample.
    """

    def __init__(
        self,
        h_white: np.ndarray,
        sigma: np.ndarray,
        jitter_s: float,
        rate_hz: float,
        window: int = 1,
    ) -> None:
        projector = consensus_projector(h_white)
        self.projector_t = projector.T.copy()
        self.noise_rank = float(round(float(np.trace(projector))))
        self.inverse_sigma = 1.0 / np.asarray(sigma, float)
        self.jitter_s = float(jitter_s)
        self.rate_hz = float(rate_hz)
        self.n = int(h_white.shape[0])
        self.window = max(1, int(window))
        self._last_values: np.ndarray | None = None
        self._last_t_ns: int | None = None
        self._history = np.zeros(0)

    def reset(self) -> None:
        """Forget the previous samples (start of a new stream)."""
        self._last_values = None
        self._last_t_ns = None
        self._history = np.zeros(0)

    def factors(self, values: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
        """``1 + A_t`` (N,) for measurements ``values`` (N, n), SI, at times ``t_ns`` (N,),
        averaged over the last ``window`` samples (fewer at the start of the stream).

        The first sample of a stream has no predecessor: A = 0 there. Non-finite
        differences (invalid samples) give A = 0.
        """
        n_samples = values.shape[0]
        if n_samples == 0:
            return np.ones(0)
        white = values * self.inverse_sigma
        t = np.asarray(t_ns, dtype=np.int64)
        if self._last_values is None:
            previous_values, previous_t = white[:1], t[:1]
        else:
            previous_values = self._last_values[None, :]
            previous_t = np.array([self._last_t_ns], dtype=np.int64)
        before = np.concatenate([previous_values, white[:-1]])
        before_t = np.concatenate([previous_t, t[:-1]])
        dt = (t - before_t) * 1e-9
        dt = np.where(np.isfinite(dt) & (dt > 0), dt, 1.0 / self.rate_hz)
        with np.errstate(invalid="ignore", over="ignore"):
            rate = ((white - before) @ self.projector_t) / dt[:, None]
            energy = np.einsum("ij,ij->i", rate, rate) - 2.0 * self.noise_rank / dt**2
        energy = np.where(np.isfinite(energy), np.maximum(energy, 0.0) / self.n, 0.0)
        self._last_values = white[-1].copy()
        self._last_t_ns = int(t[-1])
        factors = 1.0 + self.jitter_s**2 * energy
        if self.window == 1:
            return factors
        extended = np.concatenate([self._history, factors])
        cumulative = np.concatenate([[0.0], np.cumsum(extended)])
        ends = np.arange(self._history.size + 1, extended.size + 1)
        starts = np.maximum(ends - self.window, 0)
        self._history = extended[-(self.window - 1) :].copy()
        return np.asarray((cumulative[ends] - cumulative[starts]) / (ends - starts))


def array_inflation(
    array: ArrayConfig, sensor_type: str, design: np.ndarray, window: int = 1
) -> MotionInflation | None:
    """The jitter model of a sensor type from an array config: its ``[jitter]`` sigma_t and
    per-sensor noise (``<type>_noise`` or ``noise.<type>``); None when either is missing
    or sigma_t is 0 (no motion term: the caller's test is unchanged)."""
    jitter_s = float(array.jitter.get(sensor_type, 0.0))
    sigma = array.sensor_noise(sensor_type)
    if jitter_s <= 0 or sigma is None:
        return None
    return MotionInflation(design / sigma[:, None], sigma, jitter_s, array.rate_hz, window)


#: Largest sigma_t a level fit may return (s): beyond it the test is blind in any motion.
MAX_JITTER_S = 0.1


def fit_jitter(
    h_white: np.ndarray,
    values_white: np.ndarray,
    t_s: np.ndarray,
    rows: np.ndarray,
    offset: np.ndarray | None = None,
    alpha: float | None = None,
) -> float:
    """Fit ``sigma_t`` (s) from whitened measurements in motion.

    ``D_t = |P (m_w,t - offset)|^2`` (q = n - rank H parity dimensions) and
    ``e_t`` as in :class:`MotionInflation` on the selected rows.

    - ``alpha=None`` (moments): under the model ``E[D_t] = q (1 + sigma_t^2 e_t)``, so
      ``sigma_t^2 = sum_t (D_t - q) / (q sum_t e_t)`` (clipped at 0). Matches the mean;
      on real motion residuals, whose per-sample variance is a scale mixture, the tail
      is heavier than chi2 and the test exceeds its level.
    - ``alpha`` given (level): the smallest ``sigma_t`` whose per-sample test
      ``D_t / (1 + sigma_t^2 e_t) > chi2_{1-alpha}(q)`` exceeds on a share ``alpha`` of the
      rows (0 when the plain test already holds the level; :data:`MAX_JITTER_S` when no
      value does): a quantile fit, for the tail the test uses.

    In memory: :func:`jitter_rows` of the rows, then :func:`fit_jitter_rows` (``imufdi
    calibrate`` streams the rows through the same two).

    Parameters
    ----------
    h_white : ndarray, shape (n, q_cols)
    values_white : ndarray, shape (N, n)
        Calibrated measurements divided by each sensor's noise sigma.
    t_s : ndarray, shape (N,)
        Time stamps, s.
    rows : ndarray, shape (N,), bool
        Rows to use: moving, not clipped, and whose predecessor is usable (row 0 never is).
    offset : ndarray, shape (n,), optional
        Whitened per-sensor offsets to remove (e.g. the residual mean at rest).
    """
    use = np.asarray(rows, bool).copy()
    use[0] = False
    index = np.flatnonzero(use)
    dof = jitter_dof(h_white)
    if index.size == 0 or dof <= 0:
        return 0.0
    statistic, energy = jitter_rows(
        h_white, values_white[index], values_white[index - 1], t_s[index] - t_s[index - 1], offset
    )
    return fit_jitter_rows(lambda: iter([(statistic, energy)]), dof, alpha)


def jitter_dof(h_white: np.ndarray) -> int:
    """Parity dimensions ``n - rank H`` of a whitened design."""
    return int(h_white.shape[0] - int(np.linalg.matrix_rank(h_white)))


def jitter_rows(
    h_white: np.ndarray,
    current: np.ndarray,
    previous: np.ndarray,
    dt: np.ndarray,
    offset: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The statistic ``D_t`` (k,) and motion energy ``e_t`` (k,) of :func:`fit_jitter` for
    rows of whitened measurements ``current`` (k, n), each with its predecessor
    ``previous`` (k, n), ``dt`` (k,) s apart."""
    n = h_white.shape[0]
    projector = consensus_projector(h_white)
    rate = ((current - previous) @ projector.T) / dt[:, None]
    noise_rank = float(round(float(np.trace(projector))))
    energy = np.maximum(np.einsum("ij,ij->i", rate, rate) - 2.0 * noise_rank / dt**2, 0.0) / n
    centred = current if offset is None else current - offset
    residual = centred - centred @ projector.T
    return np.einsum("ij,ij->i", residual, residual), energy


def fit_jitter_rows(
    chunks: Callable[[], Iterable[tuple[np.ndarray, np.ndarray]]],
    dof: int,
    alpha: float | None = None,
) -> float:
    """:func:`fit_jitter` from its rows' ``(D_t, e_t)``, given as a function returning
    them in chunks (called once per evaluation of the level fit: the rows may be read
    from a file each time)."""
    if alpha is not None:
        threshold = float(chi2.ppf(1.0 - alpha, dof))

        def excess_rate(jitter_s: float) -> float:
            over, total = 0, 0
            for statistic, energy in chunks():
                over += int(np.count_nonzero(statistic / (1.0 + jitter_s**2 * energy) > threshold))
                total += int(statistic.size)
            return over / total - alpha

        if excess_rate(0.0) <= 0:
            return 0.0
        if excess_rate(MAX_JITTER_S) > 0:
            return MAX_JITTER_S
        from scipy.optimize import brentq  # imported when a root is needed (0.35 s of CPU)

        return float(brentq(excess_rate, 0.0, MAX_JITTER_S, xtol=1e-9))
    excess = drive = 0.0
    for statistic, energy in chunks():
        excess += float(np.sum(statistic - dof))
        drive += float(np.sum(energy))
    if drive <= 0 or excess <= 0:
        return 0.0
    return float(np.sqrt(excess / (dof * drive)))


def minimum_detectable_step(
    energy: float, dof: int, alpha: float, factor: float = 1.0, power: float = 0.5
) -> float:
    """Smallest step (in units of the sensor's sigma) that a per-sample chi2 test of
    ``dof`` degrees of freedom at level ``alpha``, widened by ``factor = 1 + A``, detects
    with probability ``power``: non-centrality ``f^2 P_jj / factor`` (``energy = P_jj``)."""
    from scipy.optimize import brentq
    from scipy.stats import ncx2  # an analysis function: keep scipy.stats off import

    threshold = float(chi2.ppf(1.0 - alpha, dof))

    def gap(nc: float) -> float:
        return float(ncx2.sf(threshold, dof, nc)) - power

    if gap(1e-9) >= 0:
        return 0.0
    nc = brentq(gap, 1e-9, 1e6)
    return float(np.sqrt(nc * factor / energy))
