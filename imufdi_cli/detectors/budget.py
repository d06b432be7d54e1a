"""The sequential test of a parity detector under a false-alarm budget.

With ``false_alarms`` > 0 (``imufdi detect --false-alarms 1/h``) the parity detectors
decide by a bank of robust CUSUM tests (:mod:`imufdi_cli.maths.sequential`) instead of a
per-sample test: per sensor i the evidence is its whitened parity residual divided by
its own standard deviation,

    z_t,i = r_t,i / sqrt(P_ii (1 + A_t)),   r_t = P m_w,t,  P = I - H_w H_w^+

(``m_w`` the measurements minus the calibrated biases, over the per-sensor sigma; ``A_t``
the motion term of :mod:`.jitter` when the array config has one), so that a step f on
sensor i shifts ``z_i`` by ``f sqrt(P_ii) / sigma_i`` (its *sensitivity*), and the
log-likelihood ratio of that hypothesis given the whole parity vector is the CUSUM
increment of column i. The threshold is set from the budget (episodes per second, per
status channel) by the bank's union bound; the long-run variance factor of the
calibration window's evidence widens it for correlated noise.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import DetectionBlock
from imufdi_cli.errors import DetectorConfigError
from imufdi_cli.maths.sequential import (
    CusumBank,
    CusumDesign,
    LeakModel,
    average_run_length,
    budget_threshold,
    long_run_factor,
    outlier_share,
)

#: Default time constant of the slow bias reference under a budget, seconds.
REFERENCE_TAU_S = 60.0
#: Sensors whose parity energy P_ii is below this carry no evidence (not testable).
MIN_ENERGY = 1e-9
#: Prior standard deviation of a motion-leak coefficient (z units per regressor unit, the
#: regressors being the body-frame estimate in units of the sensors' rms sigma): about the
#: relative scale-factor plus misalignment error of a sensor, 2 %
#: (:class:`MotionRegressors`).
LEAK_PRIOR = 0.02
#: The threshold is set for this share of the budget: the union bound is close to the
#: rate for white Gaussian evidence (0.9 of it measured), and what the model knows only
#: approximately -- each log's own sigma errors, outliers, the correlated noise and wander
#: of real boards -- must not make a budget a user relies on a promise broken.
BUDGET_SHARE = 0.5


def reference_tau(track_bias: float | None) -> float:
    """The bank's reference time constant: ``track_bias`` when given, else the default."""
    return REFERENCE_TAU_S if track_bias is None else float(track_bias)


def configured_noise(array: ArrayConfig, sensor_type: str) -> np.ndarray | None:
    """Per-sensor noise sigma (n_s,) of the array config when every IMU carrying the type
    has its own ``<type>_noise`` (what ``imufdi calibrate`` measures over many
    orientations), else None; times ``sqrt(kappa_i)`` when every IMU also carries the
    healthy noise-variance spread kappa (``<type>_noise_spread``): a chip whose noise grows
    with the orientation keeps the budget at the top of its healthy range (the budget's
    evidence would otherwise be wider than N(0, 1) there, and a CUSUM is exponentially
    sensitive to that)."""
    configured = array.sensor_noise(sensor_type)
    imus, _ = array.sensor_index(sensor_type)
    if configured is None or not all(
        sensor_type in array.imus[k].noise for k in set(imus.tolist())
    ):
        return None
    sigma = np.asarray(configured, float)
    spread = array.sensor_noise_spread(sensor_type)
    return sigma if spread is None else sigma * np.sqrt(np.asarray(spread, float))


