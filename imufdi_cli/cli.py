"""The ``imufdi`` command line: thin click commands over the library.

Each command parses its options, calls one library function and renders the result with
rich. Data go to ``-o`` (``-`` = stdout); human-readable summaries go to stderr when data go
to stdout, so commands compose in pipelines::

    imufdi ingest cap.bin -o - | imufdi inject - --fault ... -o - | imufdi detect - -d glt -o - | imufdi report -

Exit codes: 0 ok, 1 a CI gate failed, 2 usage error, 3 bad input data (or an I/O error
such as a full disk), 4 internal error; 130 interrupted (SIGINT), 143 terminated (SIGTERM),
129 hung up (SIGHUP): 128 + the signal number, after removing any partial output.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
import traceback
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

# The maths works on thin matrices (tens of sensors) where multi-threaded BLAS only adds
# contention on small machines (10-20x slower measured on 2 cores under load); campaigns
# get their parallelism from processes. Users can still override these.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import click  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from imufdi_cli import __version__  # noqa: E402
from imufdi_cli.detectors import DETECTORS  # noqa: E402
from imufdi_cli.errors import (  # noqa: E402
    EXIT_BAD_INPUT,
    EXIT_GATE_FAILED,
    EXIT_USAGE,
    ImufdiError,
    UnitError,
)

EXIT_INTERNAL = 4


def _console(to_stdout: bool) -> Console:
    """Console for summaries: stderr when stdout carries data. Not a terminal (pipes,
    CI logs): wide enough that tables are not truncated."""
    stream = sys.stdout if to_stdout else sys.stderr
    width = None if stream.isatty() else 160
    return Console(stderr=not to_stdout, highlight=False, soft_wrap=True, width=width)


def _err(message: str) -> None:
    """One non-empty line on stderr."""
    from rich.markup import escape

    message = " ".join(str(message).split()) or "unknown error (no message)"
    if sys.stderr.isatty():
        Console(stderr=True, highlight=False, soft_wrap=True).print(
            f"[bold red]imufdi: error:[/] {escape(message)}", markup=True
        )
    else:
        sys.stderr.write(f"imufdi: error: {message}\n")


def _warn(console: Console, warnings: Sequence[str]) -> None:
    for warning in warnings:
        console.print(f"[yellow]warning:[/] {warning}", markup=True)


def _start_end(start: str | None, end: str | None) -> tuple[float, float | None] | None:
    """``--start``/``--end`` as a window (seconds from the first sample), or None."""
    from imufdi_cli.errors import UsageError
    from imufdi_cli.units import parse_quantity

    if start is None and end is None:
        return None
    start_s = parse_quantity(start, "time", name="--start") if start is not None else 0.0
    end_s = parse_quantity(end, "time", name="--end") if end is not None else None
    if start_s < 0 or (end_s is not None and end_s <= start_s):
        raise UsageError(f"--start {start!r} / --end {end!r}: need 0 <= START < END")
    return start_s, end_s


def _time_source(stamps: str) -> str:
    """--stamps choice -> ImuArrayReader time source."""
    return "log_time" if stamps == "log" else stamps


def _time_range(text: str | None, name: str) -> tuple[float, float | None] | None:
    from imufdi_cli.units import parse_time_range

    if text is None:
        return None
    return parse_time_range(text, name=name)


#: options shared by every command that reads Imu topics (info, inject, detect)
_topic_option = click.option(
    "--topic",
    "topics",
    multiple=True,
    help="Imu topic to use, in array order (repeatable); /TOPIC:FIELD picks the"
    " sensor_msgs/msg/Imu field FIELD of a larger message.",
)
_stamps_option = click.option(
    "--stamps",
    type=click.Choice(["auto", "header", "log"]),
    default="auto",
    show_default=True,
    help="Imu time: header.stamp, MCAP log time, or auto (header; log time when the Imu has"
    " no header or all-zero stamps, with a warning).",
)


class _Group(click.Group):
    def format_epilog(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        formatter.write_paragraph()
        formatter.write_text(
            "Exit codes: 0 ok, 1 CI gate failed, 2 usage error, 3 bad input data or I/O error,"
            " 4 internal error, 130/143 interrupted/terminated."
        )


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="imufdi")
def cli() -> None:
    """Fault detection and isolation for redundant MEMS IMU arrays, on MCAP logs.

    Example:


    \b
        imufdi simulate --preset paper-table4 --seed 1 -o run.mcap
        imufdi inject run.mcap --fault step:imu0.gyro.x,at=2.5s,amp=0.9deg/s -o faulty.mcap
        imufdi detect faulty.mcap -d glt -o detected.mcap
        imufdi report detected.mcap --fail-if 'glt.gyro.far > 0.08'
    """


# --- simulate --------------------------------------------------------------------------


@cli.command()
@click.option("--preset", "preset_name", help="Reference scenario (see docs/simulate.md).")
@click.option("--imus", type=int, help="Number of IMUs (free simulation or preset override).")
@click.option("--rate", help="Sample rate, e.g. 100Hz, 1kHz.")
@click.option("--duration", help="Log length, e.g. 5s, 1h.")
@click.option("--motion", help="static, turntable, swing, vehicle, attitude.")
@click.option("--gyro-noise", help="Gyro white noise sigma, e.g. 0.15deg/s.")
@click.option("--accel-noise", help="Accel white noise sigma, e.g. 0.02m/s^2.")
@click.option("--outliers/--no-outliers", default=None, help="Gyro outliers on or off.")
@click.option("--chip-bias", help="Constant chip-to-chip gyro bias sigma, e.g. 0.5deg/s.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@click.option("-o", "--output", required=True, help="Output MCAP, or - for stdout.")
@click.option("--capture", "capture", help="Also write a raw serial capture (mpu6500-array).")
@click.option(
    "--corrupt/--no-corrupt",
    default=False,
    help="With --capture: add a few corrupted stretches (garbage, bad CRC, cut and lost frames).",
)
def simulate(
    preset_name: str | None,
    imus: int | None,
    rate: str | None,
    duration: str | None,
    motion: str | None,
    gyro_noise: str | None,
    accel_noise: str | None,
    outliers: bool | None,
    chip_bias: str | None,
    seed: int,
    output: str,
    capture: str | None,
    corrupt: bool,
) -> None:
    """Simulate an IMU array log from a reference scenario or free options.

    Bit-reproducible for a given --seed.

    Example:


    \b
        imufdi simulate --preset paper-table4 --seed 3 -o table4.mcap
        imufdi simulate --imus 16 --rate 1kHz --duration 1h --motion turntable -o long.mcap
    """
    from imufdi_cli.fileio import check_outputs
    from imufdi_cli.pipeline import simulate_file

    check_outputs([], [("-o", output), ("--capture", capture)])
    options: dict[str, Any] = {
        k: v
        for k, v in dict(
            imus=imus,
            rate=rate,
            duration=duration,
            motion=motion,
            gyro_noise=gyro_noise,
            accel_noise=accel_noise,
            outliers=outliers,
            chip_biases=chip_bias,
        ).items()
        if v is not None
    }
    result = simulate_file(
        preset_name, output, seed=seed, options=options, capture=capture, corrupt=corrupt
    )
    console = _console(output != "-")
    console.print(
        f"simulated {result.samples} samples of {result.n_imus} IMUs "
        f"({result.duration_s:g} s at {result.rate_hz:g} Hz) -> {output}"
    )
    if capture:
        console.print(f"raw capture -> {capture} ({result.capture_bytes} bytes)")


# --- ingest ----------------------------------------------------------------------------


@cli.command()
@click.argument("capture")
@click.option("-o", "--output", help="Output MCAP (default: CAPTURE with .mcap), - for stdout.")
@click.option(
    "--layout",
    default="mpu6500-array",
    show_default=True,
    help="mpu6500-array, csv, or a TOML layout file.",
)
@click.option("--array", "array_path", help="ArrayConfig TOML (rotations, positions, axes).")
@click.option("--rate", help="Nominal sample rate when frames carry no timestamp, e.g. 100Hz.")
@click.option("--gyro-fs", help="Built-in layout gyro full scale: 250, 500, 1000, 2000 (deg/s).")
@click.option("--accel-fs", help="Built-in layout accel full scale: 2, 4, 8, 16 (g).")
@click.option("--strict", is_flag=True, help="Any dropped byte is an error (exit 3).")
@click.option(
    "--start-time",
    help="Wall-clock time of the first frame (ISO 8601, e.g. 2024-05-01T12:00:00Z, or Unix"
    " seconds); stamps keep the device's intervals. Default: the device's own clock (from 0,"
    " shown as 1970 by viewers).",
)
def ingest(
    capture: str,
    output: str | None,
    layout: str,
    array_path: str | None,
    rate: str | None,
    gyro_fs: str | None,
    accel_fs: str | None,
    strict: bool,
    start_time: str | None,
) -> None:
    """Convert a raw serial capture (or CSV) into an IMU array MCAP.

    Resynchronises after garbage, drops frames with bad checksums, unwraps counters and
    timestamps, counts every dropped byte, frame and gap.

    Example:


    \b
        imufdi ingest board.bin --layout my_board.toml --array array.toml -o board.mcap
        cat capture.bin | imufdi ingest - -o - | imufdi info -
    """
    from imufdi_cli.fileio import check_input, check_outputs
    from imufdi_cli.pipeline import ingest_file

    check_input(capture)
    if output is None:
        output = "-" if capture == "-" else os.path.splitext(capture)[0] + ".mcap"
    layout_file = layout if layout.lower().endswith(".toml") else None
    check_outputs([capture, layout_file, array_path], [("-o", output)])
    stats = ingest_file(
        capture,
        output,
        layout=layout,
        array_path=array_path,
        rate=rate,
        gyro_fs=gyro_fs,
        accel_fs=accel_fs,
        strict=strict,
        start_time=start_time,
    )
    console = _console(output != "-")
    table = Table(title=f"ingest {capture} -> {output}", show_header=True)
    table.add_column("count")
    table.add_column("value", justify="right")
    for key, value in stats.as_rows():
        table.add_row(key, str(value))
    console.print(table)


# --- info ------------------------------------------------------------------------------


@cli.command()
@click.argument("log")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of tables.")
@_topic_option
@_stamps_option
@click.option("--strict", is_flag=True, help="A truncated or corrupt input is an error (exit 3).")
def info(log: str, as_json: bool, topics: tuple[str, ...], stamps: str, strict: bool) -> None:
    """Describe a log: topics, IMUs, rate, duration, gaps, array, faults, detectors.

    Example:


    \b
        imufdi info run.mcap
        imufdi info run.mcap --json | jq .imu_count
    """
    from imufdi_cli.fileio import check_input
    from imufdi_cli.pipeline import log_info

    check_input(log)
    summary = log_info(
        log, topics=list(topics) or None, time_source=_time_source(stamps), strict=strict
    )
    if as_json:
        click.echo(json.dumps(summary, indent=2))
        return
    console = _console(True)
    _render_info(console, summary)


def _has_cal(imu: dict[str, Any]) -> bool:
    return any(key.endswith(("_matrix", "_bias")) for key in imu)


def _render_info(console: Console, s: dict[str, Any]) -> None:
    console.print(f"[bold]{s['source']}[/]", markup=True)
    head = Table(show_header=False, box=None)
    head.add_column(style="bold")
    head.add_column()
    for key in ("n_imus", "n_samples", "duration_s", "start_ns"):
        if key in s:
            value = s[key]
            head.add_row(key, f"{value:.6g}" if isinstance(value, float) else str(value))
    if s.get("rate_hz") is not None:
        head.add_row("rate_hz", f"{s['rate_hz']:.6g}  ({s.get('rate_method', '')})")
    if s.get("time_source"):
        head.add_row("stamps", "header.stamp" if s["time_source"] == "header" else "log time")
    fields = {t: f for t, f in s.get("imu_fields", {}).items() if f}
    for topic, path in fields.items():
        head.add_row("imu field", f"{topic}: {path}")
    gaps = s.get("gaps") or {}
    if gaps:
        text = f"{gaps.get('count', 0)}"
        if gaps.get("count"):
            text += (
                f" ({gaps['missing_samples']} samples missing of {gaps['expected_samples']}"
                f" expected; longest {gaps['longest_s']:.6g} s)"
            )
        head.add_row("gaps (all topics)", text)
    ingest = s.get("ingest")
    if ingest:
        labels = (
            ("frames_ok", "frames ok"),
            ("frames_lost", "lost"),
            ("frames_bad_checksum", "bad checksum"),
            ("frames_truncated", "truncated"),
            ("duplicates", "duplicates"),
            ("bytes_dropped", "bytes dropped"),
        )
        parts = [f"{label} {ingest[key]}" for key, label in labels if key in ingest]
        head.add_row("capture (ingest)", ", ".join(parts))
    for key, value in s.get("alignment", {}).items():
        if isinstance(value, dict):
            nonzero = {k: v for k, v in value.items() if v}
            total = sum(v for v in value.values() if isinstance(v, (int, float)))
            detail = ", ".join(f"{k}: {v}" for k, v in nonzero.items()) if nonzero else ""
            text = f"{total}" + (f" ({detail})" if detail and key != "messages" else "")
        else:
            text = str(value)
        head.add_row(f"alignment.{key}", text)
    console.print(head)
    topics = Table(title="topics")
    for col in ("topic", "schema", "encoding", "messages"):
        topics.add_column(col)
    for t in s.get("topics", []):
        topics.add_row(
            t["topic"], str(t.get("schema")), t["message_encoding"], str(t["message_count"])
        )
    console.print(topics)
    array = s.get("array")
    if array:
        source = "metadata" if s.get("array_from_metadata") else "inferred"
        console.print(
            f"array ({source}): {len(array['imu'])} IMUs, noise "
            + (json.dumps(array.get("noise")) if array.get("noise") else "not given")
            + (", per-IMU calibration" if any(_has_cal(imu) for imu in array["imu"]) else "")
            + (f", range {json.dumps(array['range'])}" if array.get("range") else "")
        )
    for sensor_type, counts in s.get("validity", {}).items():
        console.print(
            f"{sensor_type}: {counts.get('clipped', 0)} clipped and {counts.get('invalid', 0)}"
            f" invalid of {counts.get('rows', 0)} samples (at ingest)"
        )
    for fault in s.get("faults", []):
        console.print(f"fault {fault.get('id', '')}: {fault.get('spec') or fault}")
    for name, det in s.get("detectors", {}).items():
        console.print(f"detector {name}: {json.dumps(det.get('params', {}))}")
        for sensor_type, counts in det.get("validity", {}).items():
            console.print(
                f"  {sensor_type}: {counts.get('clipped', 0)} clipped, {counts.get('invalid', 0)}"
                f" invalid samples excluded from the tests"
            )
    _warn(console, s.get("warnings", []))


# --- inject ----------------------------------------------------------------------------


@cli.command()
@click.argument("source", metavar="IN")
@click.option("-o", "--output", help="Output MCAP (default: IN-faults.mcap), - for stdout.")
@click.option(
    "--fault",
    "faults",
    multiple=True,
    help="Fault spec, e.g. step:imu0.gyro.x,at=2.5s,amp=0.9deg/s.",
)
@click.option("--faults", "fault_files", multiple=True, help="TOML file of [[fault]] tables.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed for random faults.")
@_topic_option
@_stamps_option
def inject(
    source: str,
    output: str | None,
    faults: tuple[str, ...],
    fault_files: tuple[str, ...],
    seed: int,
    topics: tuple[str, ...],
    stamps: str,
) -> None:
    """Inject faults into a log and record their ground truth.

    Models: step, drift, noise, stuck, scale, spikes; on one axis (imu3.gyro.z) or a
    triad (imu3.gyro). Times are seconds from the start of the log.

    Example:


    \b
        imufdi inject run.mcap --fault step:imu0.gyro.x,at=2.5s,amp=0.9deg/s -o faulty.mcap
        imufdi inject run.mcap --fault drift:imu1.accel.z,at=3s,until=8s,rate=0.01g/s -o -
    """
    from imufdi_cli.errors import FaultSpecError
    from imufdi_cli.faults import inject_file
    from imufdi_cli.fileio import check_input, check_outputs, default_output

    check_input(source)
    if not faults and not fault_files:
        raise FaultSpecError("no fault given; use --fault SPEC or --faults FILE.toml")
    output = output or default_output(source, "faults")
    check_outputs([source, *fault_files], [("-o", output)])
    result = inject_file(
        source,
        output,
        list(faults),
        list(fault_files),
        seed=seed,
        topics=list(topics) or None,
        time_source=_time_source(stamps),
    )
    console = _console(output != "-")
    for fault in result.faults:
        console.print(f"injected {fault.spec}")
    console.print(f"-> {output}")
    _warn(console, result.warnings)


# --- detect ----------------------------------------------------------------------------


@cli.command()
@click.argument("source", metavar="IN")
@click.option("-o", "--output", help="Annotated MCAP (default: IN-detect.mcap), - for stdout.")
@click.option(
    "-d",
    "--detector",
    "detectors",
    multiple=True,
    required=True,
    type=click.Choice(sorted(DETECTORS)),
    help="Detector to run (repeatable).",
)
@click.option("--param", "params", multiple=True, help="DETECTOR.KEY=VALUE, e.g. glt.alpha=0.001.")
@click.option(
    "--calibrate",
    default="0s:2s",
    show_default=True,
    help="Fault-free calibration window START:END, seconds from the log start.",
)
@_topic_option
@_stamps_option
@click.option(
    "--strict",
    is_flag=True,
    help="A truncated or corrupt input, or a calibration window a detector finds inadequate,"
    " is an error (exit 3) instead of a warning.",
)
@click.option(
    "--array",
    "array_path",
    help="ArrayConfig TOML (geometry, per-IMU calibration, range) replacing the log's.",
)
@click.option("--start", help="Test samples from this time, seconds from the log start (e.g. 30s).")
@click.option("--end", help="Test samples before this time, seconds from the log start.")
@click.option(
    "--explain/--no-explain",
    default=True,
    show_default=True,
    help="Write an explained episode event (fault class, size with interval) per alarm episode.",
)
def detect(
    source: str,
    output: str | None,
    detectors: tuple[str, ...],
    params: tuple[str, ...],
    calibrate: str,
    topics: tuple[str, ...],
    stamps: str,
    strict: bool,
    array_path: str | None,
    start: str | None,
    end: str | None,
    explain: bool,
) -> None:
    """Run detectors and write an annotated MCAP (status channels, alarm events).

    Example:


    \b
        imufdi detect faulty.mcap -d glt -d woa-mvmd-glt --param glt.alpha=0.001 -o out.mcap
        imufdi detect - -d glt -o - < faulty.mcap | imufdi report -
        imufdi detect real.mcap -d glt --array array.toml --calibrate 0s:10s --start 10s -o out.mcap
    """
    from imufdi_cli.array import ArrayConfig
    from imufdi_cli.detect import detect_file, parse_detector_params
    from imufdi_cli.fileio import check_input, check_outputs, default_output

    check_input(source)
    grouped = parse_detector_params(detectors, params)
    window = _time_range(calibrate, "--calibrate")
    assert window is not None
    tested = _start_end(start, end)
    array = ArrayConfig.load(array_path) if array_path else None
    output = output or default_output(source, "detect")
    # parameter files (e.g. woa-mvmd-glt.params=tuned.json) are inputs too
    param_files = [p.split("=", 1)[1] for p in params if "=" in p]
    check_outputs([source, *(f for f in param_files if os.path.isfile(f))], [("-o", output)])
    result = detect_file(
        source,
        output,
        grouped,
        calibrate=window,
        topics=list(topics) or None,
        strict=strict,
        array=array,
        window=tested,
        time_source=_time_source(stamps),
        explain=explain,
    )
    console = _console(output != "-")
    table = Table(title=f"detect: {result.samples} samples, {result.duration_s:.3g} s -> {output}")
    columns = ("detector", "sensor", "alarm %", "events", "isolated (alarm samples)", "episodes")
    for col in columns:
        table.add_column(col)
    for name, per_type in result.summaries.items():
        for sensor_type, s in per_type.items():
            top = sorted(s.isolated.items(), key=lambda kv: -kv[1])[:3]
            table.add_row(
                name,
                sensor_type,
                f"{100.0 * s.alarms / max(s.samples, 1):.2f}",
                str(s.events),
                ", ".join(f"{k} ({v})" for k, v in top) or "-",
                ", ".join(f"{k} {v}" for k, v in sorted(s.episodes.items(), key=lambda kv: -kv[1]))
                or "-",
            )
    console.print(table)
    for sensor_type, counts in result.validity.items():
        if counts["clipped"] or counts["invalid"]:
            console.print(
                f"{sensor_type}: {counts['clipped']} clipped and {counts['invalid']} invalid"
                f" samples excluded from the tests ({counts['held']} without consensus)"
            )
    _warn(console, result.warnings)


# --- report ----------------------------------------------------------------------------


@cli.command()
@click.argument("log")
@click.option("--json", "json_out", help="Write the JSON report here (- for stdout).")
@click.option("--markdown", "md_out", help="Write a Markdown table here.")
@click.option("--csv", "csv_out", help="Write a CSV table here.")
@click.option("--junit", "junit_out", help="Write JUnit XML (one test case per gate).")
@click.option("--plot", "plot_out", help="Write a PNG of statistics and isolation scores.")
@click.option(
    "--episodes-csv",
    "episodes_out",
    help="Write the explained alarm episodes as CSV (docs/episodes.md).",
)
@click.option("--fail-if", "gates", multiple=True, help="Gate, e.g. 'glt.gyro.far > 0.01'.")
@click.option(
    "--persist",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Detection delay counts the first run of this many alarms; recovery needs this"
    " many quiet samples after the last alarm.",
)
@click.option(
    "--match-far",
    "match_far",
    metavar="RATE",
    help="Also report MAR, FIR and delay with each detector's threshold scaled to this"
    " out-of-sample FAR (e.g. 1% or 0.01).",
)
@click.option(
    "--roc",
    "roc_out",
    metavar="FILE",
    help="Write the threshold sweep (FAR, MAR, FIR, delay per scale) as CSV; with --plot"
    " also FILE's name with .png.",
)
@click.option("--start", help="Score samples from this time, seconds from the log start.")
@click.option("--end", help="Score samples before this time, seconds from the log start.")
def report(
    log: str,
    json_out: str | None,
    md_out: str | None,
    csv_out: str | None,
    junit_out: str | None,
    plot_out: str | None,
    episodes_out: str | None,
    gates: tuple[str, ...],
    persist: int,
    match_far: str | None,
    roc_out: str | None,
    start: str | None,
    end: str | None,
) -> None:
    """Metrics per detector and sensor type: FAR, MAR, accuracy, FIR, delays.

    FAR counts samples outside the calibration window; delays are at decision time.
    --match-far compares detectors at one false-alarm rate (docs/metrics.md).
    --fail-if gates exit with code 1 when any fails (CI regression on recorded data).

    Example:


    \b
        imufdi report out.mcap --markdown table.md --fail-if 'glt.gyro.far > 0.08' --fail-if 'glt.gyro.mar > 0.35'
        imufdi report out.mcap --match-far 1% --roc roc.csv
    """
    from imufdi_cli import report as rep
    from imufdi_cli.fileio import atomic_path, check_input, check_outputs, write_text

    target = None if match_far is None else rep.parse_far(match_far)
    check_input(log)
    check_outputs(
        [log],
        [
            ("--json", json_out),
            ("--markdown", md_out),
            ("--csv", csv_out),
            ("--junit", junit_out),
            ("--plot", plot_out),
            ("--roc", roc_out),
            ("--episodes-csv", episodes_out),
        ],
    )
    parsed = [rep.parse_gate(g, DETECTORS) for g in gates]  # bad gates fail before reading
    result = rep.build_report(
        log,
        persist=persist,
        match_far=target,
        keep_series=plot_out is not None,
        keep_roc=roc_out is not None,
        window=_start_end(start, end),
    )
    gate_results = rep.evaluate_gates(result, parsed)
    stdout_taken = "-" in (json_out, md_out, csv_out, junit_out, roc_out, episodes_out)
    console = _console(not stdout_taken)
    table = Table(title=f"imufdi report: {result.source}")
    table.add_column("detector")
    table.add_column("sensor")
    for _, header, _, _ in rep.table_columns(result, console=True):
        table.add_column(header, justify="right")
    for row in rep.table_rows(result, console=True):
        table.add_row(*row)
    console.print(table)
    _print_episodes(console, result)
    for note in result.notes:
        console.print(f"[yellow]note:[/] {note}", markup=True)
    if episodes_out:
        write_text(episodes_out, rep.to_episodes_csv(result))
    if json_out:
        write_text(json_out, rep.to_json(result, gate_results))
    if md_out:
        write_text(md_out, rep.to_markdown(result, gate_results))
    if csv_out:
        write_text(csv_out, rep.to_csv(result))
    if junit_out:
        write_text(junit_out, rep.to_junit(result, gate_results))
    if roc_out:
        write_text(roc_out, rep.to_roc_csv(result))
    if plot_out:
        with atomic_path(plot_out, suffix=".png") as tmp:  # matplotlib wants the extension
            rep.plot_report(result, tmp)
        if roc_out and roc_out != "-":
            png = os.path.splitext(roc_out)[0] + ".png"
            with atomic_path(png, suffix=".png") as tmp:
                rep.plot_roc(result, tmp)
    failed = [r for r in gate_results if r.failed]
    for r in gate_results:
        style = "red" if r.failed else "green"
        console.print(f"[{style}]gate {r.message}[/]", markup=True)
    if failed:
        _err(
            f"{len(failed)} of {len(gate_results)} gate(s) failed: "
            + "; ".join(r.target for r in failed)
        )
        sys.exit(EXIT_GATE_FAILED)


# --- calibrate -------------------------------------------------------------------------


@cli.command()
@click.argument("source", metavar="IN")
@click.option("-o", "--output", required=True, help="ArrayConfig TOML to write, - for stdout.")
@click.option("--start", help="Use samples from this time, seconds from the log start.")
@click.option("--end", help="Use samples before this time, seconds from the log start.")
@click.option("--array", "array_path", help="Base ArrayConfig TOML (geometry); default: the log's.")
@click.option(
    "--gravity", default="9.80665m/s^2", show_default=True, help="|f| at rest (local gravity)."
)
@click.option(
    "--min-static", default="5s", show_default=True, help="Shortest static interval used."
)
@click.option("--topic", "topics", multiple=True, help="Imu topics to use, in array order.")
@click.option("--json", "as_json", is_flag=True, help="Print the figures as JSON.")
def calibrate(
    source: str,
    output: str,
    start: str | None,
    end: str | None,
    array_path: str | None,
    gravity: str,
    min_static: str,
    topics: tuple[str, ...],
    as_json: bool,
) -> None:
    """Per-IMU calibration (M, b of every triad) from static orientations and motion.

    Finds the static intervals, groups them by orientation, fits each accelerometer so
    all triads agree and |f| = g, each gyro bias at rest and its matrix from motion
    relative to the array consensus; writes the ArrayConfig with the calibration for
    `ingest --array` / `detect --array` (docs/real-arrays.md).

    Example:


    \b
        imufdi calibrate board.mcap --array board.toml -o board-calibrated.toml
        imufdi detect other.mcap -d glt --array board-calibrated.toml --calibrate 0s:10s -o out.mcap
    """
    from imufdi_cli.array import ArrayConfig
    from imufdi_cli.calibrate import calibrate_file
    from imufdi_cli.fileio import check_input, check_outputs, write_text
    from imufdi_cli.units import parse_quantity

    check_input(source)
    check_outputs([source, array_path], [("-o", output)])
    window = _start_end(start, end)
    base = ArrayConfig.load(array_path) if array_path else None
    result = calibrate_file(
        source,
        window=window,
        base=base,
        gravity=parse_quantity(gravity, "acceleration", name="--gravity"),
        min_static_s=parse_quantity(min_static, "time", name="--min-static"),
        topics=list(topics) or None,
    )
    write_text(output, result.array.to_toml())
    console = _console(output != "-")
    if as_json:
        console.print_json(json.dumps(result.to_dict()))
        _warn(console, result.warnings)
        return
    places = ", ".join(f"{i.start_s:.0f}-{i.end_s:.0f}s" for i in result.intervals)
    console.print(
        f"{len(result.intervals)} static intervals ({result.static_s:.0f} s: {places}),"
        f" {result.orientations} orientations, direction coverage {result.coverage:.2f};"
        f" motion {result.motion_s:.0f} s; {result.clipped_rows} clipped/invalid rows unused"
    )
    table = Table(title=f"calibrate: {source} -> {output}")
    for col in ("imu", "sensor", "scale ppm (x y z)", "misalign. mrad", "bias (x y z)"):
        table.add_column(col)
    for f in result.figures:
        unit, factor = ("deg/s", 57.29577951308232) if f.sensor_type == "gyro" else ("m/s^2", 1.0)
        table.add_row(
            f"imu{f.imu}",
            f.sensor_type,
            " ".join(f"{v:+.0f}" for v in f.scale_ppm),
            f"{f.misalignment_mrad:.2f}",
            " ".join(f"{v * factor:+.4f}" for v in f.bias) + f" {unit}",
        )
    console.print(table)
    for sensor_type, (before, after) in result.residual_rms.items():
        where = "at rest (interval means)" if sensor_type == "accel" else "in motion"
        unit, factor = ("deg/s", 57.29577951308232) if sensor_type == "gyro" else ("m/s^2", 1.0)
        console.print(
            f"{sensor_type}: RMS between triads {where}: {before * factor:.4g} -> "
            f"{after * factor:.4g} {unit}"
        )
    console.print(f"runtime {result.runtime_s:.2f} s")
    _warn(console, result.warnings)


def _print_episodes(console: Console, result: Any, limit: int = 12) -> None:
    """The episode figures per detector and type, and the strongest episodes."""
    from imufdi_cli import report as rep

    if not result.episode_scores:
        return
    table = Table(title="alarm episodes (docs/episodes.md)")
    for col in ("detector.type", "episodes", "false / h", "class right %", "covered %"):
        table.add_column(col, justify="right")
    for key, score in result.episode_scores.items():
        table.add_row(
            key,
            str(score["episodes"]),
            rep.format_value(score.get("false_episodes_per_hour"), 1.0, "{:.3g}"),
            rep.format_value(score.get("class_accuracy"), 100.0, "{:.1f}"),
            rep.format_value(score.get("coverage"), 100.0, "{:.1f}"),
        )
    console.print(table)
    rows = sorted(rep.episode_rows(result), key=lambda r: -(r["peak_ratio"] or 0.0))[:limit]
    detail = Table(title=f"strongest {len(rows)} episodes")
    for col in (
        "detector",
        "start s",
        "dur s",
        "sensor",
        "class",
        "size [90 %]",
        "runner-up",
        "peak",
        "match",
    ):
        detail.add_column(col)
    for r in rows:
        detail.add_row(
            f"{r['detector']}.{r['sensor_type']}",
            f"{r['start_s']:.2f}",
            rep.format_value(r["duration_s"], 1.0, "{:.2f}"),
            r["sensor"] or "-",
            r["fault_class"] or "-",
            r["size"],
            r["runner_up_class"] or "-",
            rep.format_value(r["peak_ratio"], 1.0, "{:.3g}"),
            r["match"] or "-",
        )
    console.print(detail)


# --- tune ------------------------------------------------------------------------------


@cli.command()
@click.argument("log")
@click.option(
    "--segment", default="0s:2.5s", show_default=True, help="Fault-free segment START:END."
)
@click.option(
    "--sensor",
    "sensor_type",
    default="gyro",
    show_default=True,
    type=click.Choice(["gyro", "accel"]),
)
@click.option("-o", "--output", default="-", show_default=True, help="Tuned parameters JSON.")
@click.option(
    "--param", "params", multiple=True, help="WOA setting KEY=VALUE (population, iterations, ...)."
)
@click.option("--seed", type=int, default=0, show_default=True)
def tune(
    log: str,
    segment: str,
    sensor_type: str,
    output: str,
    params: tuple[str, ...],
    seed: int,
) -> None:
    """Choose MVMD (K, alpha) for woa-mvmd-glt with the whale optimisation algorithm.

    Example:


    \b
        imufdi tune run.mcap --segment 0s:2.5s -o params.json
        imufdi detect run.mcap -d woa-mvmd-glt --param woa-mvmd-glt.params=params.json -o out.mcap
    """
    from imufdi_cli.fileio import check_input, check_outputs, write_text
    from imufdi_cli.pipeline import tune_file

    check_input(log)
    check_outputs([log], [("-o", output)])
    window = _time_range(segment, "--segment")
    assert window is not None
    settings = {}
    for item in params:
        if "=" not in item:
            raise UnitError(f"--param {item!r} is not KEY=VALUE")
        key, value = item.split("=", 1)
        settings[key.strip()] = value.strip()
    result = tune_file(log, window, sensor_type=sensor_type, seed=seed, settings=settings)
    console = _console(output != "-")
    table = Table(title="WOA convergence (best CFV per iteration)")
    table.add_column("iteration", justify="right")
    table.add_column("best fitness", justify="right")
    for i, value in enumerate(result.curve):
        table.add_row(str(i + 1), f"{value:.6g}")
    console.print(table)
    console.print(f"K = {result.K}, alpha = {result.alpha:.6g}, fitness = {result.fitness:.6g}")
    write_text(output, result.to_json())


# --- campaign --------------------------------------------------------------------------


@cli.command()
@click.argument("spec")
@click.option("-o", "--output", "results_dir", required=True, help="Results directory.")
@click.option("--jobs", type=click.IntRange(min=1), help="Worker processes (default: all cores).")
@click.option("--scheduler", help="dask scheduler: tcp://HOST:PORT or local:N.")
@click.option(
    "--resume", is_flag=True, help="Skip runs whose results are already in the directory."
)
@click.option(
    "--fail-if", "gates", multiple=True, help="Gate on the summary, e.g. 'glt.gyro.far > 0.08'."
)
def campaign(
    spec: str,
    results_dir: str,
    jobs: int | None,
    scheduler: str | None,
    resume: bool,
    gates: tuple[str, ...],
) -> None:
    """Run a fault-injection campaign: inject + detect + report over a matrix, in parallel.

    Example:


    \b
        imufdi campaign docs/campaigns/compare.toml -o results/ --jobs 2
        imufdi campaign spec.toml -o results/ --scheduler tcp://10.0.0.5:8786 --resume
    """
    from imufdi_cli.campaign import run_campaign_cli

    code = run_campaign_cli(
        spec,
        results_dir,
        jobs=jobs,
        scheduler=scheduler,
        resume=resume,
        gates=list(gates),
        console=_console(True),
    )
    if code:
        sys.exit(code)


# --- demo ------------------------------------------------------------------------------


@cli.command()
@click.option("--keep", "keep_dir", help="Keep the outputs in this directory.")
def demo(keep_dir: str | None) -> None:
    """Run the whole pipeline on the bundled sample log and print what it did.

    Example:


    \b
        imufdi demo
        imufdi demo --keep demo_out/
    """
    from imufdi_cli.pipeline import run_demo

    console = _console(True)
    run_demo(keep_dir, console=console)


# --- entry point -----------------------------------------------------------------------


class Terminated(BaseException):
    """SIGTERM/SIGHUP (or SIGINT) turned into an exception, so that every ``with`` block
    unwinds: atomic outputs remove their temporary files, worker pools shut down.

    A BaseException, so that library code catching ``Exception`` (a campaign recording a
    failed run) does not swallow it.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


