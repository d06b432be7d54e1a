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

import dataclasses
import math
from typing import Any

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import DetectionBlock, Param
from imufdi_cli.errors import DetectorConfigError, UnitError
from imufdi_cli.maths.sequential import (
    CusumBank,
    CusumDesign,
    MotionModel,
    budget_threshold,
    long_run_factor,
    outlier_share,
    outlier_size,
)

#: Default time constant of the slow bias reference under a budget, seconds.
REFERENCE_TAU_S = 60.0
#: Default longest time an episode keeps the references frozen, seconds.
HOLD_S = 10.0
#: The ``hold`` value that keeps them frozen until the episode ends.
LATCH = "latch"


#: Sensor types whose noise variance in motion the bank takes from each row's own evidence
#: (``CusumBank(spatial=True)``) when the array has a jitter model: the MIMU4444
#: accelerometers' motion residual is white in time with a size that changes from row to
#: row alike on every sensor (autocorrelation -0.05 to -0.03 at lag 1, within 0.013 at lags
#: 2-10, once each row is scaled by its own spread); the gyros' is correlated over tens of
#: rows (lag-1 autocorrelation 0.29-0.33), which a per-row scale does not cover, so they
#: keep the jitter model (docs/real-arrays.md).
SPATIAL_TYPES = frozenset({"accel"})


def hold_seconds(value: str) -> float:
    """An episode's hold in seconds from a ``hold`` parameter: a time (``10s``) or
    ``latch`` (infinite); UnitError for anything else."""
    from imufdi_cli.units import parse_quantity

    if value.strip().lower() == LATCH:
        return math.inf
    seconds = parse_quantity(value, "time", name="hold")
    if not (math.isfinite(seconds) and seconds >= 0):
        raise UnitError(f"hold: must be a time >= 0 or {LATCH}, got {value!r}")
    return seconds


def _check_hold(value: str) -> str | None:
    try:
        hold_seconds(value)
    except UnitError:
        return f"{value!r} is not a time (e.g. 10s) or {LATCH}"
    return None


HOLD = Param(
    "str",
    "10s",
    "under a false-alarm budget: how long an episode keeps the bias references frozen (a"
    " time), or latch: until the fault ends (a fault that lasts is never absorbed; a false"
    " alarm raised by bias wander lasts until the wander goes back)",
    check=_check_hold,
)
"""The ``hold`` parameter of the detectors whose sequential test tracks the biases."""


def check_hold(name: str, hold: str, false_alarms: float) -> float:
    """``hold`` in seconds; DetectorConfigError when it is set without a budget (the
    per-sample test has no episodes to hold)."""
    seconds = hold_seconds(hold)
    if false_alarms <= 0 and seconds != HOLD_S:
        raise DetectorConfigError(
            f"{name}.hold applies to the sequential test under a false-alarm budget: give"
            " --false-alarms (e.g. 1/h) or leave it out"
        )
    return seconds


#: Sensors whose parity energy P_ii is below this carry no evidence (not testable).
MIN_ENERGY = 1e-9
#: Default relative scale and misalignment error of each sensor left by calibration: the
#: prior of the motion model (a residual proportional to the rate or specific force).
MOTION_ERROR = 1e-3
#: Time constant of the motion model's forgetting, seconds (chip scale errors are stable).
SLOPE_TAU_S = 600.0
#: Long-run variance factor above which evidence counts as correlated (no variance
#: reference: it would learn the per-sample variance, not the long-run one).
CORRELATED = 1.5
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
    with the orientation keeps the budget at the top of its healthy range (the evidence
    would otherwise be wider than N(0, 1) there, and a CUSUM is exponentially sensitive to
    that)."""
    configured = array.sensor_noise(sensor_type)
    imus, _ = array.sensor_index(sensor_type)
    if configured is None or not all(
        sensor_type in array.imus[k].noise for k in set(imus.tolist())
    ):
        return None
    sigma = np.asarray(configured, float)
    spread = array.sensor_noise_spread(sensor_type)
    return sigma if spread is None else sigma * np.sqrt(np.asarray(spread, float))


def _per_sample(rate_hz: float, budget_per_s: float) -> float:
    """The bank's share of the budget per sample; DetectorConfigError where none exists."""
    if not rate_hz > 0:
        raise DetectorConfigError("a false-alarm budget needs the array's sample rate")
    per_sample = BUDGET_SHARE * budget_per_s / rate_hz
    if not 0.0 < per_sample < 0.5:
        raise DetectorConfigError(
            f"false-alarm budget {budget_per_s * 3600:g}/h is not below half the sample"
            f" rate ({rate_hz:g} Hz); give a rate such as 1/h"
        )
    return per_sample