class MotionRegressors:
    """The motion regressors of the leak model: the body-frame estimate ``x = H^+ m`` of a
    sensor type (first three components: the rate or the specific force at the reference
    point), centred on the calibration window's mean, in units of the sensors' rms sigma.

    A relative scale or misalignment error s of sensor i leaks ``s h_i^T x`` into its
    measurement, about ``s |x| / sigma`` standard deviations: in these units a leak
    coefficient is about s (:data:`LEAK_PRIOR`). The estimate is the weighted least
    squares one (weights ``1 / sigma^2``): its noise is then uncorrelated with the parity
    residuals of independent sensors, so that the calibration's fit of the leak does not
    read the noise of a noisy sensor, which the unweighted estimate carries, as a leak.

    Parameters
    ----------
    design : ndarray, shape (n, q)
        H (lever-arm columns after the first three).
    sigma : ndarray, shape (n,)
        Per-sensor noise sigma, SI.
    """

    def __init__(self, design: np.ndarray, sigma: np.ndarray) -> None:
        sigma = np.asarray(sigma, float)
        weighted = np.linalg.pinv(np.asarray(design, float) / sigma[:, None]) / sigma[None, :]
        self.estimator_t = weighted[:3].T.copy()  # (n, 3): x_hat = m @ it
        self.unit = float(np.sqrt(np.mean(sigma**2))) or 1.0
        self.centre = np.zeros(3)

    def fit(self, measurements: np.ndarray) -> np.ndarray:
        """Centre on the calibration window's rows (N, n); returns their regressors."""
        motion = np.asarray(measurements, float) @ self.estimator_t
        self.centre = motion.mean(axis=0)
        return (motion - self.centre) / self.unit

    def __call__(self, measurements: np.ndarray) -> np.ndarray:
        """Regressors (N, 3) of rows of measurements (N, n)."""
        return (np.asarray(measurements, float) @ self.estimator_t - self.centre) / self.unit


