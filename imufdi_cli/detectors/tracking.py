"""Slow bias tracking, shared by the parity detectors (``track_bias`` parameter).

Real MEMS gyro biases wander (about 0.05 deg/s over 8 minutes on the MIMU4444 board,
docs/real-arrays.md): a bias calibrated in the first seconds of a log slowly drifts into
the parity residual, and tests that average (pca-parity's moving mean) alarm on it. The
tracker follows each sensor's offset from the array consensus with an exponential average
of time constant ``tau`` and removes its change since the calibration window::

    r_t = P y_t                                  (P = I - H H^+: the parity residual of y)
    e_t = e_{t-1} + (dt / tau) clip(r_t - e_{t-1}, +-gate sigma)
    y'_t = y_t - P (e_{t-1} - e_0)               (e_0: mean residual of the calibration window)

The correction lies in the residual space (``P c = c``), so the consensus estimate is
unchanged; only slow parity offsets are removed. The clip bounds how fast a fault can be
absorbed (at most ``gate sigma dt / tau`` per sample).

**Trade-off.** Whatever is slow enough is tracked, faults included: a drift fault of rate
``k`` leaves a steady residual of only ``k tau`` (the tracker's lag) instead of growing
without bound, so drifts with ``k tau`` below the detection level are never seen; a step
of amplitude ``A`` decays as ``A exp(-t / tau)`` (by 15 % after 10 s at ``tau = 60 s``).
``track_bias = 0`` (the default of the per-sample tests) turns it off. Measured on the MIMU4444 recordings in
docs/real-arrays.md.
"""

from __future__ import annotations

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import Param
from imufdi_cli.log import ImuBlock
from imufdi_cli.maths.parity import residual_projector

#: The detector parameter (seconds; 0 = off).
TRACK_BIAS = Param(
    "time",
    None,
    "slow bias tracking time constant, e.g. 60s (default: 60 s under a false-alarm budget,"
    " off for the per-sample test; 0 = off; docs/real-arrays.md)",
    low=0.0,
)
#: Innovation clip, in per-sensor sigmas.
GATE_SIGMA = 3.0


class BiasTracker:
    """Exponential tracking of per-sensor parity offsets (see the module docstring).

    Parameters
    ----------
    tau_s : float
        Time constant, seconds; 0 disables tracking (``apply`` returns its input).
    """

    def __init__(self, tau_s: float | None = 0.0) -> None:
        self.tau_s = float(tau_s or 0.0)
        self.array: ArrayConfig | None = None
        self._state: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}

    @property
    def enabled(self) -> bool:
        return self.tau_s > 0

    def fit(
        self,
        calibration: ImuBlock,
        array: ArrayConfig,
        designs: dict[str, np.ndarray] | None = None,
    ) -> None:
        """Projector, per-sensor sigma and reference offset of every type with parity.

        ``designs``: the measurement matrix (n, q) a detector uses per type (e.g. with
        lever-arm columns, :mod:`.rigid`); default the array's H (n, 3)."""
        self.array = array
        self._state = {}
        if not self.enabled:
            return
        for sensor_type in array.sensor_types():
            triads = calibration.get(sensor_type)
            h = (designs or {}).get(sensor_type)
            if h is None:
                h = array.measurement_matrix(sensor_type)
            if triads is None or h.shape[0] <= h.shape[1] or len(calibration) < 2:
                continue
            projector = residual_projector(h)
            residual = array.select(triads, sensor_type) @ projector.T
            reference = residual.mean(axis=0)
            sigma = np.maximum(residual.std(axis=0), 1e-12)
            self._state[sensor_type] = (projector, sigma, reference, reference.copy())

    def apply(self, block: ImuBlock) -> ImuBlock:
        """The block with tracked offset changes removed (state carried across blocks)."""
        if not self.enabled or not self._state or self.array is None or len(block) == 0:
            return block
        step = 1.0 / (self.tau_s * self.array.rate_hz)
        fields: dict[str, np.ndarray | None] = {
            "gyro": block.gyro,
            "accel": block.accel,
            "mag": block.mag,
        }
        for sensor_type, (projector, sigma, reference, estimate) in self._state.items():
            triads = block.get(sensor_type)
            if triads is None:
                continue
            values = self.array.select(triads, sensor_type)
            residual = values @ projector.T
            correction = np.empty_like(values)
            gate = GATE_SIGMA * sigma
            for i in range(values.shape[0]):
                correction[i] = estimate - reference
                estimate += step * np.clip(residual[i] - estimate, -gate, gate)
            # the clip is per sensor: project back so the consensus stays untouched
            correction = correction @ projector.T
            out = triads.copy()
            imu_idx, axis_idx = self.array.sensor_index(sensor_type)
            out[:, imu_idx, axis_idx] = values - correction
            fields[sensor_type] = out
        return ImuBlock(t_ns=block.t_ns, **fields)

    def metadata(self) -> dict[str, list[float]]:
        """Per type, the tracked offset change at the end of the run (SI)."""
        return {s: (e - r).tolist() for s, (_, _, r, e) in self._state.items()}
