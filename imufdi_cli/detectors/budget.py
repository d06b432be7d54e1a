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

from imufdi_cli.detectors.base import DetectionBlock
from imufdi_cli.errors import DetectorConfigError
from imufdi_cli.maths.sequential import (
    CusumBank,
    CusumDesign,
    MotionModel,
    budget_threshold,
    long_run_factor,
    outlier_share,
)

#: Default time constant of the slow bias reference under a budget, seconds.
REFERENCE_TAU_S = 60.0
#: Sensors whose parity energy P_ii is below this carry no evidence (not testable).
MIN_ENERGY = 1e-9
#: Default relative scale and misalignment error of each sensor left by calibration: the
#: prior of the motion model (a residual proportional to the rate or specific force).
MOTION_ERROR = 1e-3
#: Time constant of the motion model's forgetting, seconds (chip scale errors are stable).
SLOPE_TAU_S = 600.0
#: The threshold is set for this share of the budget: the union bound is close to the
#: rate for white Gaussian evidence (0.9 of it measured), and what the model knows only
#: approximately -- each log's own sigma errors, outliers, the correlated noise and wander
#: of real boards -- must not make a budget a user relies on a promise broken.
BUDGET_SHARE = 0.5


def reference_tau(track_bias: float | None) -> float:
    """The bank's reference time constant: ``track_bias`` when given, else the default."""
    return REFERENCE_TAU_S if track_bias is None else float(track_bias)


class ParityBudget:
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
    motion_error : float
        Relative scale and misalignment error of each sensor (dimensionless): the prior of
        the motion model, which learns and removes the part of each sensor's evidence that
        is proportional to the tested state (rate for gyros, specific force for
        accelerometers) and widens the test by what it does not know yet; 0: no model.
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
        motion_error: float = MOTION_ERROR,
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
        h_white = np.asarray(h_white, float)
        self.estimator_t = np.linalg.pinv(h_white).T.copy()  # (n, q): x_hat = m_w @ it
        self.h_t = h_white.T.copy()
        energy = 1.0 - np.einsum("ij,ji->i", h_white, np.linalg.pinv(h_white))
        testable = energy > MIN_ENERGY
        self.z_scale = np.where(testable, 1.0 / np.sqrt(np.where(testable, energy, 1.0)), 0.0)
        self.sensitivity = np.where(testable, np.sqrt(np.maximum(energy, 0.0)), 0.0) / sigma
        self.isolable = np.asarray(isolable, bool) & testable
        self.residual_sd = np.sqrt(np.maximum(energy, 0.0)) * sigma  # SI, per unit z
        self.motion_error = float(motion_error)
        # a relative error e on sensor i's axis puts e |x| / sigma_i into its whitened
        # measurement, sqrt(P_ii) of it into z_i: the prior sd per unit of the state
        self.motion_prior = float(np.median(np.sqrt(np.maximum(energy, 0.0)) / sigma))
        self.n = int(h_white.shape[0])
        self.scale_variance = float(scale_variance or 0.0)
        self.calibration_samples = math.inf if calibration_samples is None else calibration_samples
        self.per_sample = per_sample
        self.contamination = 0.0
        self.threshold = math.nan  # set by fit()
        self.bank: CusumBank | None = None

    def evidence(self, white: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """z (N, n) of whitened, bias-free measurements ``white`` (N, n), standardized at
        rest, and the tested state (N, 3): the least-squares rate or specific force."""
        state = white @ self.estimator_t
        residual = white - state @ self.h_t
        residual *= self.z_scale
        return residual, state[:, :3]

    def fit(self, white: np.ndarray) -> None:
        """Start the bank, with the long-run variance factor of the calibration window's
        evidence (``white``: its whitened, bias-free measurements, (N, n))."""
        evidence, state = self.evidence(white)
        z = evidence[:, self.z_scale > 0]
        kappa = long_run_factor(z, self.design.block)
        self.contamination = outlier_share(z / math.sqrt(kappa))
        self.threshold = budget_threshold(
            self.design, self.n, self.per_sample, self.scale_variance, self.contamination
        )
        motion = None
        if self.motion_error > 0:
            scale = 1.0 / math.sqrt(kappa)  # the bank's own units
            motion = MotionModel.from_calibration(
                state,
                evidence * scale,
                self.motion_error * self.motion_prior * scale,
                SLOPE_TAU_S * self.rate_hz,
            )
        self.bank = CusumBank(
            self.design,
            self.threshold,
            self.sensitivity,
            self.isolable,
            self.rate_hz,
            kappa=kappa,
            calibration_samples=self.calibration_samples,
            motion=motion,
        )

    def process(self, white: np.ndarray, factors: np.ndarray | None = None) -> DetectionBlock:
        """Decisions on whitened, bias-free measurements (N, n)."""
        if self.bank is None:
            raise DetectorConfigError("call fit() before process()")
        evidence, state = self.evidence(white)
        decisions = self.bank.process(evidence, state, factors)
        return DetectionBlock(
            statistic=decisions.statistic,
            threshold=decisions.threshold,
            alarm=decisions.alarm,
            isolated=decisions.isolated,
            amplitude=decisions.amplitude,
            scores=decisions.scores,
        )

    def metadata(self) -> dict[str, Any]:
        """The budget, the threshold and what sets it; what the optimal test's reference
        delay needs (Lorden: ``2 ln(gamma K) / delta^2`` samples, with ``gamma`` the
        samples between false alarms at the budget, K the sensor-and-sign hypotheses and
        ``delta`` a step's size times the sensor's ``sensitivity``, z units per SI unit)."""
        bank = self.bank
        return {
            "false_alarms_per_hour": self.budget_per_s * 3600.0,
            "threshold": self.threshold,
            "design_shifts": list(self.design.shifts),
            "clip": self.design.clip,
            "scale_variance": self.scale_variance,
            "motion_error": self.motion_error,
            "outlier_share": self.contamination,
            "reference_tau_s": self.design.tau_s,
            "long_run_factor": None if bank is None else bank.kappa,
            "hypotheses": 2 * self.n,
            "run_length_samples": self.rate_hz / self.budget_per_s,
            "sensitivity": (self.sensitivity if bank is None else bank.sensitivity).tolist(),
            "episodes": 0 if bank is None else bank.episodes,
            # the reference's offsets, as residuals in SI (what the bank removed at the end)
            "reference_residual": []
            if bank is None
            else (bank.reference * math.sqrt(bank.kappa) * self.residual_sd).tolist(),
        }
