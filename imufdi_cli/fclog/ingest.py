"""Flight-controller log -> IMU array MCAP (``imufdi ingest log.ulg`` / ``log.bin``).

Two passes over the log (a log on stdin is spooled to a temporary file first):

1. **Scan**: every IMU stream with its sample count and time span, the GPS time (UTC),
   the logging parameters, the firmware and board, corruption counts.
2. **Convert**: the chosen streams decoded chunk by chunk, aligned into array samples
   (:class:`~imufdi_cli.fclog.align.NearestAligner`: no resampling, each value is one the
   log holds, stamped when its last value exists) and written as one ``sensor_msgs/Imu``
   channel per IMU with the ``imufdi.array`` and ``imufdi.ingest`` records, as every
   other source is.

Which data (``imu_data``): ``auto`` takes, of the kinds the log holds, the one with the
most IMUs, then the most sensor types, then the highest per-IMU rate; or name one
(PX4: ``sensor``, ``vehicle_imu``; ArduPilot: ``imu``, ``raw``).

Geometry: a flight controller's IMUs are taken as co-aligned in the frame the log gives
(PX4 ``sensor_*``: the board frame, the drivers having applied each chip's mounting
rotation; ``vehicle_imu`` and ArduPilot: the vehicle body frame), at the positions the log
states (ArduPilot ``INS_POS1_X``.. when set; else all at the origin). ``--array FILE``
replaces that (an IMU mounted differently, known lever arms).
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, BinaryIO, Final

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.errors import FlightLogError, ImufdiError, UsageError
from imufdi_cli.fclog.align import NearestAligner
from imufdi_cli.fclog.streams import (
    MIN_TEST_RATE_HZ,
    SOURCE_HELP,
    FlightLogReader,
    LogScan,
    Stream,
    iso_utc,
)
from imufdi_cli.log import ImuBlock

ULOG_MAGIC: Final[bytes] = b"ULog\x01\x12\x35"
DATAFLASH_MAGIC: Final[bytes] = b"\xa3\x95\x80"
FORMAT_NAMES: Final[dict[str, str]] = {
    "px4-ulog": "PX4 ULog",
    "ardupilot-dataflash": "ArduPilot DataFlash log",
}
#: the kinds of IMU data of each format, in the order ``auto`` breaks ties
SOURCES: Final[dict[str, tuple[str, ...]]] = {
    "px4-ulog": ("sensor", "vehicle_imu"),
    "ardupilot-dataflash": ("raw", "imu"),
}
IMU_DATA_CHOICES: Final[tuple[str, ...]] = ("auto", "sensor", "vehicle_imu", "imu", "raw")
#: bytes enough to recognise a format
SNIFF_BYTES: Final[int] = 8


def sniff_format(head: bytes) -> str | None:
    """``px4-ulog`` or ``ardupilot-dataflash`` from a file's first bytes, else None."""
    if head.startswith(ULOG_MAGIC):
        return "px4-ulog"
    if head.startswith(DATAFLASH_MAGIC):
        return "ardupilot-dataflash"
    return None


def open_flight_log(
    path: str | os.PathLike[str], fmt: str, *, chunk_size: int = 4 << 20
) -> FlightLogReader:
    """The reader of a log of format ``fmt`` (from :func:`sniff_format`)."""
    if fmt == "px4-ulog":
        from imufdi_cli.fclog.px4 import PX4Log

        return PX4Log(path, chunk_size=chunk_size)
    if fmt == "ardupilot-dataflash":
        from imufdi_cli.fclog.ardupilot import ArduPilotLog

        return ArduPilotLog(path, chunk_size=chunk_size)
    raise FlightLogError(f"unknown flight-log format {fmt!r}; valid: {', '.join(FORMAT_NAMES)}")


def logging_hint(fmt: str) -> str:
    """Which logging settings give every IMU at full rate, for a format."""
    if fmt == "px4-ulog":
        from imufdi_cli.fclog.px4 import LOGGING_HINT
    else:
        from imufdi_cli.fclog.ardupilot import LOGGING_HINT
    return LOGGING_HINT


@dataclass
class Imu:
    """One IMU of the array: its stream(s), gyro and/or accel."""

    gyro: Stream | None = None
    accel: Stream | None = None
    combined: Stream | None = None

    def streams(self) -> list[Stream]:
        return [s for s in (self.combined, self.gyro, self.accel) if s is not None]

    def rate_hz(self) -> float:
        rates = [s.rate_hz for s in self.streams()]
        return min(r for r in rates if r is not None) if all(r is not None for r in rates) else 0.0