class EvidenceBudget:
    """Budgeted sequential decisions over one status channel's standardized evidence.

    What every detector shares under a budget: the detector computes, per sample and
    sensor, signed evidence z (N(0, 1) without fault, shifted by ``g_i f`` by a step f on
    sensor i); this class sets the bank's threshold for :data:`BUDGET_SHARE` of the budget
    from the calibration window's evidence (its long-run variance factor and outlier
    share), runs the bank, and reports its decisions as a DetectionBlock.

    Parameters
    ----------
    sensitivity : ndarray, shape (n,)
        ``g_i``, z units per SI unit of a step on sensor i (0: sensor not testable).
    isolable : ndarray, shape (n,), bool
    rate_hz : float
    budget_per_s : float
        False alarm episodes per second of fault-free data allowed on this channel.
    tau_s : float
        Time constant of the slow bias reference (0: none).
    design : CusumDesign, optional
    scale_variance : float, optional
        Variance of ``sigma_hat^2 / sigma^2`` of the evidence's scale when it was estimated
        (None: known); the threshold allows for it
        (:func:`~imufdi_cli.maths.sequential.false_alarm_rate`).
    calibration_samples : int, optional
        Samples the biases were estimated from (None: known biases).
    hypotheses_sensors : int, optional
        Sensors counted by the union bound (default n).
    """

    def __init__(
        self,
        sensitivity: np.ndarray,
        isolable: np.ndarray,
        rate_hz: float,
        budget_per_s: float,
        tau_s: float,
        design: CusumDesign | None = None,
        *,
        scale_variance: float | None = None,
        calibration_samples: int | None = None,
        hypotheses_sensors: int | None = None,
    ) -> None:
        if not rate_hz > 0:
            raise DetectorConfigError("a false-alarm budget needs the array's sample rate")
        per_sample = BUDGET_SHARE * budget_per_s / rate_hz
        if not 0.0 < per_sample < 0.5:
            raise DetectorConfigError(
                f"false-alarm budget {budget_per_s * 3600:g}/h is not below half the sample"
                f" rate ({rate_hz:g} Hz); give a rate such as 1/h"
            )
        self.design = design or CusumDesign(tau_s=tau_s)
        self.rate_hz = float(rate_hz)
        self.budget_per_s = float(budget_per_s)
        self.sensitivity = np.asarray(sensitivity, float)
        self.isolable = np.asarray(isolable, bool) & (self.sensitivity > 0)
        self.n = int(self.sensitivity.size)
        self.hypotheses_sensors = self.n if hypotheses_sensors is None else int(hypotheses_sensors)
        self.scale_variance = float(scale_variance or 0.0)
        self.calibration_samples = math.inf if calibration_samples is None else calibration_samples
        self.per_sample = per_sample
        self.contamination = 0.0
        self.threshold = math.nan  # set by fit()
        self.bank: CusumBank | None = None

    @property
    def testable(self) -> np.ndarray:
        """(n,) bool: sensors with evidence."""
        return self.sensitivity > 0

    def fit(
        self,
        z: np.ndarray,
        regressors: np.ndarray | None = None,
        long_run: float | None = None,
    ) -> None:
        """Start the bank from the calibration window's evidence ``z`` (N, n): its
        long-run variance factor, outlier share and the threshold. With ``regressors``
        (N, r) (the window's motion, centred, in the units :meth:`decide` will get), the
        motion leak is fitted on them under the prior :data:`LEAK_PRIOR` first
        (:class:`~imufdi_cli.maths.sequential.LeakModel`) and learnt online after.
        ``long_run``: the evidence's long-run variance factor when the detector knows it
        (None: measured on ``z``, :func:`~imufdi_cli.maths.sequential.long_run_factor`);
        ``z`` may then have no rows (no outliers counted)."""
        z = np.asarray(z, float)
        leak: LeakModel | None = None
        if regressors is not None:
            regressors = np.asarray(regressors, float)
            prior = np.eye(regressors.shape[1]) / LEAK_PRIOR**2
            leak, z = LeakModel.fit(z, regressors, prior)
        z = z[:, self.testable]
        kappa = long_run_factor(z, self.design.block) if long_run is None else float(long_run)
        self.contamination = outlier_share(z / math.sqrt(kappa))
        self.threshold = budget_threshold(
            self.design,
            self.hypotheses_sensors,
            self.per_sample,
            self.scale_variance,
            self.contamination,
        )
        self.bank = CusumBank(
            self.design,
            self.threshold,
            self.sensitivity,
            self.isolable,
            self.rate_hz,
            kappa=kappa,
            calibration_samples=self.calibration_samples,
            leak=leak,
        )

    def decide(self, z: np.ndarray, regressors: np.ndarray | None = None) -> DetectionBlock:
        """Decisions on evidence ``z`` (N, n) (and the rows' regressors with a leak model)."""
        if self.bank is None:
            raise DetectorConfigError("call fit() before process()")
        decisions = self.bank.process(z, regressors)
        return DetectionBlock(
            statistic=decisions.statistic,
            threshold=decisions.threshold,
            alarm=decisions.alarm,
            isolated=decisions.isolated,
            amplitude=decisions.amplitude,
            scores=decisions.scores,
        )

    def metadata(self) -> dict[str, Any]:
        """The budget, the threshold and what sets it; per sensor the sensitivity (z
        units per SI unit of a step: the reference delays need it)."""
        bank = self.bank
        run_lengths = (
            [average_run_length(mu, self.design.clip, self.threshold) for mu in self.design.shifts]
            if bank is not None
            else []
        )
        meta: dict[str, Any] = {
            "false_alarms_per_hour": self.budget_per_s * 3600.0,
            "threshold": self.threshold,
            "design_shifts": list(self.design.shifts),
            "clip": self.design.clip,
            "scale_variance": self.scale_variance,
            "outlier_share": self.contamination,
            "reference_tau_s": self.design.tau_s,
            "long_run_factor": None if bank is None else bank.kappa,
            "hypotheses": 2 * self.hypotheses_sensors * len(self.design.shifts),
            "run_length_samples": run_lengths,
            "sensitivity": (self.sensitivity if bank is None else bank.sensitivity).tolist(),
            "episodes": 0 if bank is None else bank.episodes,
        }
        if bank is not None and bank.leak is not None:
            assert bank.slopes is not None and bank.inverse is not None
            meta["leak"] = {
                "regressors": bank.leak.regressors,
                "tau_s": self.design.leak_tau_s,
                "allowance_scale": bank.allowance_scale,
                # per regressor unit, in z units: fitted in calibration, then learnt online
                "calibration_coefficients": bank.leak.coefficients.tolist(),
                "online_coefficients": (bank.slopes * math.sqrt(bank.kappa)).tolist(),
                "coefficient_sd": np.sqrt(np.diag(bank.inverse)).tolist(),
            }
        return meta


