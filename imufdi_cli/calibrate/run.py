"""The calibration in order: static intervals, accelerometers, gyroscopes, noise levels,
jitter; ``calibrate_block`` on samples in memory, ``calibrate_file`` on a log."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imufdi_cli.array import ArrayConfig, TriadCalibration
from imufdi_cli.calibrate.motion import (
    TIME_OFFSET_WARNING,
    _zero_clipped_rows,
    jitter_stage,
    motion_rows,
    time_offsets,
)
from imufdi_cli.calibrate.noise import calibrated_values, noise_spread, static_noise
from imufdi_cli.calibrate.static import (
    STANDARD_GRAVITY,
    StaticInterval,
    body_consensus,
    find_static,
    group_orientations,
)
from imufdi_cli.calibrate.triads import (
    ACCEL_GN_MAX_STEPS,
    GOOD_COVERAGE,
    GOOD_ORIENTATIONS,
    MIN_MOTION_RATE,
    MIN_ORIENTATIONS_MATRIX,
    TriadFigures,
    _figures,
    _residual_rms,
    calibrate_accel,
    calibrate_gyro,
)
from imufdi_cli.errors import CalibrationError
from imufdi_cli.log import ImuBlock
from imufdi_cli.maths.jitter import MAX_JITTER_S


@dataclass
class CalibrationResult:
    """What ``imufdi calibrate`` estimated and measured."""

    array: ArrayConfig
    intervals: list[StaticInterval]
    orientations: int
    coverage: float
    static_s: float
    motion_s: float
    clipped_rows: int
    figures: list[TriadFigures]
    residual_rms: dict[str, tuple[float, float]]  # type -> (before, after), SI
    warnings: list[str] = field(default_factory=list)
    runtime_s: float = 0.0
    time_offsets_s: list[float] = field(default_factory=list)  # per IMU, gyro motion
    time_offset_explained: list[float] = field(default_factory=list)  # share of residual
    jitter_s: dict[str, float] = field(default_factory=dict)  # per type, sampling jitter

    def to_dict(self) -> dict[str, Any]:
        return {
            "intervals": [i.to_dict() for i in self.intervals],
            "orientations": self.orientations,
            "coverage": self.coverage,
            "static_s": self.static_s,
            "motion_s": self.motion_s,
            "clipped_rows": self.clipped_rows,
            "residual_rms": {k: list(v) for k, v in self.residual_rms.items()},
            "triads": [f.__dict__ for f in self.figures],
            "warnings": self.warnings,
            "time_offsets_s": self.time_offsets_s,
            "time_offset_explained": self.time_offset_explained,
            "jitter_s": self.jitter_s,
        }


# --- static intervals ------------------------------------------------------------------


def _gyro_stage(
    array: ArrayConfig,
    gyro: np.ndarray,
    t_s: np.ndarray,
    static: np.ndarray,
    clipped: np.ndarray,
    warnings: list[str],
) -> tuple[list[TriadCalibration], float, np.ndarray, np.ndarray, tuple[float, float]]:
    """Gyro calibration of :func:`calibrate_block`: biases from the static rows, matrices
    when the motion excites every body axis, chip time offsets (reported, not compensated).

    Parameters
    ----------
    gyro : (N, m, 3) rad/s, clipped rows zeroed; t_s : (N,) s; static, clipped : (N,) bool.
    warnings : appended to.

    Returns
    -------
    (per-IMU gyro calibrations, motion duration s, time offsets (m,) s or empty,
    share of the residual they explain (m,) or empty, residual RMS before/after, rad/s)
    """
    offsets = explained = np.zeros(0)
    motion = motion_rows(array, static, clipped)
    motion_s = float(np.count_nonzero(motion) / array.rate_hz)
    full_gyro = False
    if motion.any():
        consensus = body_consensus(array, gyro[motion] - gyro[static].mean(axis=0))
        rms = np.sqrt(np.mean(consensus**2, axis=0))
        full_gyro = bool(np.all(rms >= MIN_MOTION_RATE))
        if not full_gyro:
            warnings.append(
                "motion RMS rate per body axis "
                + "/".join(f"{np.degrees(v):.1f}" for v in rms)
                + f" deg/s: gyro matrices need >= {np.degrees(MIN_MOTION_RATE):g} deg/s on"
                " every axis; gyro biases only"
            )
    else:
        warnings.append("no motion in the log: gyro biases only (matrices need motion)")
    gyro_cal = calibrate_gyro(array, gyro, static, motion, full_gyro)
    if full_gyro:
        calibrated = array.with_calibration([{"gyro": c} for c in gyro_cal])
        # motion rows whose neighbours are usable too (central differences)
        inner = motion & np.roll(~clipped, 1) & np.roll(~clipped, -1)
        inner[[0, -1]] = False
        offsets, explained = time_offsets(
            array, calibrated.calibrate_triads(gyro, "gyro"), t_s, inner
        )
        if np.any(explained > TIME_OFFSET_WARNING):
            worst = int(np.argmax(explained))
            warnings.append(
                f"chip sampling-time offsets (up to {abs(offsets[worst]) * 1e3:.3g} ms on"
                f" imu{worst}) explain {explained[worst]:.0%} of its gyro residual in"
                " motion; they are not compensated"
            )
    sample = gyro[motion] if motion.any() else gyro[static]
    residual = (_residual_rms(array, sample, None), _residual_rms(array, sample, gyro_cal))
    return gyro_cal, motion_s, offsets, explained, residual


def calibrate_block(
    array: ArrayConfig,
    block: ImuBlock,
    *,
    gravity: float = STANDARD_GRAVITY,
    min_static_s: float = 5.0,
    jitter_fit: str = "level",
) -> CalibrationResult:
    """Estimate every triad's calibration from raw samples (see the module docstring).

    Parameters
    ----------
    array : ArrayConfig
        Geometry (rotations) of the array; its own calibration is ignored (replaced).
    block : ImuBlock
        Raw (uncalibrated) samples, N rows, accelerometers required.
    gravity : float
        |f| at rest, m/s^2.
    min_static_s : float
        Shortest static interval used, s.
    jitter_fit : {"level", "moments", "off"}
        How the sampling-time jitter is fitted (:func:`jitter_stage`).

    Raises
    ------
    CalibrationError
        No accelerometers or no static interval (exit 3).
    """
    started = time.perf_counter()
    warnings: list[str] = []
    if block.accel is None:
        raise CalibrationError("calibrate needs accelerometers (the log has none)")
    if len(block) == 0:
        raise CalibrationError("calibrate: no samples in the selected time range")
    accel, gyro, clipped = _zero_clipped_rows(array, block.accel, block.gyro)
    t_s = block.t_s()
    intervals, static = find_static(array, accel, gyro, t_s, ~clipped, min_static_s=min_static_s)
    if not intervals:
        raise CalibrationError(
            f"no static interval of at least {min_static_s:g} s found "
            f"({t_s[-1] - t_s[0]:.3g} s examined): calibrate needs the array at rest in several"
            " orientations (accelerometers) and at rest at least once (gyro biases)"
        )
    orientations, coverage = group_orientations(intervals)
    full_accel = orientations >= MIN_ORIENTATIONS_MATRIX and coverage > 0.05
    if not full_accel:
        warnings.append(
            f"only {orientations} orientation(s) (coverage {coverage:.2f}): accelerometer"
            f" matrices need >= {MIN_ORIENTATIONS_MATRIX} non-coplanar orientations;"
            " biases only (relative to the array consensus)"
        )
    elif orientations < GOOD_ORIENTATIONS or coverage < GOOD_COVERAGE:
        warnings.append(
            f"{orientations} orientations, coverage {coverage:.2f}: the accelerometer"
            f" matrices are weakly determined (aim for >= {GOOD_ORIENTATIONS} orientations"
            f" spread over the sphere, coverage >= {GOOD_COVERAGE})"
        )
    means = []
    for item in intervals:
        rows = (t_s >= item.start_s) & (t_s <= item.end_s) & static
        means.append(accel[rows].mean(axis=0))
    mean_arr = np.stack(means)  # (I, m, 3)
    accel_cal, iterations = calibrate_accel(array, mean_arr, gravity, full_accel)
    if full_accel and iterations >= ACCEL_GN_MAX_STEPS:
        warnings.append(
            f"accelerometer fit stopped after {iterations} iterations without converging"
        )
    residual = {
        "accel": (_residual_rms(array, mean_arr, None), _residual_rms(array, mean_arr, accel_cal))
    }
    cals: list[dict[str, TriadCalibration]] = [{"accel": c} for c in accel_cal]
    motion_s = 0.0
    offsets = explained = np.zeros(0)
    if gyro is not None:
        gyro_cal, motion_s, offsets, explained, residual["gyro"] = _gyro_stage(
            array, gyro, t_s, static, clipped, warnings
        )
        for k, gcal in enumerate(gyro_cal):
            cals[k]["gyro"] = gcal
    calibrated = array.with_calibration(cals)
    # the calibrated sensors, computed once for the noise, spread and jitter stages (the
    # same calibration in all three)
    values = {
        s: calibrated_values(calibrated, raw, s)
        for s, raw in (("accel", accel), ("gyro", gyro))
        if raw is not None and calibrated.n_sensors(s) >= 4
    }
    noise = static_noise(calibrated, accel, gyro, t_s, static, intervals, values=values)
    spread, _ = noise_spread(calibrated, accel, gyro, t_s, static, intervals, values=values)
    figures = [
        _figures(k, s, c)
        for k, per in enumerate(cals)
        for s, c in sorted(per.items(), reverse=True)
    ]
    out = calibrated.with_sensor_noise(noise).with_noise_spread(spread)
    jitter = jitter_stage(
        out, {"accel": accel, "gyro": gyro}, t_s, static, clipped, jitter_fit, values=values
    )
    for sensor_type, value in jitter.items():
        if value >= MAX_JITTER_S:
            warnings.append(
                f"{sensor_type}: no sampling-time jitter up to {MAX_JITTER_S * 1e3:g} ms holds the"
                " level in this log's motion (residuals unrelated to the motion?); the tests"
                " will be blind in motion: check the calibration, or --jitter-fit moments/off"
            )
    out = out.with_jitter(jitter)
    result = CalibrationResult(
        array=out,
        intervals=intervals,
        orientations=orientations,
        coverage=coverage,
        static_s=float(np.count_nonzero(static) / array.rate_hz),
        motion_s=motion_s,
        clipped_rows=int(np.count_nonzero(clipped)),
        figures=figures,
        residual_rms=residual,
        warnings=warnings,
        runtime_s=time.perf_counter() - started,
        jitter_s=jitter,
    )
    if offsets.size:
        result.time_offsets_s = [float(v) for v in offsets]
        result.time_offset_explained = [float(v) for v in explained]
    return result


def calibrate_file(
    source: str,
    *,
    window: tuple[float, float | None] | None = None,
    base: ArrayConfig | None = None,
    gravity: float = STANDARD_GRAVITY,
    min_static_s: float = 5.0,
    topics: list[str] | None = None,
    jitter_fit: str = "level",
) -> CalibrationResult:
    """Read a log, recover raw chip values and estimate the calibration.

    ``base`` (``--array``) gives the geometry; default the log's ``imufdi.array``. The
    log's own calibration (if it was ingested with one) is undone first, so the result is
    relative to the raw chip output, as ``ingest --array`` and ``detect --array`` expect.
    """
    from imufdi_cli.mcapio import read_array

    started = time.perf_counter()
    log_array, block = read_array(source, topics=topics)
    if len(block) == 0:
        raise CalibrationError(f"{source}: no aligned IMU samples")
    array = log_array if base is None else base.check_matches(log_array)
    array = array.with_range(log_array.range)
    fields: dict[str, np.ndarray | None] = {}
    for s in ("gyro", "accel", "mag"):
        data = block.get(s)
        fields[s] = None if data is None else log_array.calibrate_triads(data, s, undo=True)
    raw = ImuBlock(t_ns=block.t_ns, **fields)
    if window is not None:
        from imufdi_cli.units import window_from_log_start

        start_s, end_s = window_from_log_start(window, int(raw.t_ns[0]) if len(raw) else 0)
        rel = raw.t_s()
        keep = rel >= start_s
        if end_s is not None:
            keep &= rel < end_s
        raw = raw.mask(keep)
    result = calibrate_block(
        array.with_calibration(None),
        raw,
        gravity=gravity,
        min_static_s=min_static_s,
        jitter_fit=jitter_fit,
    )
    result.runtime_s = time.perf_counter() - started
    return result