class MotionState:
    """The tested state of the motion model for any detector's evidence: the weighted
    least-squares body-frame estimate ``x = (H^T W H)^-1 H^T W m`` (first three
    components: the rate, or the specific force at the reference point), SI.

    Weighted (``W = 1 / sigma^2``): its noise is then uncorrelated with the parity
    residuals of independent sensors, so that the calibration's fit of the model does not
    read the noise of a noisy sensor, which the unweighted estimate carries, as a scale
    error.

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
        self.estimator_t = weighted[:3].T.copy()  # (n, 3): x = m @ it

    def __call__(self, measurements: np.ndarray) -> np.ndarray:
        """States (N, 3) of rows of measurements (N, n), SI."""
        return np.asarray(measurements, float) @ self.estimator_t


class _BankBudget:
    """What both budgeted evidence models share: the budget's settings, the bank once
    fitted, its decisions as a DetectionBlock and the common part of the metadata."""

    def __init__(
        self,
        sensitivity: np.ndarray,
        isolable: np.ndarray,
        rate_hz: float,
        budget_per_s: float,
        tau_s: float,
        design: CusumDesign | None,
        scale_variance: float | None,
        calibration_samples: int | None,
        motion_error: float,
        hold_s: float = HOLD_S,
        moving: bool = False,
    ) -> None:
        self.per_sample = _per_sample(rate_hz, budget_per_s)
        self.moving = bool(moving)  # the detector passes motion factors (a jitter model)
        self.design = design or CusumDesign(tau_s=tau_s, hold_s=hold_s)
        self.rate_hz = float(rate_hz)
        self.budget_per_s = float(budget_per_s)
        self.sensitivity = np.asarray(sensitivity, float)
        self.isolable = np.asarray(isolable, bool)
        self.n = int(self.sensitivity.size)
        self.scale_variance = float(scale_variance or 0.0)
        self.calibration_samples = math.inf if calibration_samples is None else calibration_samples
        self.motion_error = float(motion_error)
        self.contamination = 0.0
        self.outlier = 0.0  # the outliers' median size, z units (the reference delays')
        self.threshold = math.nan  # set by fit()
        self.bank: CusumBank | None = None

    @property
    def threshold_contamination(self) -> float:
        """The outlier share the threshold allows for: the calibration's, and with motion
        factors at least ``design.motion_outliers`` (the bank's noise variance in motion
        is then the evidence's own, with heavy tails)."""
        if self.moving:
            return max(self.contamination, self.design.motion_outliers)
        return self.contamination

    def _measure_outliers(self, z: np.ndarray) -> None:
        """The outlier share (the threshold's) and size (the reference delays') of the
        calibration window's evidence ``z``, standardized by the long-run factor."""
        self.contamination = outlier_share(z)
        self.outlier = outlier_size(z)

    def _start(self, kappa: float, motion: MotionModel | None) -> None:
        """The threshold for the evidence's outlier share (``threshold_contamination``),
        then the bank."""
        self.threshold = budget_threshold(
            self.design, self.n, self.per_sample, self.scale_variance, self.threshold_contamination
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
            spatial=self.moving,
        )

    def _decide(
        self, z: np.ndarray, state: np.ndarray | None, factors: np.ndarray | None
    ) -> DetectionBlock:
        if self.bank is None:
            raise DetectorConfigError("call fit() before process()")
        decisions = self.bank.process(z, state, factors)
        return DetectionBlock(
            statistic=decisions.statistic,
            threshold=decisions.threshold,
            alarm=decisions.alarm,
            isolated=decisions.isolated,
            amplitude=decisions.amplitude,
            scores=decisions.scores,
        )

    def _metadata(self) -> dict[str, Any]:
        bank = self.bank
        return {
            "false_alarms_per_hour": self.budget_per_s * 3600.0,
            "threshold": self.threshold,
            "design_shifts": list(self.design.shifts),
            "clip": self.design.clip,
            "scale_variance": self.scale_variance,
            "motion_error": self.motion_error,
            "outlier_share": self.contamination,
            "outlier_size": self.outlier,
            # the rows' own spread in motion (the bank keeps the jitter model below
            # MIN_SPATIAL_COLUMNS sensors)
            "motion_scale": "spatial" if bank is not None and bank.spatial else None,
            "motion_outliers": self.design.motion_outliers if self.moving else None,
            "reference_tau_s": self.design.tau_s,
            "hold_s": None if math.isinf(self.design.hold_s) else self.design.hold_s,
            "long_run_factor": None if bank is None else bank.kappa,
            "hypotheses": 2 * self.n,
            "run_length_samples": self.rate_hz / self.budget_per_s,
            "sensitivity": (self.sensitivity if bank is None else bank.sensitivity).tolist(),
            "episodes": 0 if bank is None else bank.episodes,
        }


class ParityBudget(_BankBudget):
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
    moving : bool
        The detector passes the rows' motion variance factors (its array has a jitter
        model): the bank then takes the noise variance of the rows in motion from the
        evidence (``CusumBank(spatial=True)``) and the threshold allows for
        ``design.motion_outliers``.
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
        hold_s: float = HOLD_S,
        moving: bool = False,
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
            scale_variance,
            calibration_samples,
            motion_error,
            hold_s,
            moving,
        )
        self.estimator_t = np.linalg.pinv(h_white).T.copy()  # (n, q): x_hat = m_w @ it
        self.h_t = h_white.T.copy()
        self.z_scale = np.where(testable, 1.0 / np.sqrt(np.where(testable, energy, 1.0)), 0.0)
        self.residual_sd = np.sqrt(np.maximum(energy, 0.0)) * sigma  # SI, per unit z
        # a relative error e on sensor i's axis puts e |x| / sigma_i into its whitened
        # measurement, sqrt(P_ii) of it into z_i: the prior sd per unit of the state
        self.motion_prior = float(np.median(np.sqrt(np.maximum(energy, 0.0)) / sigma))

    def evidence(self, white: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """z (N, n) of whitened, bias-free measurements ``white`` (N, n), standardized at
        rest, and the tested state (N, 3): the least-squares rate or specific force."""
        state = white @ self.estimator_t
        residual = state @ self.h_t
        np.subtract(white, residual, out=residual)  # in place: no second (N, n) array
        residual *= self.z_scale
        return residual, state[:, :3]

    def fit(self, white: np.ndarray) -> None:
        """Start the bank, with the long-run variance factor of the calibration window's
        evidence (``white``: its whitened, bias-free measurements, (N, n))."""
        evidence, state = self.evidence(white)
        z = evidence[:, self.z_scale > 0]
        kappa = long_run_factor(z, self.design.block)
        self._measure_outliers(z / math.sqrt(kappa))
        motion = None
        if self.motion_error > 0:
            scale = 1.0 / math.sqrt(kappa)  # the bank's own units
            motion = MotionModel.from_calibration(
                state,
                evidence * scale,
                self.motion_error * self.motion_prior * scale,
                SLOPE_TAU_S * self.rate_hz,
            )
        self._start(kappa, motion)

    def process(self, white: np.ndarray, factors: np.ndarray | None = None) -> DetectionBlock:
        """Decisions on whitened, bias-free measurements (N, n)."""
        if self.bank is None:
            raise DetectorConfigError("call fit() before process()")
        evidence, state = self.evidence(white)
        return self._decide(evidence, state, factors)

    def metadata(self) -> dict[str, Any]:
        """The budget, the threshold and what sets it; what the optimal test's reference
        delay needs (Lorden: ``2 ln(gamma K) / delta^2`` samples, with ``gamma`` the
        samples between false alarms at the budget, K the sensor-and-sign hypotheses and
        ``delta`` a step's size times the sensor's ``sensitivity``, z units per SI unit)."""
        bank = self.bank
        return {
            **self._metadata(),
            # the reference's offsets, as residuals in SI (what the bank removed at the end)
            "reference_residual": []
            if bank is None
            else (bank.reference * math.sqrt(bank.kappa) * self.residual_sd).tolist(),
        }


class EvidenceBudget(_BankBudget):
    """Budgeted sequential decisions over one status channel's standardized evidence.

    What every detector shares under a budget: the detector computes, per sample and
    sensor, signed evidence z standardized at rest (N(0, 1) without fault, shifted by
    ``g_i f`` by a step f on sensor i); this class sets the bank's threshold for
    :data:`BUDGET_SHARE` of the budget from the calibration window's evidence (its long-run
    variance factor and outlier share), starts the motion model from the calibration
    window's states, and reports the bank's decisions as a DetectionBlock.
    :class:`ParityBudget` is the same for glt's parity evidence.

    Parameters
    ----------
    sensitivity : ndarray, shape (n,)
        ``g_i``, z units per SI unit of a step on sensor i (0: sensor not testable).
    isolable : ndarray, shape (n,), bool
    rate_hz, budget_per_s : float
    tau_s : float
        Time constant of the slow bias reference (0: none).
    design : CusumDesign, optional
    scale_variance : float, optional
        Variance of ``sigma_hat^2 / sigma^2`` of the evidence's scale when it was estimated
        (None: known); the threshold allows for it.
    calibration_samples : int, optional
        Samples the biases were estimated from (None: known biases).
    motion_error : float
        Relative scale and misalignment error of each sensor: the prior of the motion
        model, whose slopes are then ``motion_error`` times the typical sensitivity per SI
        unit of the state (a relative error e on a sensor puts ``e |x|`` into it, ``g e |x|``
        into its evidence); 0: no model.
    moving : bool
        The detector passes the rows' motion variance factors (its array has a jitter
        model): the bank then takes the noise variance of the rows in motion from the
        evidence (``CusumBank(spatial=True)``) and the threshold allows for
        ``design.motion_outliers``.
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
        motion_error: float = MOTION_ERROR,
        hold_s: float = HOLD_S,
        moving: bool = False,
    ) -> None:
        sensitivity = np.asarray(sensitivity, float)
        super().__init__(
            sensitivity,
            np.asarray(isolable, bool) & (sensitivity > 0),
            rate_hz,
            budget_per_s,
            tau_s,
            design,
            scale_variance,
            calibration_samples,
            motion_error,
            hold_s,
            moving,
        )
        testable = sensitivity[sensitivity > 0]
        self.motion_prior = float(np.median(testable)) if testable.size else 0.0

    @property
    def testable(self) -> np.ndarray:
        """(n,) bool: sensors with evidence."""
        return self.sensitivity > 0

    def fit(
        self,
        z: np.ndarray,
        state: np.ndarray | None = None,
        long_run: float | None = None,
    ) -> None:
        """Start the bank from the calibration window's evidence ``z`` (N, n): its
        long-run variance factor, outlier share and the threshold; with ``state`` (N, p),
        the window's tested states, the motion model (:class:`MotionModel`). ``long_run``:
        the evidence's long-run variance factor when the detector knows it (None: measured
        on ``z``, :func:`~imufdi_cli.maths.sequential.long_run_factor`); ``z`` may then have
        no rows (no outliers counted)."""
        z = np.nan_to_num(np.asarray(z, float))
        modelled = state is not None and self.motion_error > 0 and z.shape[0] > 1
        free = z
        if modelled:
            # the long-run factor and outliers of the evidence without the motion the model
            # explains: a leak in the calibration window is slow, and would read as
            # correlated noise (a factor of 4-6 on conical6, which then hides small steps)
            first = MotionModel.from_calibration(
                np.asarray(state, float), z, self.motion_error * self.motion_prior, 1.0
            )
            free = z - (np.asarray(state, float) - first.centre) @ first.slopes
        tested = free[:, self.testable]
        kappa = long_run_factor(tested, self.design.block) if long_run is None else float(long_run)
        if long_run is not None or kappa > CORRELATED:
            # the variance reference learns the per-sample variance, which for correlated
            # evidence is not what the long-run factor standardized: keep the calibrated scale
            self.design = dataclasses.replace(self.design, scale_tau_s=0.0)
        self._measure_outliers(tested / math.sqrt(kappa))
        motion = None
        if modelled:
            scale = 1.0 / math.sqrt(kappa)  # the bank's own units
            motion = MotionModel.from_calibration(
                np.asarray(state, float),
                z * scale,
                self.motion_error * self.motion_prior * scale,
                SLOPE_TAU_S * self.rate_hz,
            )
        self._start(kappa, motion)

    def decide(
        self,
        z: np.ndarray,
        state: np.ndarray | None = None,
        factors: np.ndarray | None = None,
    ) -> DetectionBlock:
        """Decisions on evidence ``z`` (N, n) standardized at rest, with the rows' tested
        states (N, p) when the bank has a motion model and their motion variance factors
        ``v_t >= 1`` (None: 1)."""
        return self._decide(z, state, factors)

    def metadata(self) -> dict[str, Any]:
        """The budget, the threshold and what sets it; per sensor the sensitivity (z
        units per SI unit of a step: the reference delays need it)."""
        bank = self.bank
        return {
            **self._metadata(),
            "reference": [] if bank is None else (bank.reference * math.sqrt(bank.kappa)).tolist(),
            "tracked_variance": self.design.scale_tau_s > 0,
            **({} if bank is None else _motion_metadata(bank)),
        }


def _motion_metadata(bank: CusumBank) -> dict[str, Any]:
    """The motion model's slopes (z units per SI unit of the state, per sensor) and their
    posterior standard deviations, when the bank has one."""
    model = bank.ref.motion
    if model is None:
        return {}
    scale = math.sqrt(bank.kappa)
    return {
        "motion_slopes": (model.slopes * scale).tolist(),
        "motion_slope_sd": (np.sqrt(np.diag(model.covariance)) * scale).tolist(),
    }