@dataclass
class Selection:
    """The IMUs chosen from a log and how they are built."""

    source: str
    imus: list[Imu]
    sensors: tuple[str, ...]
    notes: list[str] = field(default_factory=list)

    def streams(self) -> list[Stream]:
        return [s for imu in self.imus for s in imu.streams()]

    @property
    def min_rate_hz(self) -> float:
        return min(imu.rate_hz() for imu in self.imus)


def _imus_of(source: str, streams: list[Stream]) -> Selection:
    """The IMUs a source gives: one per combined stream, or gyro and accel paired.

    A stream with under 1 % of the samples of the source's largest (at least 2) is left
    out with a note: a damaged instance number makes such a stream of a few samples."""
    most = max(s.count for s in streams)
    sparse = [s for s in streams if s.count < max(2, most // 100) or s.rate_hz is None]
    if sparse and len(sparse) < len(streams):
        selection = _imus_of(source, [s for s in streams if s not in sparse])
        selection.notes[:0] = [
            f"{s.name} has {s.count} samples, the other {source} streams up to {most}"
            " (a damaged instance number?): left out"
            for s in sparse
        ]
        return selection
    if all(len(s.sensors) == 2 for s in streams):
        imus = [Imu(combined=s) for s in sorted(streams, key=lambda s: s.instance)]
        return Selection(source, imus, ("gyro", "accel"))
    gyros = sorted((s for s in streams if s.sensors == ("gyro",)), key=lambda s: s.instance)
    accels = sorted((s for s in streams if s.sensors == ("accel",)), key=lambda s: s.instance)
    notes: list[str] = []
    paired: list[Imu] = []
    free = list(accels)
    for gyro in gyros:
        # the accelerometer of the same chip: same device id, else the same instance
        match = next(
            (a for a in free if gyro.device_id is not None and a.device_id == gyro.device_id), None
        )
        if match is None:
            match = next((a for a in free if a.instance == gyro.instance), None)
        if match is not None:
            free.remove(match)
        paired.append(Imu(gyro=gyro, accel=match))
    if paired and all(imu.accel is not None for imu in paired):
        for extra in free:
            notes.append(f"{extra.name} has no gyro of its own: left out")
        return Selection(source, paired, ("gyro", "accel"), notes)
    if gyros and len(gyros) >= len(accels):
        if accels:
            notes.append(
                "not every gyro has an accelerometer stream: the array has gyros only"
                f" ({', '.join(a.name for a in accels)} left out)"
            )
        return Selection(source, [Imu(gyro=g) for g in gyros], ("gyro",), notes)
    if gyros:
        notes.append(
            f"gyro streams {', '.join(g.name for g in gyros)} left out: fewer than the accelerometers"
        )
    return Selection(source, [Imu(accel=a) for a in accels], ("accel",), notes)


def select(scan: LogScan, imu_data: str = "auto") -> Selection:
    """The IMUs to ingest (see the module docstring for ``auto``).

    Raises
    ------
    UsageError
        ``imu_data`` names a kind of data this format does not have.
    FlightLogError
        The log holds none of the IMU data asked for.
    """
    valid = SOURCES[scan.format]
    name = FORMAT_NAMES[scan.format]
    if imu_data != "auto" and imu_data not in valid:
        raise UsageError(
            f"--imu-data {imu_data!r} is not a kind of {name} IMU data; valid: auto, {', '.join(valid)}"
        )
    present = scan.sources()
    if not present:
        found = ", ".join(f"{v['batches']} of {k}" for k, v in list(scan.batches.items())[:4])
        raise FlightLogError(
            f"this {name} holds no per-IMU data ({'/'.join(valid)})"
            + (
                f"; only the batch sampler's bursts ({found}), one sensor at a time"
                if found
                else ""
            )
            + f"; {logging_hint(scan.format)}"
        )
    if imu_data != "auto":
        if imu_data not in present:
            raise FlightLogError(
                f"this {name} holds no {imu_data} data; it holds: {', '.join(sorted(present))}"
            )
        return _imus_of(imu_data, present[imu_data])
    options = [_imus_of(s, present[s]) for s in valid if s in present]
    return max(options, key=lambda o: (len(o.imus), len(o.sensors), o.min_rate_hz))


def _positions(scan: LogScan, n_imus: int) -> np.ndarray | None:
    """IMU positions (n, 3) m from ArduPilot's INS_POS<k>_X/Y/Z when any is set."""
    params = scan.parameters
    rows = []
    for k in range(1, n_imus + 1):
        rows.append([float(params.get(f"INS_POS{k}_{a}", 0.0) or 0.0) for a in "XYZ"])
    positions = np.asarray(rows)
    return positions if positions.any() else None


@dataclass
class FlightLogIngest:
    """What :func:`ingest_flight_log` did (also the ``imufdi.ingest`` record).

    Attributes
    ----------
    record : dict
        The ``imufdi.ingest`` record, JSON-ready.
    warnings : list of str
        Worth a user's attention: a rate too low to test, data left out.
    """

    record: dict[str, Any]
    warnings: list[str] = field(default_factory=list)

    @property
    def n_imus(self) -> int:
        return int(self.record["n_imus"])

    def as_rows(self) -> list[tuple[str, Any]]:
        """(name, value) rows for ``imufdi ingest``'s table."""
        r = self.record
        align = r["alignment"]
        rows: list[tuple[str, Any]] = [
            ("format", FORMAT_NAMES[r["format"]]),
            ("system", _system_text(r["system"])),
            ("imu data", r["imu_data"]),
            ("imus", r["n_imus"]),
            ("sensors", ", ".join(r["sensors"])),
            ("rate per imu (Hz)", ", ".join(f"{x:.4g}" for x in r["imu_rates_hz"])),
            ("array samples", align["samples"]),
            ("grid times dropped", align["dropped"]),
            ("max skew (ms)", f"{align['max_skew_us'] / 1000:.3g}"),
            ("utc start", r["utc"]["start"] if r["utc"] else "none (no GPS time)"),
        ]
        for key in ("corrupt_bytes", "corrupt_messages", "dropouts"):
            if key in r["counts"]:
                rows.append((key.replace("_", " "), r["counts"][key]))
        return rows

    def to_dict(self) -> dict[str, Any]:
        r = self.record
        return {
            "format": r["format"],
            "imu_data": r["imu_data"],
            "n_imus": r["n_imus"],
            "sensors": r["sensors"],
            "samples": r["alignment"]["samples"],
            "imu_rates_hz": r["imu_rates_hz"],
            "testable": r["rate"]["testable"],
            "utc_start": r["utc"]["start"] if r["utc"] else None,
            "warnings": list(self.warnings),
        }


def _system_text(system: dict[str, str]) -> str:
    """Vehicle, hardware and firmware in a few words (the record has everything)."""
    keys = ("sys_name", "ver_hw", "version", "firmware", "board")
    return ", ".join(system[k] for k in keys if system.get(k)) or "not stated"


@contextmanager
def _as_file(source: str | os.PathLike[str] | BinaryIO, head: bytes = b"") -> Iterator[str]:
    """A path for the log: the path itself, or a temporary copy of a stream (stdin) with
    ``head`` (bytes already read from it) first."""
    if isinstance(source, (str, os.PathLike)) and os.fspath(source) != "-":
        yield os.fspath(source)
        return
    stream: BinaryIO = sys.stdin.buffer if not hasattr(source, "read") else source  # type: ignore[assignment]
    fd, path = tempfile.mkstemp(prefix="imufdi-fclog-", suffix=".log")
    try:
        with os.fdopen(fd, "wb") as spool:
            spool.write(head)
            shutil.copyfileobj(stream, spool, 1 << 20)
        yield path
    finally:
        os.unlink(path)


def ingest_flight_log(
    source: str | os.PathLike[str] | BinaryIO,
    output: str | os.PathLike[str] | BinaryIO,
    *,
    fmt: str | None = None,
    head: bytes = b"",
    imu_data: str = "auto",
    array: ArrayConfig | None = None,
    strict: bool = False,
    start_time_ns: int | None = None,
    compression: str = "zstd",
    chunk_size: int = 4 << 20,
    progress: Any = None,
) -> FlightLogIngest:
    """Convert a PX4 ULog or ArduPilot DataFlash log into an IMU array MCAP.

    Parameters
    ----------
    source : path, ``"-"`` or binary stream
        The log (a stream is spooled to a temporary file: the conversion reads it twice).
    output : path or binary stream
        The MCAP (renamed into place only on success).
    fmt : str, optional
        ``px4-ulog`` or ``ardupilot-dataflash`` (default: recognised from the content).
    head : bytes
        Bytes already read from a stream ``source`` (to recognise it), written first.
    imu_data : str
        ``auto`` or the kind of IMU data (:data:`IMU_DATA_CHOICES`).
    array : ArrayConfig, optional
        Geometry (and chip calibration, applied as for captures) instead of co-aligned IMUs
        at the logged positions; its IMU count must match.
    strict : bool
        Corrupt or truncated data is an error (exit 3) instead of being counted.
    start_time_ns : int, optional
        Wall-clock time of the first array sample (overrides the GPS time).
    progress : callable, optional
        ``progress(done, total)`` in bytes over both passes.

    Returns
    -------
    FlightLogIngest

    Raises
    ------
    FlightLogError
        Not a flight-controller log, no IMU data, too few samples, or (strict) corrupt.
    UsageError
        ``imu_data`` not valid for the format, ``array`` of another IMU count.
    """
    with _as_file(source, head) as path:
        if fmt is None:
            with open(path, "rb") as handle:
                fmt = sniff_format(handle.read(SNIFF_BYTES))
            if fmt is None:
                raise FlightLogError(f"{path}: neither a PX4 ULog nor an ArduPilot DataFlash log")
        size = float(os.path.getsize(path)) or 1.0

        def half(offset: float) -> Any:
            if progress is None:
                return None
            return lambda done, total=None: progress(offset + float(done) / 2, size)

        reader = open_flight_log(path, fmt, chunk_size=chunk_size)
        scan = reader.scan(progress=half(0.0))
        if strict:
            bad = {
                k: v
                for k, v in scan.counts.items()
                if k in ("corrupt_bytes", "corrupt_messages", "truncated") and v
            }
            if bad:
                damage = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in bad.items())
                raise FlightLogError(f"strict: the log is damaged ({damage})")
        chosen = select(scan, imu_data)
        return _convert(
            reader, scan, chosen, output, array, start_time_ns, compression, half(size / 2)
        )


def _convert(
    reader: FlightLogReader,
    scan: LogScan,
    chosen: Selection,
    output: str | os.PathLike[str] | BinaryIO,
    array: ArrayConfig | None,
    start_time_ns: int | None,
    compression: str,
    progress: Any,
) -> FlightLogIngest:
    from imufdi_cli import mcapio
    from imufdi_cli.validity import ValidityCounter, apply_calibration

    streams = chosen.streams()
    m = len(chosen.imus)
    if any(s.rate_hz is None for s in streams):
        few = ", ".join(f"{s.name} ({s.count})" for s in streams if s.rate_hz is None)
        raise FlightLogError(f"too few samples to form an array: {few}")
    rates = [float(s.rate_hz or 0.0) for s in streams]
    reference = int(np.argmin(rates))
    grid_rate = rates[reference]
    tolerance_us = int(0.5e6 / grid_rate)
    aligner = NearestAligner([s.width for s in streams], reference, tolerance_us)
    warnings = list(scan.notes) + list(chosen.notes)
    name = FORMAT_NAMES[scan.format]
    min_rate = chosen.min_rate_hz
    rate_message = None
    if min_rate < MIN_TEST_RATE_HZ:
        rate_message = (
            f"this {name} holds per-IMU data ({chosen.source}) at {min_rate:.3g} Hz, too low"
            f" to test (at least {MIN_TEST_RATE_HZ:g} Hz per IMU); {logging_hint(scan.format)}"
        )
        warnings.append(rate_message)
    if array is None:
        array = ArrayConfig.co_aligned(
            m, rate_hz=grid_rate, sensors=chosen.sensors, positions=_positions(scan, m)
        )
    elif array.n_imus != m:
        raise UsageError(f"--array has {array.n_imus} IMUs, this {name} {m} ({chosen.source})")
    counter = ValidityCounter(array)
    columns = _columns(chosen)
    offset_us = scan.utc_offset_us or 0
    shift_ns: int | None = None

    def blocks() -> Iterator[ImuBlock]:
        for part in reader.chunks(streams, progress=progress):
            for k, t_us, values in part:
                aligner.add(k, t_us, values)
            yield from _blocks(aligner.pop(), columns, m, chosen.sensors)
        yield from _blocks(aligner.pop(final=True), columns, m, chosen.sensors)

    samples = 0
    first_ns: int | None = None
    last_ns: int | None = None
    try:
        target = Path(output) if isinstance(output, os.PathLike) else output
        with mcapio.McapWriter(target, compression=compression) as writer:
            imu_writer = mcapio.ImuArrayWriter(writer, array)
            for block in blocks():
                counter.count(block)
                if array.calibrated:
                    block = apply_calibration(block, array)
                t_ns = block.t_ns * 1000 + offset_us * 1000
                if start_time_ns is not None:
                    if shift_ns is None:
                        shift_ns = int(start_time_ns) - int(t_ns[0])
                    t_ns = t_ns + shift_ns
                block = replace(block, t_ns=t_ns)
                first_ns = int(t_ns[0]) if first_ns is None else first_ns
                last_ns = int(t_ns[-1])
                samples += len(block)
                imu_writer.write_block(block, owned=True)
            if samples == 0:
                raise FlightLogError(
                    f"no array samples: the {m} IMU streams of this {name} never have samples"
                    f" within {tolerance_us / 1000:g} ms of each other"
                )
            record = _record(scan, chosen, aligner, grid_rate, tolerance_us, rate_message, warnings)
            record["utc"] = (
                None
                if scan.utc_offset_us is None
                else {
                    "offset_us": scan.utc_offset_us,
                    "source": scan.utc_source,
                    "start": iso_utc((first_ns or 0) // 1000),
                }
            )
            record["parameters_of_ingest"] = {
                "start_time_ns": start_time_ns,
                "time_offset_ns": (shift_ns if shift_ns is not None else offset_us * 1000),
            }
            record["validity"] = counter.counts
            record["span_ns"] = [first_ns, last_ns]
            writer.add_metadata("imufdi.ingest", {"json": json.dumps(record)})
    except ImufdiError:
        raise
    except (OSError, ValueError) as err:
        raise FlightLogError(f"cannot write {output}: {err}") from err
    return FlightLogIngest(record=record, warnings=warnings)


def _columns(chosen: Selection) -> list[tuple[int, str, int]]:
    """Per stream of ``chosen.streams()``: (IMU index, sensor type, first value column)
    of each of its triads, flattened as (stream, imu, sensor, column) in stream order."""
    out = []
    index = 0
    for k, imu in enumerate(chosen.imus):
        for stream in imu.streams():
            for j, sensor in enumerate(stream.sensors):
                out.append((index, k, sensor, 3 * j))
            index += 1
    return out  # type: ignore[return-value]


def _blocks(
    popped: tuple[np.ndarray, list[np.ndarray]],
    columns: list[Any],
    m: int,
    sensors: tuple[str, ...],
) -> Iterator[ImuBlock]:
    t_us, values = popped
    n = t_us.shape[0]
    if n == 0:
        return
    triads: dict[str, np.ndarray] = {s: np.empty((n, m, 3)) for s in sensors}
    for stream, imu, sensor, column in columns:
        if sensor in triads:
            triads[sensor][:, imu, :] = values[stream][:, column : column + 3]
    yield ImuBlock(t_ns=t_us, **triads)


def _record(
    scan: LogScan,
    chosen: Selection,
    aligner: NearestAligner,
    grid_rate: float,
    tolerance_us: int,
    rate_message: str | None,
    warnings: list[str],
) -> dict[str, Any]:
    streams = chosen.streams()
    counts = aligner.counts
    return {
        "format": scan.format,
        "layout_name": scan.format,
        "system": scan.system,
        "imu_data": chosen.source,
        "imu_data_description": SOURCE_HELP[chosen.source],
        "n_imus": len(chosen.imus),
        "sensors": list(chosen.sensors),
        "imus": [[s.name for s in imu.streams()] for imu in chosen.imus],
        "imu_rates_hz": [round(imu.rate_hz(), 4) for imu in chosen.imus],
        "streams": [s.to_dict() for s in scan.streams],
        "alignment": {
            "method": "nearest sample within the tolerance, no resampling; stamp = latest value time",
            "reference": streams[aligner.reference].name,
            "rate_hz": round(grid_rate, 4),
            "tolerance_us": tolerance_us,
            "samples": counts.samples,
            "dropped": counts.dropped,
            "max_skew_us": counts.max_skew_us,
            "mean_skew_us": round(counts.skew_sum_us / counts.samples, 1)
            if counts.samples
            else None,
            "unused": {s.name: counts.unused[i] for i, s in enumerate(streams)},
            "late": {s.name: counts.late[i] for i, s in enumerate(streams)},
        },
        "geometry": (
            "co-aligned in the frame the log gives (PX4 sensor_*: board frame; vehicle_imu and"
            " ArduPilot: body frame), at the logged positions (ArduPilot INS_POS*) or the origin;"
            " override with --array"
        ),
        "rate": {
            "testable": rate_message is None,
            "min_per_imu_hz": round(chosen.min_rate_hz, 4),
            "minimum_hz": MIN_TEST_RATE_HZ,
            "message": rate_message,
            "logging_hint": logging_hint(scan.format),
        },
        "batch_sampler": scan.batches or None,
        "parameters": scan.parameters,
        "counts": scan.counts,
        "warnings": warnings,
    }