#: Signals that stop the CLI cleanly (exit 128 + signal number).
HANDLED_SIGNALS = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)


@contextmanager
def _signals_as_exceptions() -> Iterator[None]:
    """Install handlers raising :class:`Terminated` (the first signal only: further
    signals while cleaning up are ignored so the cleanup completes); restore on exit.
    A signal that is already ignored (``nohup`` ignores SIGHUP) stays ignored."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    raised = False

    def handler(signum: int, frame: Any) -> None:
        nonlocal raised
        if raised:
            return
        raised = True
        raise Terminated(signum)

    previous = {}
    for signum in HANDLED_SIGNALS:
        try:
            if signal.getsignal(signum) == signal.SIG_IGN:
                continue  # ignored by whoever started us (nohup, a background job): keep it
            previous[signum] = signal.signal(signum, handler)
        except (OSError, ValueError):  # pragma: no cover - platform without the signal
            continue
    try:
        yield
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)


def describe_exception(err: BaseException) -> str:
    """One non-empty line for an unexpected exception: its class and what it says."""
    text = " ".join(str(err).split())
    name = type(err).__name__
    if isinstance(err, MemoryError):
        return (
            "out of memory"
            + (f" ({text})" if text else "")
            + "; the input may declare sizes larger than it holds, or need more memory than"
            " this machine has"
        )
    if isinstance(err, OSError):
        reason = err.strerror or text or name
        where = err.filename if err.filename is not None else None
        return f"{where}: {reason}" if where is not None else f"{name}: {reason}"
    return f"{name}: {text}" if text else f"{name} (no message)"


def _debug() -> bool:
    return os.environ.get("IMUFDI_DEBUG", "") not in ("", "0")


def main(argv: Sequence[str] | None = None) -> None:
    """Console script: run the CLI, turning every error into one line and an exit code."""
    try:
        with _signals_as_exceptions():
            code = cli.main(
                args=list(argv) if argv is not None else None,
                prog_name="imufdi",
                standalone_mode=False,
            )
    except ImufdiError as err:
        if _debug():
            traceback.print_exc()
        _err(str(err) or type(err).__name__)
        sys.exit(err.exit_code)
    except Terminated as err:
        name = signal.Signals(err.signum).name
        _err("interrupted" if name == "SIGINT" else f"terminated by {name}")
        sys.exit(err.exit_code)
    except click.exceptions.Abort:
        _err("aborted")
        sys.exit(130)
    except click.ClickException as err:
        _err(" ".join(err.format_message().split()) or type(err).__name__)
        sys.exit(EXIT_USAGE if err.exit_code == 2 else err.exit_code)
    except KeyboardInterrupt:
        _err("interrupted")
        sys.exit(130)
    except BrokenPipeError:
        # the reader of our stdout went away (e.g. `| head`): not an error of ours
        try:
            sys.stdout = open(os.devnull, "w")
        finally:
            sys.exit(0)
    except (MemoryError, OSError) as err:
        if _debug():
            traceback.print_exc()
        _err(describe_exception(err))
        sys.exit(EXIT_BAD_INPUT)
    except Exception as err:  # a bug: one line, and the traceback only on request
        if _debug():
            traceback.print_exc()
        _err(
            f"internal error ({describe_exception(err)}); "
            "please report it with the output of IMUFDI_DEBUG=1"
        )
        sys.exit(EXIT_INTERNAL)
    sys.exit(code if isinstance(code, int) else 0)
