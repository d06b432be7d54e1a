"""File-level operations behind the thin CLI commands: simulate, ingest, info, tune, demo.

Each function takes paths (``-`` for stdin/stdout) and options as the CLI received them,
does one job, and returns a result object; nothing here prints (the demo renders through a
console passed in by the CLI).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, cast

from imufdi_cli.array import ArrayConfig
from imufdi_cli.errors import UsageError
from imufdi_cli.units import parse_quantity

#: the bundled sample logs (package data: installed with the package, wheel or editable)
SAMPLE_LOGS = Path(__file__).resolve().parent / "sample_logs"


# --- simulate --------------------------------------------------------------------------


@dataclass
class SimulateResult:
    output: str
    samples: int
    n_imus: int
    rate_hz: float
    duration_s: float
    capture_bytes: int = 0


def simulate_file(
    preset_name: str | None,
    output: str,
    *,
    seed: int = 0,
    options: Mapping[str, Any] | None = None,
    capture: str | None = None,
    corrupt: bool = False,
) -> SimulateResult:
    """Simulate a log (preset or free options) into an MCAP, streaming in blocks.

    With ``capture``, the same samples are also written as a raw ``mpu6500-array`` serial
    capture (optionally with corrupted stretches), the input of ``imufdi ingest``
    (``-`` = stdout, when the MCAP goes to a file). Both outputs are atomic: on any failure
    neither file is created or changed.
    """
    from imufdi_cli.fileio import check_outputs

    check_outputs([], [("-o", output), ("--capture", capture)])
    if capture == "-" and output == "-":
        raise UsageError("-o - and --capture -: only one output can go to stdout")
    from imufdi_cli.mcapio import ImuArrayWriter, McapWriter
    from imufdi_cli.simulate import config_from_options, simulate

    config = config_from_options(preset_name, seed=seed, **dict(options or {}))
    array, blocks = simulate(config)
    samples = 0
    first = last = 0
    capture_bytes = 0
    metadata = {
        "imufdi.simulate": {
            "json": json.dumps(
                {
                    "preset": preset_name,
                    "seed": seed,
                    "options": {k: str(v) for k, v in (options or {}).items()},
                }
            )
        }
    }
    with ExitStack() as stack:
        writer = stack.enter_context(McapWriter(output))
        capture_file = None
        encoder = None
        if capture:
            from imufdi_cli.capture import CaptureEncoder
            from imufdi_cli.fileio import open_atomic

            encoder = CaptureEncoder(array, corrupt=corrupt, seed=seed)
            # streamed like the MCAP: memory stays flat with log length
            capture_file = (
                sys.stdout.buffer if capture == "-" else stack.enter_context(open_atomic(capture))
            )
        for name, data in metadata.items():
            writer.add_metadata(name, data)
        imu_writer = ImuArrayWriter(writer, array)
        for block in blocks:
            if samples == 0 and len(block):
                first = int(block.t_ns[0])
            if len(block):
                last = int(block.t_ns[-1])
            samples += len(block)
            imu_writer.write_block(block)
            if encoder is not None and capture_file is not None:
                capture_bytes += _write_output(capture_file, encoder.encode(block), capture)
        if encoder is not None and capture_file is not None:
            capture_bytes += _write_output(capture_file, encoder.finish(), capture)
    return SimulateResult(
        output=output,
        samples=samples,
        n_imus=array.n_imus,
        rate_hz=array.rate_hz,
        duration_s=(last - first) / 1e9 + 1.0 / array.rate_hz if samples else 0.0,
        capture_bytes=capture_bytes,
    )


def _write_output(handle: Any, data: bytes, name: str | None) -> int:
    """Write to an output file; a full disk or file size limit is an OutputError naming it."""
    try:
        return int(handle.write(data))
    except BrokenPipeError:
        raise
    except OSError as err:
        from imufdi_cli.errors import OutputError

        raise OutputError(
            f"cannot write {name}: {err.strerror or err}; nothing was written"
        ) from err


# --- ingest ----------------------------------------------------------------------------


class _Prefixed:
    """A binary stream whose first bytes were read already (to recognise its format)."""

    def __init__(self, head: bytes, stream: Any, name: str) -> None:
        self._head = head
        self._stream = stream
        self.name = name

    def read(self, size: int = -1) -> bytes:
        if self._head:
            if size is None or size < 0:
                data, self._head = self._head + self._stream.read(), b""
                return data
            data, self._head = self._head[:size], self._head[size:]
            if len(data) < size:
                data += self._stream.read(size - len(data))
            return data
        return bytes(self._stream.read(size))


def _read_head(capture: str, size: int) -> bytes:
    """The first ``size`` bytes of a capture file or of stdin (``-``; consumed)."""
    from imufdi_cli.errors import CaptureError

    try:
        if capture == "-":
            head = b""
            while len(head) < size:
                more = sys.stdin.buffer.read(size - len(head))
                if not more:
                    break
                head += more
            return head
        with open(capture, "rb") as handle:
            return handle.read(size)
    except OSError as err:
        raise CaptureError(f"cannot read capture {capture}: {err.strerror or err}") from err


def ingest_file(
    capture: str,
    output: str,
    *,
    layout: str | None = None,
    array_path: str | None = None,
    rate: str | None = None,
    gyro_fs: str | None = None,
    accel_fs: str | None = None,
    strict: bool = False,
    start_time: str | None = None,
    imu_data: str | None = None,
    progress: Any = None,
) -> Any:
    """Convert a raw capture or a flight-controller log into an MCAP; returns what the
    conversion counted (``as_rows()``, ``to_dict()``).

    The format is recognised by content: a PX4 ULog or an ArduPilot DataFlash log goes to
    :func:`imufdi_cli.fclog.ingest_flight_log` (``imu_data``: which IMU data; ``layout``,
    ``rate``, ``gyro_fs`` and ``accel_fs`` do not apply); anything else is a capture parsed
    with ``layout`` (default ``mpu6500-array``). ``start_time``: wall-clock time of the
    first sample (see :func:`parse_start_time`); default: the GPS time of a flight log,
    the device's own time of a capture. ``progress(bytes read, bytes or None)``: see
    :mod:`imufdi_cli.progress`."""
    from imufdi_cli.fclog import FORMAT_NAMES, SNIFF_BYTES, ingest_flight_log, sniff_format

    head = _read_head(capture, SNIFF_BYTES)
    fmt = sniff_format(head)
    array = ArrayConfig.load(array_path) if array_path else None
    start_time_ns = None if start_time is None else parse_start_time(start_time)
    stdin = capture == "-"
    if fmt is not None:
        given = [
            option
            for option, value in (
                ("--layout", layout),
                ("--rate", rate),
                ("--gyro-fs", gyro_fs),
                ("--accel-fs", accel_fs),
            )
            if value is not None
        ]
        if given:
            article = "an" if FORMAT_NAMES[fmt][0] in "AEIOU" else "a"
            raise UsageError(
                f"{capture} is {article} {FORMAT_NAMES[fmt]} (recognised by its content):"
                f" {', '.join(given)} {'applies' if len(given) == 1 else 'apply'} to raw"
                f" captures only; leave {'it' if len(given) == 1 else 'them'} out"
            )
        return ingest_flight_log(
            "-" if stdin else capture,
            output,
            fmt=fmt,
            head=head if stdin else b"",
            imu_data=imu_data or "auto",
            array=array,
            strict=strict,
            start_time_ns=start_time_ns,
            progress=progress,
        )
    if imu_data is not None:
        raise UsageError(
            f"--imu-data applies to flight-controller logs only; {capture} is neither a PX4 ULog"
            " nor an ArduPilot DataFlash log (they are recognised by their first bytes)"
        )
    from imufdi_cli.capture import ingest, load_layout
    from imufdi_cli.errors import CaptureError

    builtin: dict[str, Any] = {}
    if gyro_fs is not None:
        builtin["gyro_fs"] = gyro_fs
    if accel_fs is not None:
        builtin["accel_fs"] = accel_fs
    layout_obj = load_layout(layout or "mpu6500-array", **builtin)
    rate_hz = parse_quantity(rate, "frequency", name="--rate") if rate else None
    try:
        return ingest(
            cast(BinaryIO, _Prefixed(head, sys.stdin.buffer, "stdin")) if stdin else capture,
            output,
            layout=layout_obj,
            array=array,
            rate_hz=rate_hz,
            strict=strict,
            start_time_ns=start_time_ns,
            progress=progress,
        )
    except CaptureError as err:
        if layout is None and str(err).startswith("no frames"):
            raise CaptureError(
                f"{err}; nor is {capture} a PX4 ULog or an ArduPilot DataFlash log (recognised"
                " by their first bytes): give --layout for another frame layout"
            ) from err
        raise


def parse_start_time(text: str) -> int:
    """``--start-time``: ISO 8601 date and time (``2024-05-01T12:00:00.25Z``; without a
    zone: UTC) or seconds since the Unix epoch (``1714564800.25``) -> ns since the epoch.

    Raises UsageError (naming ``--start-time``) for anything else.
    """
    from datetime import datetime, timezone
    from decimal import Decimal, InvalidOperation

    from imufdi_cli.errors import UsageError

    value = text.strip()
    try:
        return int(Decimal(value) * 1_000_000_000)
    except InvalidOperation:
        pass
    try:
        moment = datetime.fromisoformat(value.replace("Z", "+00:00").replace("z", "+00:00"))
    except ValueError as err:
        raise UsageError(
            f"--start-time {text!r} is neither an ISO 8601 time (2024-05-01T12:00:00Z) nor"
            " seconds since the Unix epoch"
        ) from err
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=timezone.utc)
    epoch = datetime(1970, 1, 1, tzinfo=timezone.utc)
    delta = moment - epoch
    return (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1000


# --- info ------------------------------------------------------------------------------


def log_info(
    source: str,
    *,
    topics: Sequence[str] | None = None,
    time_source: str = "auto",
    strict: bool = False,
) -> dict[str, Any]:
    """:func:`imufdi_cli.info.log_info` (there: ``imufdi info`` does not import this
    module; start-up time, docs/performance.md)."""
    from imufdi_cli.info import log_info as _log_info

    return _log_info(source, topics=topics, time_source=time_source, strict=strict)


# --- tune ------------------------------------------------------------------------------


def tune_file(
    source: str,
    segment: tuple[float, float | None],
    *,
    sensor_type: str = "gyro",
    seed: int = 0,
    settings: Mapping[str, str] | None = None,
) -> Any:
    """Run WOA on a fault-free segment of a log; returns the tune result (K, alpha, ...)."""
    from imufdi_cli.detectors.woa_mvmd_glt import tune
    from imufdi_cli.mcapio import read_array

    array, block = read_array(source)
    if len(block) == 0:
        from imufdi_cli.errors import McapInputError

        raise McapInputError(f"{source}: no aligned IMU samples")
    rel = (block.t_ns - block.t_ns[0]) / 1e9
    keep = rel >= segment[0]
    if segment[1] is not None:
        keep &= rel < segment[1]
    if not keep.any():
        raise UsageError(
            f"--segment {segment[0]:g}s:{segment[1] if segment[1] is not None else ''} holds no"
            f" samples (the log lasts {rel[-1]:.3g} s)"
        )
    if sensor_type not in array.sensor_types():
        raise UsageError(
            f"--sensor {sensor_type}: the log has no {sensor_type}; present: "
            + ", ".join(array.sensor_types())
        )
    from imufdi_cli.validity import Conditioner

    # clipped or impossible values (NaN, 1e308) replaced by the consensus, as in detect
    conditioner = Conditioner(array)
    segment_block, flags = conditioner.prepare(block.mask(keep))
    conditioner.fit(segment_block, flags)
    segment_block = conditioner.sanitize(segment_block, flags, count=False)
    return tune(segment_block, array, sensor_type=sensor_type, seed=seed, **_woa_settings(settings))


#: ``imufdi tune --param KEY=VALUE`` settings and their types.
TUNE_SETTINGS: dict[str, type] = {
    "population": int,
    "iterations": int,
    "k_min": int,
    "k_max": int,
    "alpha_min": float,
    "alpha_max": float,
    "max_iter": int,
    "fitness": str,
    "validation_step": float,
    "delay_weight": float,
    "window": int,
    "overlap": int,
}


def _woa_settings(settings: Mapping[str, str] | None) -> dict[str, Any]:
    """Typed WOA settings from strings; bounds grouped as the tuner wants them."""
    typed: dict[str, Any] = {}
    for key, text in (settings or {}).items():
        if key not in TUNE_SETTINGS:
            raise UsageError(
                f"--param {key}: unknown tune setting; valid: {', '.join(TUNE_SETTINGS)}"
            )
        try:
            typed[key] = TUNE_SETTINGS[key](text)
        except ValueError:
            raise UsageError(
                f"--param {key}={text!r}: not a valid {TUNE_SETTINGS[key].__name__}"
            ) from None
    passed = (
        "population",
        "iterations",
        "max_iter",
        "fitness",
        "validation_step",
        "delay_weight",
        "window",
        "overlap",
    )
    out: dict[str, Any] = {k: v for k, v in typed.items() if k in passed}
    if "k_min" in typed or "k_max" in typed:
        out["k_bounds"] = (typed.get("k_min", 2), typed.get("k_max", 6))
    if "alpha_min" in typed or "alpha_max" in typed:
        out["alpha_bounds"] = (typed.get("alpha_min", 50.0), typed.get("alpha_max", 5000.0))
    return out