class ParityBudget(EvidenceBudget):
    """Budgeted sequential decisions over one sensor type's parity residual.

    Parameters
    ----------
    h_white : ndarray, shape (n, q)
        Whitened design ``H / sigma`` of the active sensors (lever-arm columns included).
    sigma : ndarray, shape (n,)
        Per-sensor noise sigma, SI.
    isolable : ndarray, shape (n,), bool
    rate_hz : float
    budget_per_s : float
        False alarm episodes per second of fault-free data allowed on this channel.
    tau_s : float
        Time constant of the slow bias reference (0: none).
    design : CusumDesign, optional
    scale_variance : float, optional
        Variance of ``sigma_hat^2 / sigma^2`` when sigma was estimated (None: known);
        the threshold allows for it (:func:`~imufdi_cli.maths.sequential.false_alarm_rate`).
    calibration_samples : int, optional
        Samples the biases were estimated from (None: known biases).
    """

    def __init__(
        self,
        h_white: np.ndarray,
        sigma: np.ndarray,
        isolable: np.ndarray,
        rate_hz: float,
        budget_per_s: float,
        tau_s: float,
        design: CusumDesign | None = None,
        *,
        scale_variance: float | None = None,
        calibration_samples: int | None = None,
    ) -> None:
        h_white = np.asarray(h_white, float)
        energy = 1.0 - np.einsum("ij,ji->i", h_white, np.linalg.pinv(h_white))
        testable = energy > MIN_ENERGY
        super().__init__(
            np.where(testable, np.sqrt(np.maximum(energy, 0.0)), 0.0) / sigma,
            np.asarray(isolable, bool) & testable,
            rate_hz,
            budget_per_s,
            tau_s,
            design,
            scale_variance=scale_variance,
            calibration_samples=calibration_samples,
        )
        self.estimator_t = np.linalg.pinv(h_white).T.copy()  # (n, q): x_hat = m_w @ it
        self.h_t = h_white.T.copy()
        self.z_scale = np.where(testable, 1.0 / np.sqrt(np.where(testable, energy, 1.0)), 0.0)
        self.residual_sd = np.sqrt(np.maximum(energy, 0.0)) * sigma  # SI, per unit z

    def evidence(self, white: np.ndarray, factors: np.ndarray | None = None) -> np.ndarray:
        """z (N, n) of whitened, bias-free measurements ``white`` (N, n); ``factors`` (N,):
        the motion variance factors ``1 + A_t`` (None: 1)."""
        residual = white - (white @ self.estimator_t) @ self.h_t
        residual *= self.z_scale
        if factors is not None:
            residual /= np.sqrt(factors)[:, None]
        return residual

    def fit(self, white: np.ndarray, regressors: np.ndarray | None = None) -> None:  # type: ignore[override]
        """Start the bank, with the long-run variance factor of the calibration window's
        evidence (``white``: its whitened, bias-free measurements, (N, n))."""
        super().fit(self.evidence(white), regressors)

    def process(self, white: np.ndarray, factors: np.ndarray | None = None) -> DetectionBlock:
        """Decisions on whitened, bias-free measurements (N, n)."""
        if self.bank is None:
            raise DetectorConfigError("call fit() before process()")
        return self.decide(self.evidence(white, factors))

    def metadata(self) -> dict[str, Any]:
        meta = super().metadata()
        bank = self.bank
        # the reference's offsets, as residuals in SI (what the bank removed at the end)
        meta["reference_residual"] = (
            []
            if bank is None
            else (bank.reference * math.sqrt(bank.kappa) * self.residual_sd).tolist()
        )
        return meta
