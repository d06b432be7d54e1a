"""The WOA-MVMD-GLT detector: parameters and construction, choice of (K, alpha) per sensor
type, outlier clipping, and the GLT decision on u_best (paper §2.1, §3).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import asdict
from typing import Any, ClassVar

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import (
    ALPHA,
    FALSE_ALARMS,
    NO_ISOLATION,
    NOT_ISOLABLE,
    TYPES,
    DetectionBlock,
    DetectorBase,
    Param,
    parse_sensor_types,
)
from imufdi_cli.detectors.budget import REFERENCE_TAU_S, EvidenceBudget, MotionState
from imufdi_cli.detectors.mvmd import (
    MIN_SAMPLES,
    check_mvmd_params,
)
from imufdi_cli.detectors.woa_mvmd_glt.budget import (
    LeakMonitor,
    decide_rows,
    long_run,
    motion_warning,
)
from imufdi_cli.detectors.woa_mvmd_glt.fitness import (
    DEFAULT_WEIGHTS,
    FITNESS_CHOICES,
    OUTLIER_CHOICES,
    ValidationFault,
    cfv,
    cfv_components,
)
from imufdi_cli.detectors.woa_mvmd_glt.state import _row_scales, _TypeState
from imufdi_cli.detectors.woa_mvmd_glt.tuning import (
    TuneResult,
    make_validation,
    tune,
    tune_signal,
    tune_signals,
)
from imufdi_cli.detectors.woa_mvmd_glt.windows import (
    COMBINE_CHOICES,
    DEFAULT_MODE_RULE,
    MODE_RULES,
    _WindowStream,
    best_mode,
    decompose_windows,
    filter_matrices,
)
from imufdi_cli.errors import (
    ArrayConfigError,
    ArrayTooSmallError,
    CalibrationError,
    DetectorConfigError,
    ImufdiError,
    InputDataError,
)
from imufdi_cli.log import ImuBlock
from imufdi_cli.maths.jitter import MotionInflation, array_inflation
from imufdi_cli.maths.parity import (
    isolable_sensors,
    isolation_statistics,
    parity_matrix,
    residual_sigma,
    residuals,
    sigma_estimate_variance,
    whiten,
)
from imufdi_cli.maths.quantiles import chi2
from imufdi_cli.maths.rigid import accel_design

# --- the detector ----------------------------------------------------------------------

#: WOA results of this process, keyed by the tuning segment's bytes and every setting that
#: enters the search (the search is deterministic given them): a campaign's runs of one
#: seed share their calibration window, and so their tuning.
_TUNING_CACHE: dict[tuple[Any, ...], TuneResult] = {}
_TUNING_CACHE_SIZE = 64


def clear_tuning_cache() -> None:
    """Forget the WOA results reused across fits in this process (benchmarks, tests)."""
    _TUNING_CACHE.clear()


def _weights_check(value: Any) -> str | None:
    try:
        parts = [float(v) for v in str(value).split(",")]
    except ValueError:
        return "weights must be three comma-separated numbers, e.g. 1,1,1"
    if len(parts) != 3 or any(not np.isfinite(p) or p < 0 for p in parts):
        return "weights must be three comma-separated non-negative numbers, e.g. 1,1,1"
    return None


class WoaMvmdGltDetector(DetectorBase):
    """WOA-tuned MVMD + GLT detector (module docstring), CLI name ``woa-mvmd-glt``."""

    name: ClassVar[str] = "woa-mvmd-glt"
    PARAMS: ClassVar[dict[str, Param]] = {
        "alpha": ALPHA,
        "window": Param("int", 50, "MVMD window length, samples", low=MIN_SAMPLES),
        "overlap": Param("int", 40, "overlap of consecutive windows, samples", low=0),
        "combine": Param(
            "choice",
            "end",
            "per-sample row: from the first window that ends after the sample (causal,"
            " look-ahead hop - 1), the window where it is central, or the min over all"
            " windows containing it (look-ahead window - 1)",
            choices=COMBINE_CHOICES,
        ),
        "u_best": Param(
            "choice",
            DEFAULT_MODE_RULE,
            "mode tested: lowest centre frequency (lowest, the default) or largest uncentred"
            " inner product with the raw window (inner, the paper's rule; on bias-free input"
            " it follows the noise)",
            choices=MODE_RULES,
        ),
        "outliers": Param(
            "choice",
            "clip",
            "sparse spikes: clip each sample's largest standardised parity residual at"
            " outlier_cut before the decomposition (clip), add their calibration variance to sigma"
            " (variance), or nothing (ignore)",
            choices=OUTLIER_CHOICES,
        ),
        "outlier_cut": Param(
            "float",
            4.0,
            "clip level of outliers=clip, standardised residual",
            low=0.0,
            low_open=True,
        ),
        "fitness": Param(
            "choice",
            "cfv+delay",
            "WOA fitness: the paper's CFV plus the expected missed fraction of a validation"
            " step (cfv+delay), or CFV alone (cfv: picks the alpha upper bound)",
            choices=FITNESS_CHOICES,
        ),
        "validation_step": Param(
            "float", 4.0, "validation step of cfv+delay, in noise sigmas", low=0.0, low_open=True
        ),
        "delay_weight": Param(
            "float", 100.0, "weight of the validation miss fraction in cfv+delay", low=0.0
        ),
        "noise_spread": Param(
            "bool",
            True,
            "hold the level at the top of each sensor's healthy noise-variance range (ArrayConfig"
            " <type>_noise_spread from calibrate: sigma_i^2 -> kappa_i sigma_i^2) when the"
            " array carries one",
        ),
        "params": Param("path", None, "JSON file of tuned (K, alpha) from `imufdi tune`"),
        "K": Param("int", None, "number of MVMD modes (skips tuning, with mvmd_alpha)", low=1),
        "mvmd_alpha": Param(
            "float", None, "MVMD bandwidth penalty (f in cycles/sample)", low=0, low_open=True
        ),
        "population": Param("int", 8, "WOA population", low=2),
        "iterations": Param("int", 6, "WOA iterations", low=0),
        "k_min": Param("int", 2, "smallest K searched", low=1),
        "k_max": Param("int", 5, "largest K searched", low=1),
        "alpha_min": Param("float", 50.0, "smallest MVMD alpha searched", low=0, low_open=True),
        "alpha_max": Param("float", 5000.0, "largest MVMD alpha searched", low=0, low_open=True),
        "weights": Param(
            "str",
            "1,1,1",
            "CFV weights w1,w2,w3 (entropy, correlation, compactness)",
            check=_weights_check,
        ),
        "tune_samples": Param("int", 250, "calibration samples used for tuning", low=MIN_SAMPLES),
        "seed": Param("int", 0, "seed of the WOA search", low=0),
        "types": TYPES,
        "tol": Param("float", 1e-6, "MVMD relative convergence tolerance", low=0, low_open=True),
        "max_iter": Param("int", 300, "MVMD iteration cap", low=1),
        "lever_arm": Param(
            "bool",
            True,
            "model rigid-body lever arms between accelerometers (IMU positions)",
        ),
        "false_alarms": FALSE_ALARMS,
        "jitter": Param(
            "bool",
            True,
            "widen the test in motion by the array config's sampling-time jitter (if any)",
        ),
    }
    #: Parameters added after the paper's set: listed in the metadata only when not at
    #: their defaults, so that the per-sample test's metadata keeps its bytes.
    LATER_PARAMS: ClassVar[dict[str, Any]] = {
        "lever_arm": True,
        "false_alarms": 0.0,
        "jitter": True,
    }

    def __init__(
        self,
        alpha: float = 0.01,
        window: int = 50,
        overlap: int = 40,
        combine: str = "end",
        u_best: str = DEFAULT_MODE_RULE,
        outliers: str = "clip",
        outlier_cut: float = 4.0,
        fitness: str = "cfv+delay",
        validation_step: float = 4.0,
        delay_weight: float = 100.0,
        noise_spread: bool = True,
        params: str | None = None,
        K: int | None = None,
        mvmd_alpha: float | None = None,
        population: int = 8,
        iterations: int = 6,
        k_min: int = 2,
        k_max: int = 5,
        alpha_min: float = 50.0,
        alpha_max: float = 5000.0,
        weights: str = "1,1,1",
        tune_samples: int = 250,
        seed: int = 0,
        types: str = "gyro,accel",
        tol: float = 1e-6,
        max_iter: int = 300,
        lever_arm: bool = True,
        false_alarms: float = 0.0,
        jitter: bool = True,
    ) -> None:
        arguments = locals()
        values = {key: arguments[key] for key in self.PARAMS}  # each PARAMS name, typed
        self.params = values
        window = int(values["window"])
        overlap = int(values["overlap"])
        if not 0 <= overlap < window:
            raise DetectorConfigError(
                f"{self.name}.overlap: must be >= 0 and < window ({window}), got {overlap}"
            )
        if values["k_min"] > values["k_max"]:
            raise DetectorConfigError(f"{self.name}: k_min must be <= k_max")
        if values["alpha_min"] > values["alpha_max"]:
            raise DetectorConfigError(f"{self.name}: alpha_min must be <= alpha_max")
        if (values["K"] is None) != (values["mvmd_alpha"] is None):
            raise DetectorConfigError(f"{self.name}: give both K and mvmd_alpha, or neither")
        if values["K"] is not None:
            check_mvmd_params(values["K"], values["mvmd_alpha"])
        self.false_alarms = float(values["false_alarms"])
        if self.false_alarms > 0 and values["combine"] == "min":
            raise DetectorConfigError(
                f"{self.name}.combine=min takes the window with the smallest statistic, whose"
                " evidence is not N(0, 1): with a false-alarm budget use combine=end (or"
                " centre)"
            )
        self.window = window
        self.hop = window - overlap
        self.weights = tuple(float(v) for v in str(values["weights"]).split(","))
        self.types = list(parse_sensor_types(types, self.name))
        self.tuned_file = TuneResult.load(values["params"]) if values["params"] else None
        self._states: dict[str, _TypeState] = {}
        #: Per sensor type: the window evaluation its stream is pushed with (see _evaluator).
        self._evaluators: dict[str, Callable[[np.ndarray, int], dict[str, np.ndarray]]] = {}
        self._array: ArrayConfig | None = None

    @property
    def lookahead_samples(self) -> int:
        """Most samples a row is held back: its decision waits for a window's last sample.

        ``end``: a sample in the last ``hop`` samples of a window is decided when that window
        ends, ``hop - 1`` samples later at most. ``centre`` and ``min``: up to ``window - 1``
        (the first window decides its first sample ``window - 1`` samples late; ``min`` waits
        for the last window containing the sample).
        """
        if self.params["combine"] == "end":
            return self.hop - 1
        return self.window - 1

    def decision_index(self, sample: np.ndarray, n_samples: int) -> np.ndarray:
        """Index of the input sample at which each row's decision is available, (N,).

        Exact for the window grid (``end``: the end of the first window that has the sample
        in its last ``hop``; ``centre``: the end of the window where it is central; ``min``:
        the end of the last window that contains it), capped at the last sample of the log
        (the tail window of ``flush``).
        """
        sample = np.asarray(sample, dtype=np.int64)
        window, hop = self.window, self.hop
        combine = self.params["combine"]
        if combine == "end":
            first = np.maximum(-(-(sample - window + 1) // hop), 0)
            decided = first * hop + window - 1
            decided = np.where(sample < window - hop, sample, decided)  # quiet rows
        elif combine == "centre":
            pad = (window - hop) // 2
            j = np.maximum((sample - pad) // hop, 0)
            decided = j * hop + window - 1
        else:
            decided = (sample // hop) * hop + window - 1
        return np.asarray(np.minimum(decided, n_samples - 1))

    # -- calibration ----------------------------------------------------------------

    def _tuning_job(
        self, values: np.ndarray
    ) -> tuple[tuple[Any, ...], np.ndarray, ValidationFault | None, dict[str, Any]] | None:
        """What the WOA search of one sensor type needs: its cache key, the tuning segment
        (N, n), the validation fault and the search settings (None when (K, alpha) are
        given or read from a params file)."""
        p = self.params
        if p["K"] is not None or self.tuned_file is not None:
            return None
        segment = values[: int(p["tune_samples"])]
        validation = None
        if p["fitness"] == "cfv+delay":
            validation = make_validation(
                values.shape[1],
                self.window,
                self.hop,
                float(p["validation_step"]),
                float(p["delay_weight"]),
                float(p["alpha"]),
            )
        settings: dict[str, Any] = {
            "population": int(p["population"]),
            "iterations": int(p["iterations"]),
            "k_bounds": (int(p["k_min"]), int(p["k_max"])),
            "alpha_bounds": (float(p["alpha_min"]), float(p["alpha_max"])),
            "weights": self.weights,
            "seed": int(p["seed"]),
            "tol": float(p["tol"]),
            "max_iter": int(p["max_iter"]),
            "rule": str(p["u_best"]),
        }
        segment = np.ascontiguousarray(segment, dtype=np.float64)
        key = (
            hashlib.sha256(segment.tobytes()).hexdigest(),
            segment.shape,
            repr(sorted(settings.items())),
            repr(validation),
        )
        return key, segment, validation, settings

    def _tune_together(
        self, calibration: ImuBlock, array: ArrayConfig
    ) -> dict[tuple[Any, ...], TuneResult]:
        """The WOA searches of every sensor type :meth:`fit` will tune, run together
        (:func:`tune_signals`: the same results as one type at a time, in less time).

        Only when at least two types need a search not in the cache and every type passes
        the checks :meth:`fit` makes before its search; otherwise (or if the joint search
        raises) nothing is done here and :meth:`fit` tunes one type at a time, raising
        what it raises in its order."""
        jobs = {}
        for sensor_type in self.types:
            try:
                values = self._calibration_values(calibration, array, sensor_type)
                job = None if values is None else self._tuning_job(values)
            except ImufdiError:
                return {}
            if job is not None and job[0] not in _TUNING_CACHE:
                jobs[job[0]] = job
        if len(jobs) < 2 or len({repr(job[3]) for job in jobs.values()}) != 1:
            return {}
        settings = next(iter(jobs.values()))[3]
        try:
            results = tune_signals(
                [job[1].T for job in jobs.values()],
                validations=[job[2] for job in jobs.values()],
                **settings,
            )
        except ImufdiError:
            return {}
        return dict(zip(jobs, results))

    def _choose(
        self,
        sensor_type: str,
        values: np.ndarray,
        fresh: dict[tuple[Any, ...], TuneResult] | None = None,
    ) -> tuple[int, float, dict | None]:
        p = self.params
        if p["K"] is not None:
            return int(p["K"]), float(p["mvmd_alpha"]), None
        if self.tuned_file is not None:
            return self.tuned_file.K, self.tuned_file.alpha, {"source": "params file"}
        job = self._tuning_job(values)
        assert job is not None
        key, segment, validation, settings = job
        cached = _TUNING_CACHE.get(key)
        if cached is None:
            cached = (fresh or {}).get(key)
            if cached is None:
                cached = tune_signal(segment.T, validation=validation, **settings)
            if len(_TUNING_CACHE) >= _TUNING_CACHE_SIZE:
                _TUNING_CACHE.pop(next(iter(_TUNING_CACHE)))
            _TUNING_CACHE[key] = cached
            reused = False
        else:
            reused = True
        record = asdict(cached)
        record["sensor_type"] = sensor_type
        record["reused"] = reused
        return cached.K, cached.alpha, record

    def _decompose(self, K: int, alpha: float) -> Any:
        tol = float(self.params["tol"])
        max_iter = int(self.params["max_iter"])
        rule = str(self.params["u_best"])

        def u_best(windows: np.ndarray, first_row: int) -> tuple[np.ndarray, np.ndarray]:
            count = windows.shape[0]
            u, F = decompose_windows(
                windows,
                [K] * count,
                [alpha] * count,
                tol=tol,
                max_iter=max_iter,
                first_row=first_row,
                rule=rule,
            )
            return u[:, first_row:], F

        return u_best

    def _calibration_values(
        self, calibration: ImuBlock, array: ArrayConfig, sensor_type: str
    ) -> np.ndarray | None:
        """The calibration samples of ``sensor_type``, shape (N, n sensors), or None when
        the log or the array has none; raises what :meth:`fit` raises before fitting a
        type (fewer than 4 sensors, a window shorter than one MVMD window)."""
        triads = calibration.get(sensor_type)
        n = array.n_sensors(sensor_type)
        if triads is None or n == 0:
            return None
        if n < 4:
            raise ArrayTooSmallError(
                f"{self.name}: {sensor_type} has {n} sensors; the GLT needs at least 4"
            )
        values = array.select(triads, sensor_type)
        if values.shape[0] < max(self.window, 10):
            raise CalibrationError(
                f"calibration window has {values.shape[0]} samples; {self.name} needs at"
                f" least {max(self.window, 10)} (one MVMD window); use --calibrate"
            )
        return values

    def fit(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        self._array = array
        self._states = {}
        self._evaluators = {}
        fresh = self._tune_together(calibration, array)
        for sensor_type in self.types:
            values = self._calibration_values(calibration, array, sensor_type)
            if values is None:
                continue
            n = values.shape[1]
            K, alpha, tuned = self._choose(sensor_type, values, fresh)
            decompose = self._decompose(K, alpha)
            # sigma and biases of the raw sensors (many degrees of freedom), carried into the
            # u_best domain exactly through each window's filter matrix (filter_matrix)
            H = self._design(array, sensor_type)
            if n <= H.shape[1]:
                raise ArrayTooSmallError(
                    f"{self.name}: {sensor_type} has {n} sensors; with the lever-arm terms of"
                    f" these IMU positions the GLT needs at least {H.shape[1] + 1}"
                    f" (or {self.name}.lever_arm=false)"
                )
            sigma = residual_sigma(H, values)
            raw_sigma = sigma
            if np.any(~np.isfinite(sigma)) or np.any(sigma <= 0):
                raise CalibrationError(
                    f"{self.name}: {sensor_type} noise sigma is zero or not finite;"
                    " the calibration window is degenerate"
                )
            outlier_variance = 0.0
            outlier_cut = None
            if self.params["outliers"] == "clip":
                outlier_cut = float(self.params["outlier_cut"])
            if self.params["outliers"] == "variance":
                # sparse spikes, smoothed by u_best, act as extra white noise: their variance
                # (all samples minus the spike-free fit), pooled over the sensors of the type
                plain = residual_sigma(H, values, outlier_cut=None)
                outlier_variance = float(np.mean(np.maximum(plain**2 - sigma**2, 0.0)))
                sigma = np.sqrt(sigma**2 + outlier_variance)
            bias = residuals(H, values).mean(axis=0)
            V = parity_matrix(whiten(H, sigma))
            if outlier_cut is not None:
                # a clipped spike still carries c standardised sigmas: its variance, at the
                # rate spikes were clipped in the calibration window, joins the noise
                probe = _TypeState.clip_probe(values, bias, sigma, V, outlier_cut)
                rate = float(np.mean(probe))
                diagonal = np.einsum("ki,ki->i", V, V)
                outlier_variance = rate * outlier_cut**2
                sigma = sigma * np.sqrt(1.0 + outlier_variance / diagonal)
                V = parity_matrix(whiten(H, sigma))
            kappa = array.sensor_noise_spread(sensor_type) if self.params["noise_spread"] else None
            if kappa is not None:
                # the healthy noise of a chip changes with the orientation (MIMU4444 z gyros:
                # variance up to 3.3x the calibration window's); the null hypothesis becomes
                # Var(x_i) <= kappa_i sigma_i^2, whose boundary is the worst case (Anderson
                # 1955: a chi-square form's exceedance grows with the covariance)
                sigma = sigma * np.sqrt(kappa)
                V = parity_matrix(whiten(H, sigma))
            state = _TypeState(
                sensor_type=sensor_type,
                n=n,
                K=K,
                alpha=alpha,
                tuned=tuned,
                sigma=sigma,
                bias=bias,
                V=V,
                isolable=isolable_sensors(V),
                threshold=float(chi2.ppf(1.0 - float(self.params["alpha"]), V.shape[0])),
                stream=_WindowStream(self.window, self.hop, self.params["combine"]),
                n_calibration=int(values.shape[0]),
                outlier_variance=outlier_variance,
                outlier_cut=outlier_cut,
                spread=kappa,
                lever_arm_columns=int(H.shape[1] - 3),
                motion=MotionState(H, sigma),
                inflation=array_inflation(array, sensor_type, H) if self.params["jitter"] else None,
            )
            state.motion_centre = state.motion(values).mean(axis=0)  # type: ignore[misc]
            self._states[sensor_type] = state
            self._evaluators[sensor_type] = self._evaluator(state, decompose)
            if self.false_alarms > 0:
                self._fit_budget(state, values, decompose, H, raw_sigma, calibration.t_ns)
            else:
                state.monitor = LeakMonitor(n)
        if not self._states:
            raise CalibrationError(
                f"{self.name}: no tested sensor type ({', '.join(self.types)}) in the log"
            )

    def _design(self, array: ArrayConfig, sensor_type: str) -> np.ndarray:
        """H (n, 3); for accelerometers with ``lever_arm``, the rigid-body design [H | B]
        (:mod:`.rigid`): the filter of u_best is the same on every channel, so the parity
        space of the design cancels the lever-arm terms in the u_best domain too."""
        if sensor_type == "accel" and self.params["lever_arm"]:
            try:
                return accel_design(array, sensor_type)
            except ArrayConfigError:
                pass
        return array.measurement_matrix(sensor_type)

    @staticmethod
    def _carried(
        state: _TypeState, values: np.ndarray, t_ns: np.ndarray, inflation: MotionInflation | None
    ) -> np.ndarray:
        """The stream's columns for rows of measurements (N, n): clipped, raw and, with the
        jitter model, each sample's motion variance factor ``1 + A_t``."""
        columns = [state.clip(values), values]
        if inflation is not None:
            columns.append(inflation.factors(values, t_ns)[:, None])
        return np.concatenate(columns, axis=1)

    def _fit_budget(
        self,
        state: _TypeState,
        values: np.ndarray,
        decompose: Any,
        H: np.ndarray,
        raw_sigma: np.ndarray,
        t_ns: np.ndarray,
    ) -> None:
        """The budget's bank for one type: the calibration window's rows decided as online
        (its windows one hop apart, their last hop rows), their evidence and regressors,
        the long-run factor of the u_best filters, the sensitivities."""
        n = state.n
        starts = np.arange(0, values.shape[0] - self.window + 1, self.hop)
        first_row = self.window - self.hop
        inflation = None
        if state.inflation is not None and self._array is not None:
            inflation = array_inflation(self._array, state.sensor_type, H)  # its own stream
        carried = self._carried(state, values, t_ns, inflation)
        state.clipped = 0  # (calibration rows are not the log's)
        stack = carried[starts[:, None] + np.arange(self.window)]  # (W, L, 2n)
        rows = self._evaluators[state.sensor_type](stack, first_row)
        _, F = decompose(stack[..., :n], first_row)
        _, dc_gain, row_scale = _row_scales(F, state.n_calibration)
        kappa = long_run(F, row_scale, first_row, self.hop)
        evidence = rows["evidence"].reshape(-1, n)
        energy = np.einsum("ki,ki->i", state.V, state.V)  # P_ii, whitened
        # z per SI unit of a step on sensor i: the filter passes it with its DC gain
        gain = float(np.mean(dc_gain / row_scale))
        # the state in the unit where a relative scale error e leaks e g |x| into z_i
        state.state_gain = gain
        regressors = rows["regressors"].reshape(-1, 3) / gain
        sensitivity = np.where(energy > 1e-12, np.sqrt(np.maximum(energy, 0.0)), 0.0)
        state.budget = EvidenceBudget(
            sensitivity * gain / state.sigma,
            state.isolable,
            self._array.rate_hz if self._array is not None else 0.0,
            self.false_alarms,
            REFERENCE_TAU_S,
            scale_variance=float(np.mean(sigma_estimate_variance(H, raw_sigma, len(values)))),
            calibration_samples=state.n_calibration,
        )
        state.budget.fit(np.nan_to_num(evidence), regressors, long_run=kappa)

    def _evaluator(self, state: _TypeState, decompose: Any) -> Any:
        def evaluate(windows: np.ndarray, first_row: int) -> dict[str, np.ndarray]:
            # windows (W, L, 2n); the stream carries [clipped | raw] side by side (process);
            # rows first_row .. L - 1 of each window: R = L - first_row
            raw = windows[..., state.n : 2 * state.n]
            u, F = decompose(windows[..., : state.n], first_row)  # (W, R, n), (W, R, L)
            noise_gain, dc_gain, row_scale = _row_scales(F, state.n_calibration)
            motion_factor = None
            if state.inflation is not None:
                # sampling-time jitter in motion (maths/jitter.py): a row's noise
                # variance grows by the filter's weighted mean of the samples' factors
                factors = windows[..., 2 * state.n]  # (W, L)
                motion_factor = np.einsum("wrl,wl->wr", F**2, factors) / noise_gain**2
            whitened = (u - dc_gain[..., None] * state.bias) / (
                state.sigma[None, :] * row_scale[..., None]
            )
            p = whitened @ state.V.T
            statistic = np.einsum("...j,...j->...", p, p)  # eq. 5, V V^T = I
            d_fi, signed = isolation_statistics(p, state.V)  # eq. 6
            # eq. 6 with its sign, standardized at rest: the budget's evidence
            evidence = np.sign(signed) * np.sqrt(d_fi)
            if motion_factor is not None:
                statistic = statistic / motion_factor
                d_fi = d_fi / motion_factor[..., None]
            if state.outlier_cut is not None:  # eq. 7 on the unclipped signal
                raw_white = (F @ raw - dc_gain[..., None] * state.bias) / (
                    state.sigma[None, :] * row_scale[..., None]
                )
                _, amplitude = isolation_statistics(raw_white @ state.V.T, state.V)
            else:
                _, amplitude = isolation_statistics(p, state.V)
            # amplitude of a step in the raw signal: undo whitening and the filter's DC gain
            scale = (
                state.sigma[None, :]
                * (row_scale / np.where(dc_gain != 0, dc_gain, np.nan))[..., None]
            )
            out = {"statistic": statistic, "scores": d_fi, "amplitude": amplitude * scale}
            out["evidence"] = evidence
            out["factor"] = np.ones(statistic.shape) if motion_factor is None else motion_factor
            # the u_best of the body-frame estimate, centred, in the evidence's row scale
            motion = state.motion
            assert motion is not None
            out["regressors"] = (
                u @ motion.estimator_t - dc_gain[..., None] * state.motion_centre
            ) / (row_scale[..., None] * state.state_gain)
            return out

        return evaluate

    # -- streaming ------------------------------------------------------------------

    def _rows(self, state: _TypeState, parts: list[dict[str, np.ndarray] | int]) -> DetectionBlock:
        if state.budget is not None:
            return self._budget_rows(state, parts)
        blocks = []
        for part in parts:
            if isinstance(part, int):  # rows no window decides
                blocks.append(DetectionBlock.empty(part, state.n))
                continue
            statistic = part["statistic"]
            count = statistic.shape[0]
            alarm = statistic > state.threshold
            scores = part["scores"]
            safe_scores = np.where(np.isfinite(scores), scores, -np.inf)
            best = np.argmax(safe_scores, axis=1).astype(np.int32)
            isolated = np.where(
                alarm, np.where(state.isolable[best], best, NOT_ISOLABLE), NO_ISOLATION
            ).astype(np.int32)
            amplitude = np.where(isolated >= 0, part["amplitude"][np.arange(count), best], np.nan)
            if state.monitor is not None:
                root = np.sqrt(part["factor"])[:, None]  # the test's own standardization
                state.monitor.add(part["evidence"] / root, part["regressors"] / root, alarm)
            blocks.append(
                DetectionBlock(
                    statistic=statistic,
                    threshold=np.full(count, state.threshold),
                    alarm=alarm,
                    isolated=isolated,
                    amplitude=amplitude,
                    scores=scores,
                )
            )
        if not blocks:
            return DetectionBlock.empty(0, state.n)
        return DetectionBlock.concatenate(blocks)

    def _budget_rows(
        self, state: _TypeState, parts: list[dict[str, np.ndarray] | int]
    ) -> DetectionBlock:
        """The rows of ``parts`` decided by the budget's bank (:func:`.budget.decide_rows`)."""
        assert state.budget is not None
        return decide_rows(state.budget, state.n, parts)

    def calibration_warnings(self) -> list[str]:
        """The per-sample test in motion: one warning per sensor type whose evidence
        followed the motion on the rows processed (a scale-factor or misalignment leak
        that test does not model, :mod:`.budget`), with the share of its variance the
        motion explains and the alarm rate; none under a budget (the bank learns it)."""
        alpha = float(self.params["alpha"])
        messages = (
            motion_warning(self.name, sensor_type, state.monitor, alpha)
            for sensor_type, state in self._states.items()
        )
        return [m for m in messages if m is not None]

    def process(self, block: ImuBlock) -> dict[str, DetectionBlock]:
        if not self._states or self._array is None:
            raise CalibrationError(f"{self.name}: fit() must be called before process()")
        out = {}
        for sensor_type, state in self._states.items():
            triads = block.get(sensor_type)
            if triads is None:
                raise InputDataError(f"{self.name}: block has no {sensor_type} data")
            values = self._array.select(triads, sensor_type)
            carried = self._carried(state, values, block.t_ns, state.inflation)
            evaluate = self._evaluators[sensor_type]
            out[sensor_type] = self._rows(state, state.stream.push(carried, evaluate))
        return out

    def flush(self) -> dict[str, DetectionBlock]:
        return {
            t: self._rows(s, s.stream.flush(self._evaluators[t])) for t, s in self._states.items()
        }

    def metadata(self) -> dict[str, Any]:
        params = {
            k: v
            for k, v in self.params.items()
            if k not in self.LATER_PARAMS or v != self.LATER_PARAMS[k]
        }
        return {
            "params": params,
            "types": {
                t: {
                    "K": s.K,
                    "mvmd_alpha": s.alpha,
                    "tuning": s.tuned,
                    "sigma_u_best": s.sigma.tolist(),
                    "bias_u_best": s.bias.tolist(),
                    "threshold": s.threshold,
                    "window": self.window,
                    "hop": self.hop,
                    "lookahead_samples": self.lookahead_samples,
                    "outlier_variance": s.outlier_variance,
                    "clipped_residuals": s.clipped,
                    **({"noise_spread": s.spread.tolist()} if s.spread is not None else {}),
                    **({"lever_arm_columns": s.lever_arm_columns} if s.lever_arm_columns else {}),
                    **({"budget": s.budget.metadata()} if s.budget is not None else {}),
                }
                for t, s in self._states.items()
            },
        }


__all__ = [
    "COMBINE_CHOICES",
    "DEFAULT_WEIGHTS",
    "FITNESS_CHOICES",
    "TuneResult",
    "ValidationFault",
    "WoaMvmdGltDetector",
    "best_mode",
    "cfv",
    "cfv_components",
    "clear_tuning_cache",
    "decompose_windows",
    "filter_matrices",
    "make_validation",
    "tune",
    "tune_signal",
    "tune_signals",
]
