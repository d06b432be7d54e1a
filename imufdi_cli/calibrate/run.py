"""The calibration in order: static intervals, accelerometers, gyroscopes, noise levels,
jitter, in passes over the log's blocks (``calibrate_blocks``: memory independent of the
log's length); ``calibrate_block`` on samples in memory, ``calibrate_file`` on a log."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imufdi_cli.array import ArrayConfig, TriadCalibration
from imufdi_cli.calibrate.motion import (
    JITTER_LEVEL_ALPHA,
    TIME_OFFSET_WARNING,
    TimeOffsetSums,
    _zero_clipped_rows,
)
from imufdi_cli.calibrate.noise import (
    IntervalResiduals,
    calibrated_values,
    interval_pieces,
    store_noise,
    store_spread,
)
from imufdi_cli.calibrate.static import (
    STANDARD_GRAVITY,
    STATIC_WINDOW_S,
    StaticInterval,
    group_orientations,
)
from imufdi_cli.calibrate.triads import (
    ACCEL_GN_MAX_STEPS,
    GOOD_COVERAGE,
    GOOD_ORIENTATIONS,
    MIN_MOTION_RATE,
    MIN_ORIENTATIONS_MATRIX,
    TriadFigures,
    TriadMoments,
    _figures,
    _residual_rms,
    calibrate_accel,
    consensus_rms,
    gyro_calibration,
)
from imufdi_cli.errors import ArrayConfigError, CalibrationError
from imufdi_cli.log import ImuBlock
from imufdi_cli.maths.jitter import MAX_JITTER_S, fit_jitter_rows, jitter_dof, jitter_rows
from imufdi_cli.maths.parity import residual_projector
from imufdi_cli.maths.rigid import accel_design


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


# --- the passes ------------------------------------------------------------------------

#: A function giving the raw blocks of the log afresh at each call (one pass each).
Blocks = Callable[[], Iterable[ImuBlock]]


@dataclass
class _Rows:
    """One block of a pass: its first row, times (s from the first row), raw triads with
    the clipped and invalid rows zeroed, and those rows."""

    start: int
    t_s: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray | None
    clipped: np.ndarray

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


def _row_passes(array: ArrayConfig, blocks: Blocks) -> Callable[[], Iterator[_Rows]]:
    """Each call: one pass over ``blocks`` as :class:`_Rows`."""
    origin: list[int] = []

    def rows() -> Iterator[_Rows]:
        start = 0
        for block in blocks():
            if len(block) == 0:
                continue
            if block.accel is None:
                raise CalibrationError("calibrate needs accelerometers (the log has none)")
            if not origin:
                origin.append(int(block.t_ns[0]))
            accel, gyro, clipped = _zero_clipped_rows(array, block.accel, block.gyro)
            t_s = (block.t_ns - origin[0]).astype(np.float64) * 1e-9  # as ImuBlock.t_s()
            yield _Rows(start, t_s, accel, gyro, clipped)
            start += len(block)

    return rows


def _neighbours(rows: Iterator[_Rows]) -> Iterator[tuple[_Rows, _Rows | None, _Rows | None]]:
    """Each block with the last row before it and the first row after it (1-row
    :class:`_Rows`; None at the ends of the log)."""

    def first(r: _Rows) -> _Rows:
        return _Rows(
            r.start, r.t_s[:1], r.accel[:1], None if r.gyro is None else r.gyro[:1], r.clipped[:1]
        )

    def last(r: _Rows) -> _Rows:
        end = len(r) - 1
        return _Rows(
            r.start + end,
            r.t_s[end:],
            r.accel[end:],
            None if r.gyro is None else r.gyro[end:],
            r.clipped[end:],
        )

    held: _Rows | None = None
    before: _Rows | None = None
    for block in rows:
        if held is not None:
            yield held, before, first(block)
            before = last(held)
        held = block
    if held is not None:
        yield held, before, None


class _Layout:
    """Where the static intervals put every row: static (inside one), near static (within
    one static window of one, :func:`motion_rows`), and the per-interval row ranges."""

    def __init__(self, array: ArrayConfig, intervals: list[StaticInterval]) -> None:
        self.intervals = intervals
        self.ranges = [(item.first_row, item.end_row) for item in intervals]
        w = round(STATIC_WINDOW_S * array.rate_hz)
        self.near = [(max(a - w, 0), b + w) for a, b in self.ranges]

    @staticmethod
    def _mask(ranges: list[tuple[int, int]], start: int, size: int) -> np.ndarray:
        mask = np.zeros(size, dtype=bool)
        for a, b in ranges:
            lo, hi = max(a, start), min(b, start + size)
            if lo < hi:
                mask[lo - start : hi - start] = True
        return mask

    def static(self, r: _Rows) -> np.ndarray:
        return self._mask(self.ranges, r.start, len(r))

    def motion(self, r: _Rows) -> np.ndarray:
        """Rows more than one static window away from any static row, not clipped."""
        return ~self._mask(self.near, r.start, len(r)) & ~r.clipped


def _body_deviation_squares(
    array: ArrayConfig, triads: np.ndarray, cals: list[TriadCalibration] | None
) -> float:
    """Sum over rows, IMUs and axes of (body-frame value - array mean)^2 (the sums of
    :func:`~imufdi_cli.calibrate.triads._residual_rms`)."""
    if triads.shape[0] == 0:
        return 0.0
    rot = array.rotations()
    body = np.stack(
        [
            (triads[:, k] if cals is None else cals[k].apply(triads[:, k])) @ rot[k].T
            for k in range(triads.shape[1])
        ],
        axis=1,
    )
    return float(np.sum((body - body.mean(axis=1, keepdims=True)) ** 2))


def calibrate_block(
    array: ArrayConfig,
    block: ImuBlock,
    *,
    gravity: float = STANDARD_GRAVITY,
    min_static_s: float = 5.0,
    jitter_fit: str = "level",
) -> CalibrationResult:
    """Estimate every triad's calibration from raw samples in memory: :func:`calibrate_blocks`
    of the one block.

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
    if block.accel is None:
        raise CalibrationError("calibrate needs accelerometers (the log has none)")
    return calibrate_blocks(
        array, lambda: [block], gravity=gravity, min_static_s=min_static_s, jitter_fit=jitter_fit
    )


