"""The bank detector: parameters and construction, fit (mode, noise, thresholds), the
per-block test of the accelerometer and magnetometer components, and metadata.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.attitude import (
    make_continuous,
)
from imufdi_cli.detectors.bank.array_mode import _ArrayTest, _fit_array_test
from imufdi_cli.detectors.bank.budget import ArrayBudget
from imufdi_cli.detectors.bank.gyro import _GyroTest
from imufdi_cli.detectors.bank.marg import FULL_ESTIMATOR, BankDetails, _MargModel
from imufdi_cli.detectors.bank.thresholds import _empty_block, bonferroni_threshold, robust_std
from imufdi_cli.detectors.base import (
    ALPHA,
    FALSE_ALARMS,
    NO_ISOLATION,
    DetectionBlock,
    DetectorBase,
    Param,
    calibration_stats,
)
from imufdi_cli.detectors.budget import (
    REFERENCE_TAU_S,
    SPATIAL_TYPES,
    EvidenceBudget,
    configured_noise,
)
from imufdi_cli.errors import CalibrationError, DetectorConfigError
from imufdi_cli.log import ImuBlock
from imufdi_cli.maths.jitter import array_inflation
from imufdi_cli.maths.rigid import accel_design


class BankDetector(_GyroTest, DetectorBase):
    """Bank of estimators with structured residuals (Berbra, Gentil, Lesecq).

    Parameters
    ----------
    alpha : float
        Per-sample false-alarm level of each tested sensor type (Bonferroni over residuals).
    mode : {"auto", "marg", "array"}
        ``auto``: ``marg`` for a single IMU with magnetometer, ``array`` otherwise.
    tau : float
        marg mode: time constant of the first-order filter of the gyro residuals, s.
    max_faults : int
        array mode: most simultaneous faulty sensors isolated per sensor type.
    iterations : int
        marg mode: most Gauss-Newton iterations per block.
    false_alarms : float
        False-alarm budget, episodes per second per status channel (0: the per-sample
        test at ``alpha``); positive: sequential decisions on the same residuals
        (:mod:`.budget`), several simultaneous faults isolated by exclusion.
    """

    name: ClassVar[str] = "bank"
    #: Causal: the row of sample i depends on samples up to i only.
    lookahead_samples: int = 0
    PARAMS: ClassVar[dict[str, Param]] = {
        "alpha": ALPHA,
        "mode": Param(
            "choice",
            "auto",
            "marg (one IMU with accel+mag+gyro) or array (leave-one-out bank); auto picks",
            choices=("auto", "marg", "array"),
        ),
        "tau": Param(
            "time", 0.5, "marg: time constant of the gyro residual filter", low=0.0, low_open=True
        ),
        "max_faults": Param(
            "int", 2, "array: simultaneous faulty sensors isolated per type", low=1, high=5
        ),
        "iterations": Param("int", 20, "marg: maximum Gauss-Newton iterations", low=1, high=50),
        "false_alarms": FALSE_ALARMS,
    }

    def __init__(
        self,
        alpha: float = 0.01,
        mode: str = "auto",
        tau: float = 0.5,
        max_faults: int = 2,
        iterations: int = 20,
        false_alarms: float = 0.0,
    ) -> None:
        self.false_alarms = float(false_alarms)
        self.alpha = float(alpha)
        self.mode = mode
        self.tau = float(tau)
        self.max_faults = int(max_faults)
        self.iterations = int(iterations)
        self.array: ArrayConfig | None = None
        self.resolved_mode: str | None = None
        self.tests: dict[str, _ArrayTest] = {}
        self.budgets: dict[str, ArrayBudget] = {}  # array mode under a budget
        self.last_details: BankDetails | None = None
        # marg state
        self._model: _MargModel | None = None
        self._marg_threshold = math.inf
        self._gyro_bias: np.ndarray | None = None
        self._gyro_variance: np.ndarray | None = None
        self._bias_weight_energy = 0.0
        self._gyro_threshold = math.inf
        self._filter_pole = 0.0
        self._sample_period = 0.0
        self._gyro_H: np.ndarray | None = None
        self._gyro_chosen = np.zeros(0, dtype=np.intp)
        self._marg_budget: EvidenceBudget | None = None  # marg under a budget
        self._marg_offset = np.zeros(6)
        self._gyro_budget: EvidenceBudget | None = None
        self._reset_stream()

    # --- streaming state ---------------------------------------------------------------

    def _reset_stream(self) -> None:
        self._q_last: np.ndarray | None = None  # (7, 4)
        self._gyro_last: np.ndarray | None = None  # (n_g,)
        self._t_last: int | None = None
        self._filter_state: np.ndarray | None = None  # (7, 1, n_g)
        self._episode_counts = np.zeros(6)  # accel/mag isolations in the current alarm
        # under a budget: fit-cost sums and counts of the current accel/mag episode
        self._episode_cost = (np.zeros(6), np.zeros(6))
        self._variance_state: np.ndarray | None = None  # (7, 1, n_g)
        self._gyro_integral = np.zeros(0)  # (n_g,) running gyro integral, rad
        self._t_origin = 0  # ns, origin of the float times below
        # per estimator: attitude, gyro integral and time of its last clean sample
        self._clean_q = np.tile([1.0, 0.0, 0.0, 0.0], (7, 1))
        self._clean_integral = np.zeros((7, 0))
        self._clean_t = np.full(7, np.nan)

    # --- fit ---------------------------------------------------------------------------

    def fit(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        """Calibrate residual biases, noise and thresholds on a fault-free block."""
        self.array = array
        mode = self.mode
        if mode == "auto":
            mode = "marg" if array.has("mag") and array.n_imus == 1 else "array"
        self.resolved_mode = mode
        self.tests = {}
        self.budgets = {}
        self._reset_stream()
        if mode == "marg":
            self._fit_marg(calibration, array)
        else:
            self._fit_array(calibration, array)

    def _fit_array(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        for sensor_type in array.sensor_types():
            data = calibration.get(sensor_type)
            if data is None:
                raise CalibrationError(f"bank: calibration block has no {sensor_type} data")
            values = array.select(data, sensor_type)
            self.tests[sensor_type] = _fit_array_test(
                values,
                # accelerometers at different points: rigid-body lever arms (maths/rigid.py)
                accel_design(array)
                if sensor_type == "accel"
                else array.measurement_matrix(sensor_type),
                sensor_type,
                self.alpha,
                self.max_faults,
            )
            if self.false_alarms > 0:
                self.budgets[sensor_type] = self._array_budget(values, array, sensor_type)

    def _array_budget(
        self, values: np.ndarray, array: ArrayConfig, sensor_type: str
    ) -> ArrayBudget:
        """The array-mode test under a budget: the per-sample test's residuals, weighted by
        the array config's per-IMU noise when every IMU has one (as glt; with the healthy
        noise spread folded in, :func:`~imufdi_cli.detectors.budget.configured_noise`),
        with its jitter model when it has one."""
        test = self.tests[sensor_type]
        configured = configured_noise(array, sensor_type)
        known = configured is not None
        if configured is not None:
            test = _fit_array_test(
                values, test.H, sensor_type, self.alpha, self.max_faults, sigma=configured
            )
        budget = ArrayBudget(
            test,
            array.rate_hz,
            self.false_alarms,
            None,
            inflation=array_inflation(array, sensor_type, test.H),
            sigma_known=known,
            spatial=sensor_type in SPATIAL_TYPES,
        )
        budget.fit(values)
        return budget

    def _fit_marg(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        imu = array.imus[0]
        if (
            array.n_imus != 1
            or imu.axes_of("accel") != ("x", "y", "z")
            or imu.axes_of("mag") != ("x", "y", "z")
        ):
            raise DetectorConfigError(
                "bank: mode=marg needs exactly one IMU with 3-axis accel and 3-axis mag"
                f" (got {array.n_imus} IMUs); use mode=array for arrays"
            )
        if calibration.accel is None or calibration.mag is None:
            raise CalibrationError("bank: mode=marg needs accel and mag data in the calibration")
        calibration_stats(np.zeros((len(calibration), 1)))  # window length check
        accel = calibration.accel[:, 0, :]
        mag = calibration.mag[:, 0, :]
        accel_norm = np.linalg.norm(accel, axis=1)
        mag_norm = np.linalg.norm(mag, axis=1)
        gravity_norm = float(np.median(accel_norm))
        field_norm = float(np.median(mag_norm))
        if not (gravity_norm > 0 and field_norm > 0):
            raise CalibrationError("bank: accel or mag is zero in the calibration window")
        cosine = float(np.median(np.einsum("ni,ni->n", accel, mag) / (accel_norm * mag_norm)))
        angle = math.acos(min(1.0, max(-1.0, cosine)))
        if math.sin(angle) < 0.05:
            raise CalibrationError(
                f"bank: specific force and magnetic field are {math.degrees(angle):.1f} deg"
                " apart in the calibration window; attitude is not observable from them"
            )
        g_ref = np.array([0.0, 0.0, 1.0])
        h_ref = np.array([math.sin(angle), 0.0, math.cos(angle)])
        H_accel = array.measurement_matrix("accel")
        H_mag = array.measurement_matrix("mag")
        scale = np.array([gravity_norm] * 3 + [field_norm] * 3)
        y_calibration = (
            np.concatenate(
                [array.select(calibration.accel, "accel"), array.select(calibration.mag, "mag")],
                axis=1,
            )
            / scale
        )
        noise = self._component_noise(array, y_calibration, gravity_norm, field_norm)
        self._model = _MargModel(
            sensor_axes=np.vstack([H_accel, H_mag]),
            references=np.vstack([np.tile(g_ref, (3, 1)), np.tile(h_ref, (3, 1))]),
            gravity_norm=gravity_norm,
            field_norm=field_norm,
            angle=angle,
            accel_to_body=np.linalg.inv(H_accel),
            mag_to_body=np.linalg.inv(H_mag),
            noise=noise,
        )
        solution = self._model.solve(y_calibration, self.iterations)
        self._marg_threshold = bonferroni_threshold(self.alpha, 6)
        self._marg_budget = None
        self._gyro_budget = None
        if self.false_alarms > 0:
            # the evidence: the full estimator's residual linearised (the blind residuals'
            # first order, without the heavy tails of weakly observable blind estimators)
            z, energy = solution.parity_evidence(self._model.noise)
            self._marg_offset = np.nan_to_num(np.nanmean(z, axis=0))
            # z per SI unit of a step on a component: sqrt(P_jj) / (its norm x its noise)
            sensitivity = np.median(energy, axis=0) / (scale * self._model.noise)
            self._marg_budget = EvidenceBudget(
                sensitivity,
                np.ones(6, dtype=bool),
                array.rate_hz,
                self.false_alarms,
                REFERENCE_TAU_S,
                calibration_samples=len(calibration),
            )
            self._marg_budget.fit(np.nan_to_num(z - self._marg_offset))

        self._gyro_H = None
        if array.has("gyro") and calibration.gyro is not None:
            self._fit_gyro(calibration, array, solution.q[FULL_ESTIMATOR])

    @staticmethod
    def _component_noise(
        array: ArrayConfig, y: np.ndarray, gravity_norm: float, field_norm: float
    ) -> np.ndarray:
        """White-noise std (6,) of the normalised accel/mag components.

        From ``ArrayConfig.noise`` when given, else from second differences of the
        calibration window (``Var(D^2 y) = 6 sigma^2`` for white noise; smooth motion
        cancels to O(Te^2)).
        """
        from_data = robust_std(np.diff(y, n=2, axis=0)) / math.sqrt(6.0)
        noise = from_data.copy()
        if "accel" in array.noise:
            noise[:3] = array.noise["accel"] / gravity_norm
        if "mag" in array.noise:
            noise[3:] = array.noise["mag"] / field_norm
        if not np.all(np.isfinite(noise)) or np.any(noise <= 0):
            raise CalibrationError(
                "bank: accel/mag noise from the calibration window is not positive"
                " (constant data?); give noise in the array config or another --calibrate"
            )
        return noise

    # --- process -----------------------------------------------------------------------

    def _require_fit(self) -> ArrayConfig:
        if self.array is None or self.resolved_mode is None:
            raise DetectorConfigError("bank: call fit() with a calibration block before process()")
        return self.array

    def process(self, block: ImuBlock) -> dict[str, DetectionBlock]:
        """One row per input sample for every tested sensor type (causal)."""
        array = self._require_fit()
        if self.resolved_mode == "marg":
            return self._process_marg(block, array)
        out: dict[str, DetectionBlock] = {}
        isolated_sets: dict[str, np.ndarray] = {}
        for sensor_type, test in self.tests.items():
            data = block.get(sensor_type)
            if data is None:
                raise CalibrationError(f"bank: block has no {sensor_type} data")
            values = array.select(data, sensor_type)
            budget = self.budgets.get(sensor_type)
            if budget is not None:
                out[sensor_type], isolated_sets[sensor_type] = budget.process(values, block.t_ns)
                out[sensor_type].amplitudes = budget.amplitudes(values, isolated_sets[sensor_type])
            else:
                out[sensor_type], isolated_sets[sensor_type] = test.run(values)
            out[sensor_type].isolated_set = isolated_sets[sensor_type]
        self.last_details = BankDetails(isolated_sets=isolated_sets)
        return out

    def _process_marg(self, block: ImuBlock, array: ArrayConfig) -> dict[str, DetectionBlock]:
        model = self._model
        assert model is not None
        n_samples = len(block)
        y = model.normalised(block, array)
        solution = model.solve(y, self.iterations)
        q, residuals, blind, fit_cost = (
            solution.q,
            solution.residuals,
            solution.blind,
            solution.fit_cost,
        )
        blind_z2 = (blind / solution.blind_std) ** 2  # (N, 6), chi-square(1) when fault-free
        scale = np.array([model.gravity_norm] * 3 + [model.field_norm] * 3)
        rows = np.arange(n_samples)
        if self._marg_budget is not None:
            # under a budget: one bank of CUSUM tests over the six standardized blind
            # residuals; each episode goes to the channel of the component it isolates
            evidence, _ = solution.parity_evidence(model.noise)
            decided = self._marg_budget.decide(evidence - self._marg_offset)
            statistic, alarm = decided.statistic, decided.alarm
            # Table 1 decides which component: the one whose blind estimator fits the other
            # five best, on average since the episode began (the linearised evidence cannot
            # tell a large fault on a weakly observable component from its neighbours)
            best = self._episode_fit(alarm, fit_cost)
            isolated = np.where(alarm, best, NO_ISOLATION).astype(np.int32)
            amplitude = np.where(alarm, blind[rows, best] * scale[best], np.nan)
            threshold = decided.threshold
            scores = decided.scores
        else:
            statistic = np.max(np.nan_to_num(blind_z2, nan=0.0), axis=1)
            alarm = statistic > self._marg_threshold
            # Table 1: the faulty component j is the one whose blind residual exceeds the
            # threshold while its estimator (blind to j) fits the other five: argmin of the
            # fit cost among the components above threshold.
            with np.errstate(invalid="ignore"):
                candidates = np.where(blind_z2 > self._marg_threshold, fit_cost, np.inf)
            best = np.argmin(candidates, axis=1)
            isolated = np.where(alarm, best, NO_ISOLATION).astype(np.int32)
            amplitude = np.where(alarm, blind[rows, best] * scale[best], np.nan)
            threshold = np.full(n_samples, self._marg_threshold)
            scores = blind_z2

        out: dict[str, DetectionBlock] = {}
        isolated_sets: dict[str, np.ndarray] = {}
        for sensor_type, offset in (("accel", 0), ("mag", 3)):
            mine = alarm & (isolated >= offset) & (isolated < offset + 3)
            out[sensor_type] = DetectionBlock(
                statistic=statistic.copy(),
                threshold=threshold.copy(),
                alarm=mine,
                isolated=np.where(mine, isolated - offset, NO_ISOLATION).astype(np.int32),
                amplitude=np.where(mine, amplitude, np.nan),
                scores=scores[:, offset : offset + 3].copy(),
            )
            isolated_sets[sensor_type] = np.zeros((n_samples, 3), dtype=bool)
            isolated_sets[sensor_type][mine, isolated[mine] - offset] = True

        clean, candidates, abstain = self._gyro_candidates(solution, model.noise, alarm, best)
        chosen = np.where(alarm & clean[np.arange(n_samples), best], best, FULL_ESTIMATOR)
        q = make_continuous(q, self._q_last)
        gyro_residuals = None
        if self._gyro_H is not None and block.gyro is not None and n_samples > 0:
            out["gyro"], isolated_sets["gyro"], gyro_residuals = self._gyro_test(
                block, array, q, clean, candidates, solution.covariance, abstain
            )
            chosen = self._gyro_chosen
        if n_samples > 0:
            self._q_last = q[:, -1, :].copy()
        self.last_details = BankDetails(
            isolated_sets=isolated_sets,
            estimator_residuals=np.moveaxis(residuals, 0, 1),
            attitude=np.moveaxis(q, 0, 1),
            gyro_residuals=gyro_residuals,
            chosen_estimator=chosen,
        )
        for sensor_type, det in out.items():
            chosen_set = isolated_sets.get(sensor_type)
            if chosen_set is not None and chosen_set.shape == det.scores.shape:
                det.isolated_set = chosen_set
        return out

    def _episode_fit(self, alarm: np.ndarray, fit_cost: np.ndarray) -> np.ndarray:
        """marg under a budget: per row (N,), the component of smallest mean fit cost of its
        blind estimator over the rows of the current alarm episode so far (state carried
        over blocks; 0 outside alarms)."""
        n = alarm.size
        if n == 0:
            return np.zeros(0, dtype=np.intp)
        cost = np.where(np.isfinite(fit_cost), fit_cost, np.nan)
        seen = np.isfinite(cost).astype(float)
        cost = np.nan_to_num(cost)
        previous = np.concatenate([[self._episode_cost[1].any()], alarm[:-1]])
        starts = alarm & ~previous
        segment = np.cumsum(starts)  # 0: the episode carried over from the last block
        sums = np.cumsum(cost * alarm[:, None], axis=0)
        counts = np.cumsum(seen * alarm[:, None], axis=0)
        start_rows = np.flatnonzero(starts)
        base_sums = np.empty((start_rows.size + 1, 6))
        base_counts = np.empty((start_rows.size + 1, 6))
        base_sums[0] = -self._episode_cost[0]
        base_counts[0] = -self._episode_cost[1]
        before = np.maximum(start_rows - 1, 0)
        first = (start_rows == 0)[:, None]
        base_sums[1:] = np.where(first, 0.0, sums[before])
        base_counts[1:] = np.where(first, 0.0, counts[before])
        total = sums - base_sums[segment]
        count = counts - base_counts[segment]
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(count > 0, total / count, np.inf)
        if alarm[-1]:
            self._episode_cost = (total[-1].copy(), count[-1].copy())
        else:
            self._episode_cost = (np.zeros(6), np.zeros(6))
        return np.where(alarm, np.argmin(mean, axis=1), 0)  # type: ignore[no-any-return]

    def flush(self) -> dict[str, DetectionBlock]:
        """Causal detector: nothing is held back."""
        array = self._require_fit()
        types = list(self.tests) if self.resolved_mode == "array" else ["accel", "mag"]
        if self.resolved_mode == "marg" and self._gyro_H is not None:
            types.append("gyro")
        return {s: _empty_block(array.n_sensors(s)) for s in types}

    def metadata(self) -> dict[str, Any]:
        """Parameters and calibration results (JSON-ready)."""
        meta: dict[str, Any] = {
            "params": {
                "alpha": self.alpha,
                "mode": self.mode,
                "tau": self.tau,
                "max_faults": self.max_faults,
                "iterations": self.iterations,
            },
            "mode": self.resolved_mode,
        }
        if self.false_alarms > 0:  # (the per-sample test's metadata is unchanged)
            meta["params"]["false_alarms_per_hour"] = self.false_alarms * 3600.0
        if self.resolved_mode == "array":
            meta["calibration"] = {s: t.metadata() for s, t in self.tests.items()}
            for sensor_type, budget in self.budgets.items():
                meta["calibration"][sensor_type]["threshold"] = budget.first.threshold  # type: ignore[union-attr]
                meta["calibration"][sensor_type]["budget"] = budget.metadata()
        elif self.resolved_mode == "marg" and self._model is not None:
            calibration: dict[str, Any] = {
                "gravity_norm": self._model.gravity_norm,
                "field_norm": self._model.field_norm,
                "field_angle_deg": math.degrees(self._model.angle),
                "component_noise": self._model.noise.tolist(),
                "accel_mag_threshold": self._marg_threshold,
            }
            if self._gyro_variance is not None and self._gyro_bias is not None:
                calibration.update(
                    gyro_bias=self._gyro_bias.tolist(),
                    gyro_noise_sigma=np.sqrt(self._gyro_variance).tolist(),
                    gyro_threshold=self._gyro_threshold,
                    filter_pole=self._filter_pole,
                )
            if self._marg_budget is not None:
                calibration["accel_mag_threshold"] = self._marg_budget.threshold
                calibration["accel_mag_budget"] = self._marg_budget.metadata()
            if self._gyro_budget is not None:
                calibration["gyro_threshold"] = self._gyro_budget.threshold
                calibration["gyro_budget"] = self._gyro_budget.metadata()
            meta["calibration"] = calibration
        return meta
