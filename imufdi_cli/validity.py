"""Sample validity: chip calibration, clipping and impossible values, before the tests.

Real arrays saturate (a MEMS gyro at +-2000 deg/s in hand motion) and damaged logs carry
NaN or absurd numbers (1e308 in a gyro). Neither is a sensor fault a parity test should
alarm on, and neither may crash a detector. :class:`Conditioner` sits between the reader
and the detectors of ``imufdi detect``:

1. **Chip calibration.** The messages of a log carry the values described by its
   ``imufdi.array`` record (calibrated with that record's per-IMU ``M, b`` when it has them).
   With ``detect --array FILE`` the calibration of FILE replaces it: each triad is mapped
   back to the raw chip output ``raw = M_log^-1 y + b_log`` and forward with FILE's
   ``M (raw - b)``.
2. **Flags**, on the raw chip values of each sensor (one mask for both mechanisms):

   - *invalid*: not finite, beyond the array's ``range`` by more than
     :data:`OUT_OF_RANGE_FACTOR` (a chip cannot output it), or beyond the absurd limit of
     its type in SI (:data:`ABSURD`, used whether a range is known or not);
   - *clipped*: within :data:`CLIP_FRACTION` of the ``range`` (full scale) or beyond it.
3. **Exclusion by consensus.** A flagged sensor sample is replaced by the least-squares
   consensus of the valid sensors of its type, ``h_j^T x_hat + beta_j`` with
   ``x_hat = H_v^+ (y_v - beta_v)`` and ``beta`` each sensor's mean offset from the
   consensus in the calibration window. It then carries no parity residual: the tests see
   only the valid sensors (the statistic of the n-1 others against the n-sensor threshold,
   slightly conservative). For accelerometers of IMUs at different positions H is the
   rigid-body design ``[H | lever-arm columns]`` (:mod:`imufdi_cli.maths.rigid`), so
   the replacement includes the lever-arm terms. When the valid sensors do not span the
   model (every gyro of an axis clipped at once), the whole sample of that type is *held*:
   every sensor gets the last consensus, so nothing alarms on a sample that cannot be
   tested.

4. **Missing IMUs.** A sample where some IMUs have no message (a topic that stopped or
   slowed while the others went on; the reader's ``missing`` mask, values NaN) is
   treated like a flagged one: the missing sensors are replaced by the consensus of the
   others, so every detector goes on testing the remaining IMUs with the reduced
   redundancy (the n-1 residuals against the n-sensor threshold: no extra alarms), and a
   fault on the remaining IMUs is still seen. These rows are *tested*, so they are
   counted apart (``missing`` rows, ``missing_ns`` runs), not as invalid.

Every row with a flagged sensor is counted (``clipped``, ``invalid``, ``held``,
``missing`` rows) and listed in time intervals (``clipped_ns``, ``invalid_ns``,
``held_ns``, ``missing_ns``) in the detector's ``imufdi.detect.<name>`` metadata;
``imufdi report`` leaves the clipped, invalid and held rows out of every metric (the
rows with a missing IMU were tested on the others: they are scored) and shows the
counts.

Why replacement rather than a mask passed to detectors: every detector (parity, PCA,
bank, MVMD, CNN) works unchanged, streaming state (moving means, filters) sees a
continuous and consistent signal, and no detector internals change.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any
from weakref import WeakKeyDictionary

import numpy as np

from imufdi_cli.array import SENSOR_TYPES, ArrayConfig
from imufdi_cli.log import ImuBlock

#: A raw value at or beyond this fraction of the full scale is clipped.
CLIP_FRACTION = 0.995
#: A raw value beyond this multiple of the full scale cannot come from the chip: invalid.
OUT_OF_RANGE_FACTOR = 1.05
#: Magnitudes no sensor of the type measures (SI): invalid whatever the range. Gyro
#: 1000 rad/s (57,000 deg/s), accel 10,000 m/s^2 (1,000 g), magnetometer 0.01 T.
ABSURD: Mapping[str, float] = {"gyro": 1e3, "accel": 1e4, "mag": 1e-2}


def flag_values(
    raw: np.ndarray, sensor_type: str, full_scale: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """Clipped and invalid flags of raw chip values.

    Parameters
    ----------
    raw : ndarray, shape (..., 3)
        Raw chip values, SI.
    sensor_type : str
    full_scale : float or None
        Measurement range of the type, SI (None: only non-finite and absurd values flag).

    Returns
    -------
    clipped, invalid : ndarray of bool, shape of ``raw``
        Disjoint: an invalid value is not also clipped.
    """
    with np.errstate(invalid="ignore", over="ignore"):
        magnitude = np.abs(np.asarray(raw, dtype=float))
        invalid = ~np.isfinite(magnitude) | (magnitude > ABSURD[sensor_type])
        if full_scale is None:
            return np.zeros(magnitude.shape, dtype=bool), invalid
        invalid |= magnitude > OUT_OF_RANGE_FACTOR * full_scale
        clipped = ~invalid & (magnitude >= CLIP_FRACTION * full_scale)
    return clipped, invalid


class Runs:
    """Runs of flagged rows as [first, last] timestamps (ns), merged across blocks."""

    def __init__(self) -> None:
        self.intervals: list[list[int]] = []
        self._open = False

    def add(self, t_ns: np.ndarray, flagged: np.ndarray) -> None:
        idx = np.flatnonzero(flagged)
        if idx.size:
            breaks = np.flatnonzero(np.diff(idx) > 1)
            starts = np.concatenate([[idx[0]], idx[breaks + 1]])
            ends = np.concatenate([idx[breaks], [idx[-1]]])
            for a, b in zip(starts, ends):
                if self._open and a == 0 and self.intervals:
                    self.intervals[-1][1] = int(t_ns[b])
                else:
                    self.intervals.append([int(t_ns[a]), int(t_ns[b])])
        self._open = bool(flagged[-1]) if len(flagged) else self._open


@dataclass
class TypeValidity:
    """Counts for one sensor type over the tested rows."""

    rows: int = 0
    clipped_rows: int = 0  # rows with at least one clipped sensor
    invalid_rows: int = 0  # rows with at least one invalid sensor
    held_rows: int = 0  # rows without 3 valid dimensions: every sensor held
    missing_rows: int = 0  # rows where some IMU had no sample (tested on the others)
    clipped_values: int = 0
    invalid_values: int = 0
    clipped_runs: Runs = field(default_factory=Runs)
    invalid_runs: Runs = field(default_factory=Runs)
    held_runs: Runs = field(default_factory=Runs)
    missing_runs: Runs = field(default_factory=Runs)

    def to_dict(self) -> dict[str, Any]:
        return {
            "rows": self.rows,
            "clipped": self.clipped_rows,
            "invalid": self.invalid_rows,
            "held": self.held_rows,
            "missing": self.missing_rows,
            "clipped_values": self.clipped_values,
            "invalid_values": self.invalid_values,
            "clipped_ns": self.clipped_runs.intervals,
            "invalid_ns": self.invalid_runs.intervals,
            "held_ns": self.held_runs.intervals,
            "missing_ns": self.missing_runs.intervals,
        }


class Conditioner:
    """Calibration override, flags and exclusion by consensus, block by block.

    Parameters
    ----------
    log_array : ArrayConfig
        What the log's messages are (its ``imufdi.array`` record).
    array : ArrayConfig, optional
        The array to test with (``detect --array``); default ``log_array``. Its calibration
        replaces the log's; its ``range`` (else the log's) sets the clipping limits.
    """

    def __init__(self, log_array: ArrayConfig, array: ArrayConfig | None = None) -> None:
        self.log_array = log_array
        self.array = array if array is not None else log_array
        self.ranges = {**dict(log_array.range), **dict(self.array.range)}
        self.recalibrate = self.array is not log_array and any(
            not _same(a.calibration_of(s), b.calibration_of(s))
            for a, b in zip(log_array.imus, self.array.imus)
            for s in SENSOR_TYPES
        )
        #: per sensor type: whether the log's values are the raw chip values (no calibration)
        self._raw = _uncalibrated(log_array)
        self.offsets: dict[str, np.ndarray] = {}
        self.last_rate: dict[str, np.ndarray] = {}
        self._designs: dict[str, np.ndarray] = {}
        self.counts: dict[str, TypeValidity] = {
            s: TypeValidity() for s in self.array.sensor_types()
        }

    # --- 1 + 2: calibration and flags --------------------------------------------------

    def prepare(self, block: ImuBlock) -> tuple[ImuBlock, dict[str, tuple[np.ndarray, np.ndarray]]]:
        """Apply the calibration override and flag values.

        Returns the block to test (triads calibrated as ``array`` says) and, per sensor
        type, (clipped, invalid) masks of shape (N, m, 3).
        """
        flags: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        fields: dict[str, np.ndarray | None] = {}
        for s in SENSOR_TYPES:
            triads = block.get(s)
            fields[s] = triads
            if triads is None:
                continue
            # the log's values are the raw chip values when it records no chip calibration
            raw = triads if self._raw[s] else self.log_array.calibrate_triads(triads, s, undo=True)
            if _none_flagged(raw, s, self.ranges.get(s)):  # two reductions, no masks to build
                quiet = np.zeros(raw.shape, dtype=bool)
                flags[s] = (quiet, quiet)
            else:
                flags[s] = flag_values(raw, s, self.ranges.get(s))
            if self.recalibrate:
                fields[s] = self.array.calibrate_triads(raw, s)
        return ImuBlock(t_ns=block.t_ns, missing=block.missing, **fields), flags

    # --- 3: exclusion -----------------------------------------------------------------

    def fit(self, block: ImuBlock, flags: Mapping[str, tuple[np.ndarray, np.ndarray]]) -> None:
        """Each sensor's mean offset from the LS consensus over unflagged calibration rows."""
        for s in self.array.sensor_types():
            triads = block.get(s)
            if triads is None or s not in flags:
                continue
            y = self.array.select(triads, s)
            bad = self._bad(flags, s)
            good = ~bad.any(axis=1)
            h = self._design(s)
            offsets = np.zeros(h.shape[0])
            if good.any() and _full_rank(self.array, s):
                yg = y[good]
                residual = yg - yg @ _designs(self.array)[s][1].T @ h.T
                offsets = residual.mean(axis=0)
            self.offsets[s] = offsets

    def sanitize(
        self,
        block: ImuBlock,
        flags: Mapping[str, tuple[np.ndarray, np.ndarray]],
        *,
        count: bool = True,
    ) -> ImuBlock:
        """Replace flagged sensor samples by the consensus (or hold the row); count them."""
        fields: dict[str, np.ndarray | None] = {s: block.get(s) for s in SENSOR_TYPES}
        for s in self.array.sensor_types():
            triads = block.get(s)
            if triads is None or s not in flags:
                continue
            clipped, invalid = (self.array.select(f, s) for f in flags[s])
            bad = clipped | invalid
            absent = self._absent(block, s)  # (N, n_s): a missing IMU's sensors
            held = np.zeros(len(block), dtype=bool)
            rows = np.flatnonzero(bad.any(axis=1))
            if rows.size or np.any(flags[s][1]):
                triads = triads.copy()
                # values of unused axes never reach a test, but must not carry NaN/inf
                triads[flags[s][1] | ~np.isfinite(triads)] = 0.0
                y = self.array.select(triads, s)
                held = self._replace(s, y, bad, rows)
                imu_idx, axis_idx = self.array.sensor_index(s)
                triads[:, imu_idx, axis_idx] = y
                fields[s] = triads
            self._track_consensus(s, fields[s], bad)
            if count:
                c = self.counts[s]
                invalid = invalid & ~absent  # a missing sample is not an invalid one
                missing_rows = absent.any(axis=1)
                c.rows += len(block)
                c.clipped_rows += int(np.count_nonzero(clipped.any(axis=1)))
                c.invalid_rows += int(np.count_nonzero(invalid.any(axis=1)))
                c.held_rows += int(np.count_nonzero(held))
                c.missing_rows += int(np.count_nonzero(missing_rows))
                c.clipped_values += int(np.count_nonzero(clipped))
                c.invalid_values += int(np.count_nonzero(invalid))
                c.clipped_runs.add(block.t_ns, np.asarray(clipped.any(axis=1)))
                c.invalid_runs.add(block.t_ns, np.asarray(invalid.any(axis=1)))
                c.held_runs.add(block.t_ns, np.asarray(held))
                c.missing_runs.add(block.t_ns, np.asarray(missing_rows))
        return ImuBlock(t_ns=block.t_ns, missing=block.missing, **fields)

    def _absent(self, block: ImuBlock, s: str) -> np.ndarray:
        """(N, n_s) bool: the sensors of type ``s`` whose IMU has no sample at the row."""
        imu_idx, _ = self.array.sensor_index(s)
        if block.missing is None or s == "mag":  # a missing magnetometer reads as invalid
            return np.zeros((len(block), imu_idx.size), dtype=bool)
        return block.missing[:, imu_idx]

    def _design(self, s: str) -> np.ndarray:
        """Consensus model of a type: H, or for accelerometers of IMUs at different
        positions the rigid-body design [H | lever-arm columns] (maths/rigid.py), so a
        replaced sample carries no lever-arm residual either."""
        if s not in self._designs:
            self._designs[s] = _designs(self.array)[s][0]
        return self._designs[s]

    def _bad(self, flags: Mapping[str, tuple[np.ndarray, np.ndarray]], s: str) -> np.ndarray:
        clipped, invalid = flags[s]
        return self.array.select(clipped | invalid, s)

    def _replace(self, s: str, y: np.ndarray, bad: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """In place on ``y`` (N, n_s): flagged entries of ``rows`` -> consensus. Returns
        the rows held (no 3-dimensional consensus)."""
        h = self._design(s)
        q = h.shape[1]
        beta = self.offsets.get(s, np.zeros(h.shape[0]))
        held = np.zeros(y.shape[0], dtype=bool)
        if rows.size == 0:
            return held
        patterns, inverse = np.unique(bad[rows], axis=0, return_inverse=True)
        inverse = np.asarray(inverse).reshape(-1)
        for p, pattern in enumerate(patterns):
            sel = rows[inverse == p]
            valid = ~pattern
            hv = h[valid]
            if hv.shape[0] >= q and np.linalg.matrix_rank(hv) == q:
                x_hat = (y[np.ix_(sel, valid)] - beta[valid]) @ np.linalg.pinv(hv).T
                y[np.ix_(sel, pattern)] = x_hat @ h[pattern].T + beta[pattern]
            else:
                held[sel] = True
        if held.any():
            # hold: every sensor gets the consensus of the last testable row before it
            x_prev = self.last_rate.get(s, np.zeros(q))
            pinv = np.linalg.pinv(h)
            good_rows = ~bad.any(axis=1)
            for i in np.flatnonzero(held | good_rows):
                if held[i]:
                    y[i] = h @ x_prev + beta
                else:
                    x_prev = pinv @ (y[i] - beta)
        return held

    def _track_consensus(self, s: str, triads: np.ndarray | None, bad: np.ndarray) -> None:
        if triads is None:
            return
        good = np.flatnonzero(~bad.any(axis=1))
        if good.size:
            h = self._design(s)
            beta = self.offsets.get(s, np.zeros(h.shape[0]))
            y = self.array.select(triads[good[-1:]], s)[0]
            self.last_rate[s] = _designs(self.array)[s][1] @ (y - beta)

    def metadata(self) -> dict[str, Any]:
        """JSON-ready record: limits and counts per sensor type."""
        return {
            "clip_fraction": CLIP_FRACTION,
            "out_of_range_factor": OUT_OF_RANGE_FACTOR,
            "absurd": dict(ABSURD),
            "range": dict(self.ranges),
            "types": {s: c.to_dict() for s, c in self.counts.items()},
        }


#: per array (the same object for every run of a campaign base): its consensus designs and
#: their pseudo-inverses, and which types carry no chip calibration
_DESIGNS: WeakKeyDictionary[ArrayConfig, _LazyDesigns] = WeakKeyDictionary()
_UNCALIBRATED: WeakKeyDictionary[ArrayConfig, dict[str, bool]] = WeakKeyDictionary()


def _designs(array: ArrayConfig) -> _LazyDesigns:
    """Per sensor type of ``array`` asked for so far: the consensus model H (for
    accelerometers of IMUs at different positions the rigid-body design, maths/rigid.py),
    its pseudo-inverse and whether it has full column rank, computed
    once per array."""
    found = _DESIGNS.get(array)
    if found is None:
        found = _DESIGNS[array] = _LazyDesigns(array)
    return found


class _LazyDesigns(dict[str, tuple[np.ndarray, np.ndarray, bool]]):
    """The designs of one array, each made when first asked for."""

    def __init__(self, array: ArrayConfig) -> None:
        super().__init__()
        self.array = array

    def __missing__(self, s: str) -> tuple[np.ndarray, np.ndarray, bool]:
        from imufdi_cli.maths.rigid import accel_design

        h = accel_design(self.array) if s == "accel" else self.array.measurement_matrix(s)
        self[s] = (h, np.linalg.pinv(h), bool(np.linalg.matrix_rank(h) == h.shape[1]))
        return self[s]


def _full_rank(array: ArrayConfig, s: str) -> bool:
    """Whether the consensus model of type ``s`` has full column rank."""
    return _designs(array)[s][2]


def _uncalibrated(array: ArrayConfig) -> dict[str, bool]:
    """Per sensor type: whether no IMU of ``array`` has a chip calibration other than the
    identity (its values are then the raw chip values)."""
    found = _UNCALIBRATED.get(array)
    if found is None:
        found = {
            s: all(
                imu.calibration.get(s) is None or imu.calibration_of(s).is_identity
                for imu in array.imus
            )
            for s in SENSOR_TYPES
        }
        _UNCALIBRATED[array] = found
    return found


def _none_flagged(raw: np.ndarray, sensor_type: str, full_scale: float | None) -> bool:
    """True when :func:`flag_values` would flag no value of ``raw``: every value finite and
    below both the clipping level and the absurd magnitude (two reductions instead of the
    flags' passes; NaN fails the comparisons, so any NaN or inf says False)."""
    if raw.size == 0:
        return True
    limit = ABSURD[sensor_type]
    low, high = float(np.min(raw)), float(np.max(raw))
    within = -limit <= low and high <= limit  # NaN: False
    if full_scale is not None:
        clip = CLIP_FRACTION * full_scale
        within = within and -clip < low and high < clip
    return within and np.isfinite(low) and np.isfinite(high)


class ValidityCounter:
    """Rows with clipped or invalid raw values per sensor type (``ingest`` records them
    in ``imufdi.ingest``; ``info`` shows them)."""

    def __init__(self, array: ArrayConfig) -> None:
        self.array = array
        self.counts: dict[str, dict[str, int]] = {}

    def count(self, block: ImuBlock) -> ImuBlock:
        for s in SENSOR_TYPES:
            data = block.get(s)
            if data is None:
                continue
            full_scale = self.array.range.get(s)
            entry = self.counts.setdefault(s, {"rows": 0, "clipped": 0, "invalid": 0})
            entry["rows"] += len(block)
            if _none_flagged(data, s, full_scale):
                continue
            clipped, invalid = flag_values(data, s, full_scale)
            entry["clipped"] += int(np.count_nonzero(clipped.any(axis=(1, 2))))
            entry["invalid"] += int(np.count_nonzero(invalid.any(axis=(1, 2))))
        return block


def apply_calibration(block: ImuBlock, array: ArrayConfig) -> ImuBlock:
    """The block with each IMU's chip calibration applied, ``M (raw - b)`` (new arrays)."""
    fields: dict[str, np.ndarray | None] = {}
    for s in SENSOR_TYPES:
        triads = block.get(s)
        fields[s] = None if triads is None else array.calibrate_triads(triads, s)
    return ImuBlock(t_ns=block.t_ns, **fields)


def _same(a: Any, b: Any) -> bool:
    return bool(np.array_equal(a.matrix, b.matrix) and np.array_equal(a.bias, b.bias))


#: The calibration window must keep at least this share of its samples with every IMU.
MIN_COMPLETE_CALIBRATION = 0.5


def complete_rows(
    block: ImuBlock,
    flags: Mapping[str, tuple[np.ndarray, np.ndarray]],
    topics: Sequence[str],
    window: tuple[float, float | None],
) -> tuple[ImuBlock, dict[str, tuple[np.ndarray, np.ndarray]], str]:
    """The samples of a calibration window (``block``, its ``flags``) where every IMU has
    one, and a warning saying how many were left out. Calibrating on a missing IMU's
    stand-in (the consensus of the others, noise-free) would teach the detectors a noise
    of zero for it, and they would alarm once it is back.

    Raises
    ------
    CalibrationError
        Fewer than :data:`MIN_COMPLETE_CALIBRATION` of the window's samples complete
        (``window``: its start and end, s, for the message), exit 3.
    """
    from imufdi_cli.errors import CalibrationError

    assert block.missing is not None
    complete = np.asarray(~block.missing.any(axis=1))
    absent = [topics[int(k)] for k in np.flatnonzero(block.missing.any(axis=0)) if k < len(topics)]
    shown = ", ".join(absent[:3]) + (f" and {len(absent) - 3} more" if len(absent) > 3 else "")
    n_complete, n = int(np.count_nonzero(complete)), len(block)
    if n_complete < MIN_COMPLETE_CALIBRATION * n:
        end = "" if window[1] is None else f"{window[1]:g}s"
        raise CalibrationError(
            f"calibration window {window[0]:g}s:{end} has an IMU missing in {n - n_complete} of its {n}"
            f" samples ({shown}); choose a window where every IMU publishes with"
            " --calibrate START:END"
        )
    note = (
        f"calibration window: {n - n_complete} of its {n} samples have an IMU missing"
        f" ({shown}); the detectors are calibrated on the {n_complete} complete ones"
    )
    kept = {s: (c[complete], i[complete]) for s, (c, i) in flags.items()}
    return block.mask(complete), kept, note


# --- report side -----------------------------------------------------------------------


@dataclass
class Selection:
    """Which status rows of one detector and sensor type a report counts."""

    keep: np.ndarray  # (N,) bool
    clipped: int = 0  # rows with a clipped sensor, in the window
    invalid: int = 0  # rows with an invalid sensor, in the window
    excluded: int = 0  # rows not scored for validity (inside the time window)
    missing: int = 0  # rows tested with some IMU missing (scored), in the window


def select_rows(
    t_ns: np.ndarray,
    record: Mapping[str, Any] | None,
    sensor_type: str,
    window: tuple[float, float | None] | None = None,
    *,
    origin_ns: int | None = None,
) -> Selection:
    """Rows to score: inside ``window`` (seconds from the log's first sample, as recorded
    by ``detect``; else from the first status row) and outside the validity exclusions.

    Parameters
    ----------
    t_ns : ndarray, shape (N,)
        Status row times.
    record : dict or None
        The detector's ``imufdi.detect.<name>`` record (decoded JSON).
    origin_ns : int, optional
        Time origin when the record has no ``t0_ns`` (a stream's first status row).
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    keep = np.ones(t_ns.shape, dtype=bool)
    record = record or {}
    if window is not None:
        t0 = record.get("t0_ns")
        if isinstance(t0, int):
            origin = t0
        elif origin_ns is not None:
            origin = int(origin_ns)
        else:
            origin = int(t_ns[0]) if t_ns.size else 0
        from imufdi_cli.units import window_from_log_start

        start_s, end_s = window_from_log_start(window, origin)
        rel = (t_ns - origin) / 1e9
        keep &= rel >= start_s
        if end_s is not None:
            keep &= rel < end_s
    validity = record.get("validity")
    counts = validity.get("types", {}).get(sensor_type) if isinstance(validity, Mapping) else None
    if not isinstance(counts, Mapping):
        return Selection(keep=keep)
    clipped = _in_runs(t_ns, counts.get("clipped_ns", []))
    invalid = _in_runs(t_ns, counts.get("invalid_ns", []))
    held = _in_runs(t_ns, counts.get("held_ns", []))  # not tested: no consensus
    missing = _in_runs(t_ns, counts.get("missing_ns", [])) & ~held
    flagged = clipped | invalid | held
    return Selection(
        keep=keep & ~flagged,
        clipped=int(np.count_nonzero(clipped & keep)),
        invalid=int(np.count_nonzero(invalid & keep)),
        excluded=int(np.count_nonzero(flagged & keep)),
        missing=int(np.count_nonzero(missing & keep & ~flagged)),
    )


def _in_runs(t_ns: np.ndarray, runs: Any) -> np.ndarray:
    """Rows of ``t_ns`` (sorted) inside any [first, last] interval of ``runs``."""
    try:
        intervals = np.asarray(runs, dtype=np.int64).reshape(-1, 2)
    except (TypeError, ValueError):
        return np.zeros(t_ns.shape, dtype=bool)
    if intervals.size == 0 or t_ns.size == 0:
        return np.zeros(t_ns.shape, dtype=bool)
    lo = np.searchsorted(t_ns, intervals[:, 0], side="left")
    hi = np.searchsorted(t_ns, intervals[:, 1], side="right")
    delta = np.zeros(t_ns.size + 1, dtype=np.int64)
    np.add.at(delta, lo, 1)
    np.add.at(delta, hi, -1)
    return np.cumsum(delta[:-1]) > 0
