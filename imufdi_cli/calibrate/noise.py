"""Each sensor's white-noise level after calibration, pooled over the static intervals, and
its healthy spread over the orientations (``<type>_noise``, ``<type>_noise_spread``)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.calibrate.static import StaticInterval
from imufdi_cli.maths.parity import residual_projector


def static_noise(
    array: ArrayConfig,
    accel: np.ndarray,
    gyro: np.ndarray | None,
    t_s: np.ndarray,
    static: np.ndarray,
    intervals: list[StaticInterval],
    *,
    values: Mapping[str, np.ndarray] | None = None,
) -> list[dict[str, np.ndarray]]:
    """Per-IMU, per-type noise sigma (3,) of the calibrated sensors at rest (SI).

    For every sensor type with a parity space (>= 4 sensors), the least-squares residuals
    ``r = (I - H H^+) m`` of each static interval (motion and common offsets cancel) about
    their interval mean give pooled residual variances ``v`` (weighted by the intervals'
    sample counts); per-sensor variances solve ``((I - S) o (I - S)) sigma^2 = v`` as in
    :func:`~imufdi_cli.maths.parity.residual_sigma` (plain least squares: the pooled
    system is well determined; a non-positive solution falls back to the common
    ``sum v / (n - 3)``). Axes a type lacks keep no entry.

    In memory: :class:`IntervalResiduals` fed once (``calibrate`` streams them).

    Parameters
    ----------
    array : ArrayConfig
        Geometry with the chip calibration to apply.
    accel, gyro : ndarray, shape (N, m, 3)
        Raw samples (SI).
    t_s : ndarray, shape (N,)
    static : ndarray, shape (N,), bool
    intervals : list of StaticInterval
    values : mapping, optional
        Per sensor type, the calibrated values of ``accel``/``gyro`` in sensor-id order
        (N, n), ``array.select(array.calibrate_triads(raw, type), type)``, when the caller
        has them; else computed here.
    """
    out: list[dict[str, np.ndarray]] = [{} for _ in range(array.n_imus)]
    pieces = interval_pieces(intervals, t_s, static)
    for sensor_type, raw in (("accel", accel), ("gyro", gyro)):
        if raw is None or array.n_sensors(sensor_type) < 4:
            continue
        given = None if values is None else values.get(sensor_type)
        projector, residual = _parity_residuals(array, raw, sensor_type, given)
        acc = IntervalResiduals(projector.shape[0], pieces, intervals)
        acc.add(0, residual)
        store_noise(array, sensor_type, acc, projector, out)
    return out


def store_noise(
    array: ArrayConfig,
    sensor_type: str,
    acc: IntervalResiduals,
    projector: np.ndarray,
    out: list[dict[str, np.ndarray]],
) -> None:
    """:func:`static_noise`'s per-sensor sigmas of one type from its pooled interval
    variances, into ``out[imu][type]``."""
    variances = acc.pooled_variances()
    if variances is None:
        return
    n = projector.shape[0]
    sigma2, *_ = np.linalg.lstsq(projector**2, variances, rcond=None)
    if not np.all(sigma2 > 0):
        sigma2 = np.full(n, variances.sum() / (n - 3))
    _scatter_triads(array, sensor_type, np.sqrt(sigma2), out)


def interval_pieces(
    intervals: list[StaticInterval], t_s: np.ndarray, static: np.ndarray
) -> list[tuple[int, int, int]]:
    """``(interval index, first row, end row)``: the runs of static rows of each interval
    (its ``first_row:end_row`` when known; else the rows from its start to its end time,
    ``np.searchsorted`` on ``t_s``), sorted by first row."""
    pieces = []
    for index, item in enumerate(intervals):
        if item.first_row >= 0:
            pieces.append((index, item.first_row, item.end_row))
            continue
        lo, hi = np.searchsorted(t_s, [item.start_s, item.end_s], side="left")
        hi = min(int(hi) + 1, len(t_s))
        inside = np.asarray(static[lo:hi], bool)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], inside.astype(np.int8), [0]])))
        pieces += [(index, int(lo + a), int(lo + b)) for a, b in zip(edges[::2], edges[1::2])]
    return sorted(pieces, key=lambda p: p[1])


class IntervalResiduals:
    """Parity residuals of the static intervals, streamed: per interval the count, mean
    and sum of squared deviations (merged block by block, Chan et al.'s pairwise update),
    for :func:`static_noise`; per orientation the sum of squared successive differences
    and their count, for :func:`noise_spread`.

    Parameters
    ----------
    n : int
        Sensors of the type.
    pieces : list of (interval index, first row, end row)
        The rows to use (:func:`interval_pieces`), sorted by first row.
    intervals : list of StaticInterval
        With their ``orientation`` numbers (for the differences).
    """

    def __init__(
        self, n: int, pieces: list[tuple[int, int, int]], intervals: list[StaticInterval]
    ) -> None:
        self.pieces = pieces
        self.starts = np.array([p[1] for p in pieces], dtype=np.int64)
        self.orientation = [item.orientation for item in intervals]
        size = len(intervals)
        self.count = np.zeros(size, np.int64)
        self.mean = np.zeros((size, n))
        self.m2 = np.zeros((size, n))
        self.diff_sums: dict[int, np.ndarray] = {}
        self.diff_counts: dict[int, int] = {}
        self._last: dict[int, tuple[int, np.ndarray]] = {}  # piece -> (its last row, residual)

    def add(self, start: int, residual: np.ndarray) -> None:
        """Residual rows (k, n), the first of them row ``start`` of the log."""
        stop = start + residual.shape[0]
        first = max(int(np.searchsorted(self.starts, start, side="right")) - 1, 0)
        for p in range(first, len(self.pieces)):
            index, lo, hi = self.pieces[p]
            if lo >= stop:
                break
            lo, hi = max(lo, start), min(hi, stop)
            if hi <= lo:
                continue
            part = residual[lo - start : hi - start]
            self._moments(index, part)
            previous = self._last.get(p)
            joined = (
                part
                if previous is None or previous[0] != lo - 1
                else np.vstack([previous[1], part])
            )
            if joined.shape[0] >= 2:
                diffs = np.diff(joined, axis=0)
                o = self.orientation[index]
                self.diff_sums[o] = self.diff_sums.get(o, np.zeros(part.shape[1])) + np.sum(
                    diffs**2, axis=0
                )
                self.diff_counts[o] = self.diff_counts.get(o, 0) + diffs.shape[0]
            self._last[p] = (hi - 1, part[-1].copy())

    def _moments(self, index: int, part: np.ndarray) -> None:
        k = part.shape[0]
        mean = part.mean(axis=0)
        m2 = part.var(axis=0) * k
        n = self.count[index]
        if n == 0:
            self.count[index], self.mean[index], self.m2[index] = k, mean, m2
            return
        total = n + k
        delta = mean - self.mean[index]
        self.m2[index] += m2 + delta**2 * (n * k / total)
        self.mean[index] += delta * (k / total)
        self.count[index] = total

    def pooled_variances(self) -> np.ndarray | None:
        """The residual variances pooled over the intervals of at least 10 rows (their
        sums of squared deviations over their degrees of freedom), or None."""
        used = self.count >= 10
        dof = int(np.sum(self.count[used] - 1))
        if dof == 0:
            return None
        return np.sum(self.m2[used], axis=0) / dof


def calibrated_values(array: ArrayConfig, raw: np.ndarray, sensor_type: str) -> np.ndarray:
    """The calibrated sensors of one type in sensor-id order, (N, n) SI, from raw triads
    (N, m, 3)."""
    return array.select(array.calibrate_triads(raw, sensor_type), sensor_type)


def _parity_residuals(
    array: ArrayConfig, raw: np.ndarray, sensor_type: str, values: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``(I - H H^+)`` (n, n) and the parity residuals (N, n) of the calibrated sensors of
    one type (``values``, :func:`calibrated_values` of ``raw`` if not given): motion and
    the array's common offsets cancel in them."""
    if values is None:
        values = calibrated_values(array, raw, sensor_type)
    H = array.measurement_matrix(sensor_type)
    projector = residual_projector(H)
    return projector, values @ projector.T


def _scatter_triads(
    array: ArrayConfig, sensor_type: str, per_sensor: np.ndarray, out: list[dict[str, np.ndarray]]
) -> None:
    """Store per-sensor values (n,) as each complete IMU triad's (3,) in ``out[imu][type]``."""
    imu_idx, axis_idx = array.sensor_index(sensor_type)
    for k in range(array.n_imus):
        mine = imu_idx == k
        if np.count_nonzero(mine) == 3:
            triad = np.empty(3)
            triad[axis_idx[mine]] = per_sensor[mine]
            out[k][sensor_type] = triad


def expected_normal_range(count: int) -> float:
    """E[max - min] of ``count`` independent standard normal variables.

    ``d_n = integral of (1 - Phi(x)^n - (1 - Phi(x))^n) dx`` (Tippett, *Biometrika* 17,
    1925); 0 for n < 2, 1.128 for n = 2, 3.735 for n = 20.
    """
    if count < 2:
        return 0.0
    from imufdi_cli.maths.quantiles import norm

    grid = np.linspace(-10.0, 10.0, 20001)
    cdf = norm.cdf(grid)
    inside = 1.0 - cdf**count - (1.0 - cdf) ** count
    return float(np.sum(inside) * (grid[1] - grid[0]))


#: An orientation enters the noise spread with at least this many successive differences.
SPREAD_MIN_DIFFERENCES = 50


def noise_spread(
    array: ArrayConfig,
    accel: np.ndarray,
    gyro: np.ndarray | None,
    t_s: np.ndarray,
    static: np.ndarray,
    intervals: list[StaticInterval],
    *,
    values: Mapping[str, np.ndarray] | None = None,
) -> tuple[list[dict[str, np.ndarray]], dict[str, np.ndarray]]:
    """Each sensor's healthy white-noise variance spread over the static orientations.

    For every sensor type with a parity space (>= 4 sensors) and every orientation o (the
    static intervals grouped by :func:`group_orientations`), the mean square of the
    successive differences of the parity residuals ``r = (I - H H^+) m`` inside its static
    intervals gives ``v_o`` (n,); per-sensor difference variances solve
    ``((I - S) o (I - S)) s_o = v_o`` (as :func:`static_noise` does for the pooled
    variances; successive differences remove each interval's mean and slow drift, as
    noise-glr's own differences do). The spread of sensor j is::

        ln kappa_j = max(0, max_o ln s_jo - min_o ln s_jo - d_O se)

    with ``se = sqrt(2 / nu)`` the standard error of ``ln s_jo`` (``nu = 2 N^2 / (3 N - 1)``
    equivalent degrees of freedom of the mean square of N differences of white noise,
    lag-1 correlation -1/2; root-mean-square over the orientations) and ``d_O`` the
    expected range of O standard normals (:func:`expected_normal_range`): the range of O
    estimates of one constant variance is about ``d_O se`` in the log, so a sensor whose
    noise does not change with the orientation gets kappa ~ 1, and one whose variance
    changes by a factor F gets about F (slightly less: the correction assumes no change).
    The per-sensor solution's sampling error is taken as that of ``v_o`` (the operator
    is close to diagonal for 24 sensors and 3 unknowns); coloured noise has fewer
    degrees of freedom, which leaves kappa slightly high (the conservative side for a
    test whose null hypothesis is ``sigma^2 <= kappa sigma_cal^2``).

    Parameters
    ----------
    array : ArrayConfig
        Geometry with the chip calibration to apply.
    accel, gyro : ndarray, shape (N, m, 3)
        Raw samples (SI).
    t_s : ndarray, shape (N,)
    static : ndarray, shape (N,), bool
    intervals : list of StaticInterval
        With their ``orientation`` numbers set.
    values : mapping, optional
        Per sensor type, the calibrated values (N, n), as for :func:`static_noise`.

    Returns
    -------
    spread : list of dict
        Per IMU, per sensor type, kappa (3,) (>= 1, dimensionless).
    per_orientation : dict
        Per sensor type, ``s_o`` (O, n): the difference variances per orientation (SI^2),
        sensor-id order.
    """
    out: list[dict[str, np.ndarray]] = [{} for _ in range(array.n_imus)]
    tables: dict[str, np.ndarray] = {}
    pieces = interval_pieces(intervals, t_s, static)
    for sensor_type, raw in (("accel", accel), ("gyro", gyro)):
        if raw is None or array.n_sensors(sensor_type) < 4:
            continue
        given = None if values is None else values.get(sensor_type)
        projector, residual = _parity_residuals(array, raw, sensor_type, given)
        acc = IntervalResiduals(projector.shape[0], pieces, intervals)
        acc.add(0, residual)
        store_spread(array, sensor_type, acc, projector, out, tables)
    return out, tables


def store_spread(
    array: ArrayConfig,
    sensor_type: str,
    acc: IntervalResiduals,
    projector: np.ndarray,
    out: list[dict[str, np.ndarray]],
    tables: dict[str, np.ndarray],
) -> None:
    """:func:`noise_spread`'s kappa of one type from its per-orientation sums of squared
    successive differences, into ``out[imu][type]`` (and its table into ``tables``)."""
    n = projector.shape[0]
    sums, counts = acc.diff_sums, acc.diff_counts
    used = sorted(o for o in counts if counts[o] >= SPREAD_MIN_DIFFERENCES)
    if len(used) < 2:
        return
    weights = projector**2
    variances = []
    for o in used:
        s_o, *_ = np.linalg.lstsq(weights, sums[o] / counts[o], rcond=None)
        if not np.all(s_o > 0):  # as static_noise: fall back to the common level
            s_o = np.full(n, float(np.sum(sums[o] / counts[o])) / (n - 3))
        variances.append(s_o)
    table = np.stack(variances)  # (O, n)
    tables[sensor_type] = table
    count = np.array([counts[o] for o in used], dtype=float)
    dof = 2.0 * count**2 / (3.0 * count - 1.0)
    se = float(np.sqrt(np.mean(2.0 / dof)))
    logs = np.log(table)
    excess = logs.max(axis=0) - logs.min(axis=0) - expected_normal_range(len(used)) * se
    _scatter_triads(array, sensor_type, np.exp(np.maximum(excess, 0.0)), out)
