"""cnn-map's input test (beyond the paper): a CUSUM on the leave-one-out residual energy of
every accelerometer axis (calibration, statistics, metadata).
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import DetectionBlock
from imufdi_cli.detectors.cnn_map.reference import _ReferenceRate
from imufdi_cli.detectors.cnn_map.signals import INPUT_DESIGN, INPUT_MEAN_S, INPUT_RELEASE_S
from imufdi_cli.detectors.cusum import (
    cusum_threshold,
    local_mean_residual,
    run_cusum,
)
from imufdi_cli.detectors.moving import MovingWindow
from imufdi_cli.detectors.noise_glr import (
    NoiseGlrDetector,
    clipped_square_moments,
    robust_scale,
)
from imufdi_cli.errors import (
    CalibrationError,
)
from imufdi_cli.log import ImuBlock


@functools.lru_cache(maxsize=32)
def _input_threshold(
    level: float, margin: float, calibration_dof: float, seed: int, mean_window: int
) -> float:
    """The input test's CUSUM threshold h (:func:`imufdi_cli.detectors.cusum.cusum_threshold`
    on ``INPUT_DESIGN``, from the generator seeded by ``[seed, 0x1C5]``), which is a function
    of these arguments alone: fits with the same settings and calibration length in one
    process (campaign runs, detectors refitted) simulate the null (256 chains of 17 408
    steps, about 0.3-1 s of CPU) once and get the same float."""
    return cusum_threshold(
        level,
        INPUT_DESIGN,
        margin,
        calibration_dof,
        np.random.default_rng([seed, 0x1C5]),
        mean_window=mean_window,
    )


class _InputTest(_ReferenceRate):
    """The CUSUM input test of :class:`CnnMapDetector`."""

    def _fit_input_test(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        """Step 8: leave-one-out accelerometer residuals and the CUSUM threshold.

        The residual model (rigid body with lever arms) is
        :class:`~imufdi_cli.detectors.noise_glr.NoiseGlrDetector`'s (accelerometers only).
        Each residual minus the mean of its ``INPUT_MEAN_S`` previous samples
        (:func:`imufdi_cli.detectors.cusum.local_mean_residual`) is standardized by its variance, estimated on
        the calibration window robustly (Huber's proposal 2 at the clip, noise-glr's
        ``robust_scale``). The per-channel level is the Šidák share over the tested
        channels of ``alpha`` (``alpha / 2`` when the mapping test alarms too); the
        threshold comes from :func:`imufdi_cli.detectors.cusum.cusum_threshold` (simulated null, seeded by
        ``seed``). Arrays whose accelerometers have no leave-one-out redundancy run the
        mapping test alone (at ``alpha``), noted in the metadata.
        """
        self._input = None
        self.input_note = "off (input_test=false)"
        self.mapping_alpha = self.alpha
        if not self.input_test:
            return
        glr = NoiseGlrDetector(alpha=self.alpha, types="accel", false_alarms=self.false_alarms)
        try:
            glr.fit(calibration, array)
        except CalibrationError as err:
            self.input_note = f"not run: {err}"
            return
        if "accel" not in glr.models:
            self.input_note = "not run: no redundant accelerometers"
            return
        model = glr.models["accel"]
        if model.budget is not None:  # the sequential test decides; no simulated threshold
            self._input = glr
            self.input_note = "on"
            return
        share = self.alpha / 2.0 if self.mapping_alarms else self.alpha
        self.input_mean_window = max(1, round(INPUT_MEAN_S * array.rate_hz))
        residuals = glr._residuals("accel", model, calibration)
        centred = local_mean_residual(residuals, self.input_mean_window)[self.input_mean_window :]
        if centred.shape[0] < 20:
            self.input_note = "not run: calibration window too short for the input test"
            return
        self._input = glr
        self.mapping_alpha = share
        moments = clipped_square_moments(INPUT_DESIGN.clip, 0.0)
        scale = robust_scale(centred, INPUT_DESIGN.clip, moments[0])
        self.input_scale = np.where(model.testable & (scale > 0), scale, 1.0)  # (n,), (m/s^2)^2
        self._input_past = np.zeros((0, model.operator.shape[0]))
        n_tested = int(model.testable.sum())
        self.input_level = -math.expm1(math.log1p(-share) / n_tested)
        self.input_margin = (
            INPUT_RELEASE_S
            * array.rate_hz
            * (INPUT_DESIGN.offset - INPUT_DESIGN.gain)  # |null drift| per sample
        )
        self.input_threshold = _input_threshold(
            self.input_level,
            self.input_margin,
            float(model.calibration_dof),
            self.seed,
            self.input_mean_window,
        )
        self.input_note = "on"
        self._input_state = np.zeros(model.operator.shape[0])
        self._input_window = MovingWindow(
            max(1, round(self.window_s * array.rate_hz)), model.operator.shape[0]
        )

    def _budget_statistics(self, block: ImuBlock) -> DetectionBlock:
        """The input test under a false-alarm budget: noise-glr's sequential test of the
        accelerometers (:class:`~imufdi_cli.detectors.noise_glr.NoiseBudget`)."""
        assert self._input is not None
        return self._input._decide("accel", self._input.models["accel"], block)

    def _input_statistics(self, block: ImuBlock) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Step 8 on one block: CUSUM (N, n_accel) (NaN for untested channels), windowed
        mean of z^2 (N, n_accel) and the added noise std estimate (N, n_accel), m/s^2."""
        assert self._input is not None
        model = self._input.models["accel"]
        residuals = self._input._residuals("accel", model, block)  # (N, n)
        z = local_mean_residual(residuals, self.input_mean_window, self._input_past)
        z /= np.sqrt(self.input_scale)
        self._input_past = np.concatenate([self._input_past, residuals])[-self.input_mean_window :]
        increments = INPUT_DESIGN.increments(z)
        increments[:, ~model.testable] = 0.0
        cusum, self._input_state = run_cusum(
            increments, self._input_state, self.input_threshold + self.input_margin
        )
        cusum[:, ~model.testable] = np.nan
        sums, counts = self._input_window.push(np.where(np.isnan(z), 1.0, np.square(z)))
        energy = sums / counts[:, None]  # variance ratio of the recent residuals
        # added variance: (energy - 1) x the nominal variance, scale / (1 + 1/W)
        nominal = self.input_scale / (1.0 + 1.0 / self.input_mean_window)
        added = np.sqrt(np.maximum(energy - 1.0, 0.0) * nominal)
        added[:, ~model.testable] = np.nan
        return cusum, energy, added

    def _input_metadata(self) -> dict[str, Any]:
        """Step 8 calibration (JSON-ready)."""
        info: dict[str, Any] = {"status": self.input_note}
        if self._input is None:
            return info
        model = self._input.models["accel"]
        if model.budget is not None:
            info.update({"lever_arm": bool(model.lever_arm), "budget": model.budget.metadata()})
            return info
        info.update(
            {
                "design_variance_ratio": INPUT_DESIGN.ratio,
                "mean_window_samples": int(self.input_mean_window),
                "clip_sigma": INPUT_DESIGN.clip,
                "channel_level": float(self.input_level),
                "threshold": float(self.input_threshold),
                "cap_above_threshold": float(self.input_margin),
                "lever_arm": bool(model.lever_arm),
                "tested": model.testable.tolist(),
                "residual_sigma": np.sqrt(
                    self.input_scale / (1.0 + 1.0 / self.input_mean_window)
                ).tolist(),
                "calibration_dof": float(model.calibration_dof),
            }
        )
        return info