def calibrate_blocks(
    array: ArrayConfig,
    blocks: Blocks,
    *,
    gravity: float = STANDARD_GRAVITY,
    min_static_s: float = 5.0,
    jitter_fit: str = "level",
) -> CalibrationResult:
    """Estimate every triad's calibration from raw samples given block by block, in
    passes over them (``blocks()`` is called once per pass and must give the same rows
    each time), in memory independent of the number of rows (see the module docstring
    of :mod:`imufdi_cli.calibrate` for the estimates):

    1. static intervals: the per-row spread (moving standard deviation of the array
       consensus) to temporary files, its exact 10th percentile, the still runs
       (:class:`~imufdi_cli.calibrate.static.StaticScan`);
    2. the accelerometer means of every interval, the gyro bias at rest and the sums of
       the gyro rates' products in motion (:class:`TriadMoments`): the accelerometer and
       gyro ``M, b``;
    3. with that calibration: the parity residuals of every interval (noise levels and
       their spread over the orientations), the residual RMS between triads, the chip
       time offsets;
    4. with the noise levels: the sampling-time jitter (its per-row statistic to a
       temporary file, the level fit evaluated over it).

    Raises
    ------
    CalibrationError
        No accelerometers, no samples or no static interval (exit 3).
    """
    from imufdi_cli.calibrate.passes import Spool
    from imufdi_cli.calibrate.static import StaticScan

    started = time.perf_counter()
    warnings: list[str] = []
    passes = _row_passes(array, blocks)
    # --- pass 1: the static intervals -------------------------------------------------
    scan: StaticScan | None = None
    has_gyro = False
    last_t = 0.0
    clipped_rows = 0
    try:
        for r in passes():
            if scan is None:
                has_gyro = r.gyro is not None
                scan = StaticScan(array, has_gyro, min_static_s=min_static_s)
            scan.add(r.t_s, r.accel, r.gyro, ~r.clipped)
            clipped_rows += int(np.count_nonzero(r.clipped))
            last_t = float(r.t_s[-1])
        if scan is None:
            raise CalibrationError("calibrate: no samples in the selected time range")
        intervals = scan.finish()
    finally:
        if scan is not None:
            scan.close()
    if not intervals:
        raise CalibrationError(
            f"no static interval of at least {min_static_s:g} s found "
            f"({last_t:.3g} s examined): calibrate needs the array at rest in several"
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
    layout = _Layout(array, intervals)
    m = array.n_imus
    # --- pass 2: interval means, gyro bias and motion sums -----------------------------
    accel_sums = np.zeros((len(intervals), m, 3))
    accel_counts = np.zeros(len(intervals), np.int64)
    gyro_static_sum = np.zeros((m, 3))
    n_static = 0
    motion_sums = TriadMoments(m)
    n_motion = 0
    jitter_rows_found = False
    previous_motion: bool | None = None
    for r in passes():
        static = layout.static(r)
        for i, (a, b) in enumerate(layout.ranges):
            lo, hi = max(a, r.start), min(b, r.start + len(r))
            if lo < hi:
                accel_sums[i] += r.accel[lo - r.start : hi - r.start].sum(axis=0)
                accel_counts[i] += hi - lo
        n_static += int(np.count_nonzero(static))
        motion = layout.motion(r)
        n_motion += int(np.count_nonzero(motion))
        if r.gyro is not None:
            gyro_static_sum += r.gyro[static].sum(axis=0)
            motion_sums.add(r.gyro[motion])
        after = motion & np.concatenate([[bool(previous_motion)], motion[:-1]])
        jitter_rows_found |= bool(after.any())  # a moving row after a moving row
        previous_motion = bool(motion[-1])
    mean_arr = accel_sums / accel_counts[:, None, None]  # (I, m, 3)
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
    full_gyro = False
    gyro_cal: list[TriadCalibration] | None = None
    if has_gyro:
        biases = gyro_static_sum / n_static
        motion_s = float(n_motion / array.rate_hz)
        if n_motion:
            rms = consensus_rms(array, motion_sums, biases)
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
        gyro_cal = gyro_calibration(array, biases, motion_sums, full_gyro)
        for k, gcal in enumerate(gyro_cal):
            cals[k]["gyro"] = gcal
    calibrated = array.with_calibration(cals)
    # --- pass 3: noise, its spread, the gyro residual, time offsets --------------------
    types = [
        s for s in ("accel", "gyro") if (s == "accel" or has_gyro) and calibrated.n_sensors(s) >= 4
    ]
    projectors = {s: residual_projector(calibrated.measurement_matrix(s)) for s in types}
    pieces = interval_pieces(intervals, np.zeros(0), np.zeros(0, bool))
    noise_sums = {s: IntervalResiduals(projectors[s].shape[0], pieces, intervals) for s in types}
    static_values = {s: np.zeros(projectors[s].shape[0]) for s in types}
    gyro_squares = [0.0, 0.0]  # before, after the calibration
    gyro_rows = 0
    offsets_sums = TimeOffsetSums(m)
    inner_rows = 0
    gyro_only = (
        array.with_calibration([{"gyro": c} for c in gyro_cal]) if full_gyro and gyro_cal else None
    )
    for r, before, after in _neighbours(passes()):
        static = layout.static(r)
        motion = layout.motion(r)
        for s in types:
            raw = r.accel if s == "accel" else r.gyro
            assert raw is not None
            values = calibrated_values(calibrated, raw, s)
            noise_sums[s].add(r.start, values @ projectors[s].T)
            static_values[s] += values[static].sum(axis=0)
        if r.gyro is not None and gyro_cal is not None:
            sample = r.gyro[motion] if n_motion else r.gyro[static]
            gyro_squares[0] += _body_deviation_squares(array, sample, None)
            gyro_squares[1] += _body_deviation_squares(array, sample, gyro_cal)
            gyro_rows += int(sample.shape[0])
        if gyro_only is not None:
            inner_rows += _add_time_offsets(
                array, gyro_only, layout, r, before, after, offsets_sums
            )
    if gyro_cal is not None:
        residual["gyro"] = tuple(  # type: ignore[assignment]
            float(np.sqrt(v / (gyro_rows * m * 3))) if gyro_rows else float("nan")
            for v in gyro_squares
        )
    offsets = explained = np.zeros(0)
    if gyro_only is not None:
        offsets, explained = (
            offsets_sums.result() if inner_rows >= 3 else (np.zeros(m), np.zeros(m))
        )
        if np.any(explained > TIME_OFFSET_WARNING):
            worst = int(np.argmax(explained))
            warnings.append(
                f"chip sampling-time offsets (up to {abs(offsets[worst]) * 1e3:.3g} ms on"
                f" imu{worst}) explain {explained[worst]:.0%} of its gyro residual in"
                " motion; they are not compensated"
            )
    noise: list[dict[str, np.ndarray]] = [{} for _ in range(m)]
    spread: list[dict[str, np.ndarray]] = [{} for _ in range(m)]
    for s in types:
        store_noise(calibrated, s, noise_sums[s], projectors[s], noise)
        store_spread(calibrated, s, noise_sums[s], projectors[s], spread, {})
    figures = [
        _figures(k, s, c)
        for k, per in enumerate(cals)
        for s, c in sorted(per.items(), reverse=True)
    ]
    out = calibrated.with_sensor_noise(noise).with_noise_spread(spread)
    # --- pass 4: the sampling-time jitter ----------------------------------------------
    jitter: dict[str, float] = {}
    if jitter_fit != "off" and jitter_rows_found:
        alpha = JITTER_LEVEL_ALPHA if jitter_fit == "level" else None
        models = _jitter_models(out, types, static_values, n_static)
        spools = {s: (Spool(np.float64), Spool(np.float64)) for s in models}
        try:
            for r, before, _ in _neighbours(passes()):
                _add_jitter_rows(out, layout, models, r, before, spools)
            for s, (_, dof, _, _) in models.items():
                jitter[s] = fit_jitter_rows(_pair_chunks(spools[s]), dof, alpha)
        finally:
            for pair in spools.values():
                for spool in pair:
                    spool.close()
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
        static_s=float(n_static / array.rate_hz),
        motion_s=motion_s,
        clipped_rows=clipped_rows,
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


def _extended(parts: list[_Rows | None], field: str) -> np.ndarray:
    """``field`` of the given blocks (None skipped) end to end."""
    return np.concatenate([getattr(p, field) for p in parts if p is not None])


def _add_time_offsets(
    array: ArrayConfig,
    gyro_only: ArrayConfig,
    layout: _Layout,
    r: _Rows,
    before: _Rows | None,
    after: _Rows | None,
    sums: TimeOffsetSums,
) -> int:
    """Add a block's rows to the time-offset sums (:func:`time_offsets`): the calibrated
    gyro consensus differentiated with ``np.gradient`` over the block and its neighbour
    rows (each row's central difference; one-sided at the ends of the log), on the motion
    rows whose neighbours are usable too (never the log's first or last row). Returns how
    many rows were added."""
    parts = [before, r, after]
    gyro = _extended(parts, "gyro")
    if gyro.shape[0] < 2:
        return 0
    t_s = _extended(parts, "t_s")
    usable = ~_extended(parts, "clipped")
    shift = 0 if before is None else 1
    k = len(r)
    body = np.einsum("kij,nkj->nki", array.rotations(), gyro_only.calibrate_triads(gyro, "gyro"))
    consensus = body.mean(axis=1)
    rate_dot = np.gradient(consensus, t_s, axis=0)
    inner = layout.motion(r)
    rows = np.arange(k) + shift  # the block's rows in the extended arrays
    has_prior = rows - 1 >= 0
    has_next = rows + 1 < usable.size
    inner &= has_prior & has_next
    inner[inner] &= usable[rows[inner] - 1] & usable[rows[inner] + 1]
    picked = rows[inner]
    sums.add(body[picked], consensus[picked], rate_dot[picked])
    return int(picked.size)


def _pair_chunks(pair: tuple[Any, Any]) -> Callable[[], Iterator[tuple[np.ndarray, np.ndarray]]]:
    """The jitter rows of two spools (statistic, energy), chunk by chunk, at each call."""
    from imufdi_cli.calibrate.passes import spool_chunks

    def chunks() -> Iterator[tuple[np.ndarray, np.ndarray]]:
        return ((statistic, energy) for statistic, energy in spool_chunks(pair))

    return chunks


def _jitter_models(
    out: ArrayConfig, types: list[str], static_values: dict[str, np.ndarray], n_static: int
) -> dict[str, tuple[np.ndarray, int, np.ndarray, np.ndarray | None]]:
    """Per sensor type fitted by :func:`jitter_stage`: whitened design, parity dimensions,
    noise sigmas and the whitened mean at rest (the offset removed)."""
    models = {}
    for s in types:
        sigma = out.sensor_noise(s)
        if sigma is None:
            continue
        design = out.measurement_matrix(s)
        if s == "accel":
            try:
                design = accel_design(out, s)
            except ArrayConfigError:
                pass
        if design.shape[0] <= design.shape[1]:
            continue
        h_white = design / sigma[:, None]
        offset = static_values[s] / n_static / sigma if n_static else None
        models[s] = (h_white, jitter_dof(h_white), sigma, offset)
    return models


def _add_jitter_rows(
    out: ArrayConfig,
    layout: _Layout,
    models: dict[str, tuple[np.ndarray, int, np.ndarray, np.ndarray | None]],
    r: _Rows,
    before: _Rows | None,
    spools: dict[str, tuple[Any, Any]],
) -> None:
    """A block's jitter rows (moving rows after a moving row, never the log's first) to
    the spools: their statistic and motion energy (:func:`jitter_rows`, with the
    predecessor row from the block before)."""
    motion = layout.motion(r)
    prior_motion = np.r_[layout.motion(before) if before is not None else [False], motion[:-1]]
    use = motion & prior_motion
    if not use.any():
        return
    shift = 0 if before is None else 1
    rows = np.flatnonzero(use) + shift  # in the extended arrays; every one has a predecessor
    t_s = _extended([before, r], "t_s")
    dt = t_s[rows] - t_s[rows - 1]
    for s, (h_white, _, sigma, offset) in models.items():
        raw = _extended([before, r], s)
        white = calibrated_values(out, raw, s) / sigma
        statistic, energy = jitter_rows(h_white, white[rows], white[rows - 1], dt, offset)
        spools[s][0].append(statistic)
        spools[s][1].append(energy)


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
    """Read a log in blocks, recover raw chip values and estimate the calibration
    (:func:`calibrate_blocks`: the log is read once per pass; memory does not grow with
    its length).

    ``base`` (``--array``) gives the geometry; default the log's ``imufdi.array``. The
    log's own calibration (if it was ingested with one) is undone first, so the result is
    relative to the raw chip output, as ``ingest --array`` and ``detect --array`` expect.
    The reader's warnings (a damaged file, an IMU that stops) come first in the result's.
    """
    from imufdi_cli.mcapio import ImuArrayReader

    started = time.perf_counter()
    stream, close = _seekable(source)
    try:
        with ImuArrayReader(stream, topics=topics) as reader:
            log_array = reader.array
            reader_warnings = list(reader.warnings)
        array = log_array if base is None else base.check_matches(log_array)
        array = array.with_range(log_array.range)
        seen: list[str] = []
        origin: list[int] = []
        bounds: list[tuple[float, float | None]] = []  # the window, seconds from the start

        def blocks() -> Iterator[ImuBlock]:
            if not isinstance(stream, str):
                stream.seek(0)
            with ImuArrayReader(stream, topics=topics) as reader:
                for block in reader.blocks():
                    if not origin:
                        origin.append(int(block.t_ns[0]))
                        if window is not None:  # absolute times resolved on the log start
                            from imufdi_cli.units import window_from_log_start

                            bounds.append(window_from_log_start(window, origin[0]))
                    fields: dict[str, np.ndarray | None] = {}
                    for s in ("gyro", "accel", "mag"):
                        data = block.get(s)
                        fields[s] = (
                            None if data is None else log_array.calibrate_triads(data, s, undo=True)
                        )
                    raw = ImuBlock(t_ns=block.t_ns, **fields)
                    if bounds:
                        start_s, end_s = bounds[0]
                        rel = (raw.t_ns - origin[0]).astype(np.float64) * 1e-9
                        keep = rel >= start_s
                        if end_s is not None:
                            keep &= rel < end_s
                        raw = raw.mask(keep)
                    yield raw
                if not seen:
                    seen.extend(reader.warnings)

        try:
            result = calibrate_blocks(
                array.with_calibration(None),
                blocks,
                gravity=gravity,
                min_static_s=min_static_s,
                jitter_fit=jitter_fit,
            )
        except CalibrationError:
            if not origin:  # not one sample in the log, whatever the window
                raise CalibrationError(f"{source}: no aligned IMU samples") from None
            raise
    finally:
        if close:
            stream.close()  # type: ignore[union-attr]
    result.warnings = list(dict.fromkeys([*reader_warnings, *seen])) + result.warnings
    result.runtime_s = time.perf_counter() - started
    return result


def _seekable(source: str) -> tuple[Any, bool]:
    """A path, or stdin spooled to a temporary file (the log is read once per pass)."""
    import shutil
    import sys
    import tempfile

    if source != "-":
        return source, False
    spool = tempfile.TemporaryFile(prefix="imufdi-calibrate-")
    shutil.copyfileobj(sys.stdin.buffer, spool, 1 << 20)
    spool.seek(0)
    return spool, True
