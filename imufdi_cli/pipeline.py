"""File-level operations behind the thin CLI commands: simulate, ingest, info, tune, demo.

Each function takes paths (``-`` for stdin/stdout) and options as the CLI received them,
does one job, and returns a result object; nothing here prints (the demo renders through a
console passed in by the CLI).
"""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from imufdi_cli.array import ArrayConfig
from imufdi_cli.errors import UsageError
from imufdi_cli.units import parse_quantity

if TYPE_CHECKING:
    from imufdi_cli.cli.plain import PlainTable

SAMPLE_LOGS = Path(__file__).resolve().parent.parent / "sample_logs"


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


def ingest_file(
    capture: str,
    output: str,
    *,
    layout: str = "mpu6500-array",
    array_path: str | None = None,
    rate: str | None = None,
    gyro_fs: str | None = None,
    accel_fs: str | None = None,
    strict: bool = False,
    start_time: str | None = None,
    progress: Any = None,
) -> Any:
    """Parse a raw capture with a layout and write the MCAP; returns the ingest stats.

    ``start_time``: wall-clock time of the first frame (see :func:`parse_start_time`);
    default: the device's own time. ``progress(bytes read, capture bytes or None)``:
    see :mod:`imufdi_cli.progress`."""
    from imufdi_cli.capture import ingest, load_layout

    builtin: dict[str, Any] = {}
    if gyro_fs is not None:
        builtin["gyro_fs"] = gyro_fs
    if accel_fs is not None:
        builtin["accel_fs"] = accel_fs
    layout_obj = load_layout(layout, **builtin)
    array = ArrayConfig.load(array_path) if array_path else None
    rate_hz = parse_quantity(rate, "frequency", name="--rate") if rate else None
    return ingest(
        capture,
        output,
        layout=layout_obj,
        array=array,
        rate_hz=rate_hz,
        strict=strict,
        start_time_ns=None if start_time is None else parse_start_time(start_time),
        progress=progress,
    )


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
    """:func:`imufdi_cli.mcapio.summary.log_info` (moved there: ``imufdi info`` does not
    import this module; start-up time, docs/performance.md)."""
    from imufdi_cli.mcapio.summary import log_info as _log_info

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


# --- demo ------------------------------------------------------------------------------

DEMO_FAULT = "step:imu0.gyro.x,at=2.5s,amp=0.9deg/s"


@dataclass
class DemoStep:
    name: str
    command: str
    seconds: float
    output: str


@dataclass
class DemoResult:
    directory: str
    steps: list[DemoStep] = field(default_factory=list)


def demo_table(report: Any) -> PlainTable:
    """The demo's table: the report's terminal columns (right-justified) per detector and
    sensor type."""
    from imufdi_cli import report as rep
    from imufdi_cli.cli.plain import PlainTable

    columns = rep.table_columns(report, console=True)
    table = PlainTable(
        ("detector", "sensor", *(header for _, header, _, _ in columns)),
        title="demo: 0.9 deg/s step on imu0.gyro.x at 2.5 s (paper-table4)",
        justify=("left", "left", *("right" for _ in columns)),
    )
    for row in rep.table_rows(report, console=True):
        table.add_row(*row)
    return table


def run_demo(keep_dir: str | None, *, console: Any) -> DemoResult:
    """ingest (or simulate) -> inject -> detect -> report on the bundled sample, printing
    each step as the equivalent command line."""
    from imufdi_cli import report as rep
    from imufdi_cli.cli.ui import print_table
    from imufdi_cli.detect import detect_file
    from imufdi_cli.detectors import DETECTORS
    from imufdi_cli.faults import inject_file
    from imufdi_cli.fileio import atomic_path, check_outputs, write_text

    if keep_dir:
        workdir = Path(keep_dir)
        workdir.mkdir(parents=True, exist_ok=True)
        cleanup = False
    else:
        workdir = Path(tempfile.mkdtemp(prefix="imufdi-demo-"))
        cleanup = True
    result = DemoResult(directory=str(workdir))
    check_outputs(
        [p for p in SAMPLE_LOGS.iterdir() if p.is_file()] if SAMPLE_LOGS.is_dir() else [],
        [
            (f"--keep {keep_dir}", workdir / name)
            for name in ("table4.mcap", "faulty.mcap", "detected.mcap", "report.md")
        ],
    )

    def step(name: str, command: str, output: Path, fn: Any) -> Any:
        console.print(f"[bold cyan]$ {command}[/]", markup=True)
        start = time.perf_counter()
        value = fn()
        seconds = time.perf_counter() - start
        result.steps.append(DemoStep(name, command, seconds, str(output)))
        console.print(f"  [dim]{seconds:.2f} s -> {output}[/]", markup=True)
        return value

    try:
        capture = SAMPLE_LOGS / "paper-table4.cap"
        base = workdir / "table4.mcap"
        if capture.exists():
            stats = step(
                "ingest",
                f"imufdi ingest {capture.relative_to(SAMPLE_LOGS.parent)} -o {base}",
                base,
                lambda: ingest_file(str(capture), str(base)),
            )
            rows = dict(stats.as_rows())
            console.print(
                "  "
                + ", ".join(
                    f"{k}: {v}" for k, v in rows.items() if isinstance(v, (int, float)) and v
                )
            )
        else:
            sample = SAMPLE_LOGS / "paper-table4.mcap"
            with atomic_path(base) as tmp:
                shutil.copyfile(sample, tmp)
        faulty = workdir / "faulty.mcap"
        step(
            "inject",
            f"imufdi inject {base} --fault {DEMO_FAULT} --seed 1 -o {faulty}",
            faulty,
            lambda: inject_file(str(base), str(faulty), [DEMO_FAULT], [], seed=1),
        )
        detected = workdir / "detected.mcap"
        names = [
            n for n in ("glt", "woa-mvmd-glt", "pca-parity", "bank", "noise-glr") if n in DETECTORS
        ]
        flags = " ".join(f"-d {n}" for n in names)
        step(
            "detect",
            f"imufdi detect {faulty} {flags} -o {detected}",
            detected,
            lambda: detect_file(str(faulty), str(detected), [(n, {}) for n in names]),
        )
        md = workdir / "report.md"
        report = step(
            "report",
            f"imufdi report {detected} --markdown {md}",
            md,
            lambda: rep.build_report(str(detected)),
        )
        write_text(str(md), rep.to_markdown(report))
        print_table(console, demo_table(report))
        if keep_dir:
            console.print(f"outputs kept in {workdir}")
    finally:
        if cleanup:
            shutil.rmtree(workdir, ignore_errors=True)
    return result
