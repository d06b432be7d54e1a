"""Commands that run the maths: ``detect``, ``tune``, ``calibrate``."""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from typing import Any

import click

from imufdi_cli.cli.app import (
    TIME_POINT_HELP,
    cli,
    complete_file,
    stamps_option,
    start_end,
    time_range,
    time_source,
    topic_option,
)
from imufdi_cli.cli.choices import LazyChoice, detectors
from imufdi_cli.cli.plain import PlainTable
from imufdi_cli.cli.ui import UI, common_options

# --- detect ----------------------------------------------------------------------------


def false_alarm_rate(text: str) -> float:
    """``--false-alarms`` in episodes per second (``1/h``, ``0.1/h``, ``5/min``)."""
    from imufdi_cli.errors import UnitError, UsageError
    from imufdi_cli.units import parse_quantity

    try:
        value = parse_quantity(text, "frequency", name="--false-alarms")
    except UnitError as err:
        raise UsageError(str(err)) from None
    if value < 0:
        raise UsageError(f"--false-alarms must be >= 0 (e.g. 1/h), got {text!r}")
    return value


@cli.command()
@click.argument("source", metavar="IN", shell_complete=complete_file)
@click.option(
    "-o",
    "--output",
    help="Annotated MCAP (default: IN-detect.mcap), - for stdout.",
    shell_complete=complete_file,
)
@click.option(
    "-d",
    "--detector",
    "detector_names",
    multiple=True,
    required=True,
    type=LazyChoice(detectors),
    help="Detector to run (repeatable).",
)
@click.option("--param", "params", multiple=True, help="DETECTOR.KEY=VALUE, e.g. glt.alpha=0.001.")
@click.option(
    "--false-alarms",
    "false_alarms",
    metavar="RATE",
    help="False-alarm budget per status channel, e.g. 1/h: every detector decides"
    " sequentially so that fault-free data raise at most RATE false alarm episodes."
    " Default: the papers' per-sample tests at each detector's alpha.",
)
@click.option(
    "--calibrate",
    default="0s:2s",
    show_default=True,
    help="Fault-free calibration window START:END, seconds from the log start.",
)
@topic_option
@stamps_option
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
    shell_complete=complete_file,
)
@click.option("--start", help=f"Test samples from this time: {TIME_POINT_HELP}.")
@click.option("--end", help="Test samples before this time (the same forms as --start).")
@click.option(
    "--explain/--no-explain",
    default=True,
    show_default=True,
    help="Write an explained episode event (fault class, size with interval) per alarm episode.",
)
@click.option(
    "--named-scores/--no-named-scores",
    default=False,
    show_default=True,
    help="Also write the per-sensor scores under the sensors' names"
    " (/imufdi/DETECTOR/TYPE/scores) for Foxglove and PlotJuggler (about 40 % larger"
    " files for a 16-IMU array).",
)
@common_options(json_help="Summary: alarms, events, isolations and episodes per detector.")
def detect(
    source: str,
    output: str | None,
    detector_names: tuple[str, ...],
    params: tuple[str, ...],
    false_alarms: str | None,
    calibrate: str,
    topics: tuple[str, ...],
    stamps: str,
    strict: bool,
    array_path: str | None,
    start: str | None,
    end: str | None,
    explain: bool,
    named_scores: bool,
    ui: UI,
) -> None:
    """Run detectors and write an annotated MCAP (status channels, alarm events).

    Example:


    \b
        imufdi detect faulty.mcap -d glt -d woa-mvmd-glt --param glt.alpha=0.001 -o out.mcap
        imufdi detect recorded.mcap -d glt -d pca-parity --false-alarms 1/h -o out.mcap
        imufdi detect - -d glt -o - < faulty.mcap | imufdi report -
        imufdi detect real.mcap -d glt --array array.toml --calibrate 0s:10s --start 10s -o out.mcap
    """
    from imufdi_cli.array import ArrayConfig
    from imufdi_cli.detect import detect_file
    from imufdi_cli.fileio import check_input, check_outputs, default_output

    check_input(source)
    grouped = parse_detector_params(detector_names, params)
    budget = None if false_alarms is None else false_alarm_rate(false_alarms)
    window = time_range(calibrate, "--calibrate")
    tested = start_end(start, end)
    output = default_output(source, "detect") if output is None else output
    ui.data_to_stdout(output)
    # parameter files (e.g. woa-mvmd-glt.params=tuned.json) are inputs too
    param_files = [p.split("=", 1)[1] for p in params if "=" in p]
    check_outputs(
        [source, array_path, *(f for f in param_files if os.path.isfile(f))],
        [("-o", output), ("--json", ui.json_target)],
    )
    array = ArrayConfig.load(array_path) if array_path else None
    with ui.progress(f"detect {source}") as progress:
        result = detect_file(
            source,
            output,
            grouped,
            calibrate=window,
            topics=list(topics) or None,
            strict=strict,
            array=array,
            window=tested,
            time_source=time_source(stamps),
            explain=explain,
            progress=progress,
            false_alarms=budget,
            named_scores=named_scores,
        )
    ui.print_table(detect_table(result, output, shown=None if ui.verbose else 3), summary=True)
    per_detector: dict[str, Any] = {}
    for name, per_type in result.summaries.items():
        for sensor_type, s in per_type.items():
            per_detector.setdefault(name, {})[sensor_type] = {
                "samples": s.samples,
                "alarms": s.alarms,
                "alarm_rate": s.alarms / s.samples if s.samples else None,
                "events": s.events,
                "isolated": dict(_ranked(s.isolated)),
                "episodes": dict(s.episodes),
            }
    for sensor_type, counts in result.validity.items():
        if counts["clipped"] or counts["invalid"]:
            ui.summary.print(
                f"{sensor_type}: {counts['clipped']} clipped and {counts['invalid']} invalid"
                f" samples excluded from the tests ({counts['held']} without consensus)"
            )
        if counts.get("missing"):
            ui.summary.print(
                f"{sensor_type}: {counts['missing']} samples tested with an IMU missing (its"
                " sensors replaced by the others' consensus)"
            )
    ui.warn(result.warnings)
    ui.json(
        {
            "command": "detect",
            "source": source,
            "output": output,
            "samples": result.samples,
            "duration_s": result.duration_s,
            "detectors": per_detector,
            "validity": result.validity,
            "warnings": list(result.warnings),
        }
    )


def _ranked(counts: dict[str, int]) -> list[tuple[str, int]]:
    """``counts`` items, largest first (ties in their order)."""
    return sorted(counts.items(), key=lambda kv: -kv[1])


def detect_table(result: Any, output: str, shown: int | None = 3) -> PlainTable:
    """``imufdi detect``'s summary table: per detector and sensor type, the alarm rate,
    events, the ``shown`` sensors isolated most often (all with None) and the episodes."""
    table = PlainTable(
        ("detector", "sensor", "alarm %", "events", "isolated (alarm samples)", "episodes"),
        title=f"detect: {result.samples} samples, {result.duration_s:.3g} s -> {output}",
    )
    for name, per_type in result.summaries.items():
        for sensor_type, s in per_type.items():
            table.add_row(
                name,
                sensor_type,
                f"{100.0 * s.alarms / max(s.samples, 1):.2f}",
                str(s.events),
                ", ".join(f"{k} ({v})" for k, v in _ranked(s.isolated)[:shown]) or "-",
                ", ".join(f"{k} {v}" for k, v in _ranked(s.episodes)) or "-",
            )
    return table


# --- tune ------------------------------------------------------------------------------


@cli.command()
@click.argument("log", shell_complete=complete_file)
@click.option(
    "--segment", default="0s:2.5s", show_default=True, help="Fault-free segment START:END."
)
@click.option(
    "--sensor",
    "sensor_type",
    default="gyro",
    show_default=True,
    type=click.Choice(["gyro", "accel"]),
    help="Sensor type whose MVMD parameters are tuned.",
)
@click.option(
    "-o",
    "--output",
    default="-",
    show_default=True,
    help="Tuned parameters JSON.",
    shell_complete=complete_file,
)
@click.option(
    "--param", "params", multiple=True, help="WOA setting KEY=VALUE (population, iterations, ...)."
)
@click.option(
    "--seed",
    type=int,
    default=0,
    show_default=True,
    help="Seed of the whale optimisation (same seed, same result).",
)
@common_options(json_help="Summary: K, alpha, fitness and the convergence curve.")
def tune(
    log: str,
    segment: str,
    sensor_type: str,
    output: str,
    params: tuple[str, ...],
    seed: int,
    ui: UI,
) -> None:
    """Choose MVMD (K, alpha) for woa-mvmd-glt with the whale optimisation algorithm.

    Example:


    \b
        imufdi tune run.mcap --segment 0s:2.5s -o params.json
        imufdi detect run.mcap -d woa-mvmd-glt --param woa-mvmd-glt.params=params.json -o out.mcap
    """
    from imufdi_cli.errors import UnitError
    from imufdi_cli.fileio import check_input, check_outputs, write_text
    from imufdi_cli.pipeline import tune_file

    check_input(log)
    ui.data_to_stdout(output)
    check_outputs([log], [("-o", output), ("--json", ui.json_target)])
    window = time_range(segment, "--segment")
    settings = {}
    for item in params:
        if "=" not in item:
            raise UnitError(f"--param {item!r} is not KEY=VALUE")
        key, value = item.split("=", 1)
        settings[key.strip()] = value.strip()
    result = tune_file(log, window, sensor_type=sensor_type, seed=seed, settings=settings)
    if ui.verbose:
        ui.print_table(convergence_table(result.curve), summary=True)
    ui.summary.print(
        f"tune: K = {result.K}, alpha = {result.alpha:.6g}, fitness = {result.fitness:.6g}"
        f" after {len(result.curve)} iterations -> {output}"
    )
    write_text(output, result.to_json())
    ui.json(
        {
            "command": "tune",
            "source": log,
            "output": output,
            "sensor_type": sensor_type,
            "seed": seed,
            "K": result.K,
            "alpha": result.alpha,
            "fitness": result.fitness,
            "curve": list(result.curve),
        }
    )


def convergence_table(curve: Any) -> PlainTable:
    """``imufdi tune -v``'s table: the best fitness (CFV) after each WOA iteration."""
    table = PlainTable(
        ("iteration", "best fitness"),
        title="WOA convergence (best CFV per iteration)",
        justify=("right", "right"),
    )
    for i, value in enumerate(curve):
        table.add_row(str(i + 1), f"{value:.6g}")
    return table


# --- calibrate -------------------------------------------------------------------------


@cli.command()
@click.argument("source", metavar="IN", shell_complete=complete_file)
@click.option(
    "-o",
    "--output",
    required=True,
    help="ArrayConfig TOML to write, - for stdout.",
    shell_complete=complete_file,
)
@click.option("--start", help=f"Use samples from this time: {TIME_POINT_HELP}.")
@click.option("--end", help="Use samples before this time (the same forms as --start).")
@click.option(
    "--array",
    "array_path",
    help="Base ArrayConfig TOML (geometry); default: the log's.",
    shell_complete=complete_file,
)
@click.option(
    "--gravity", default="9.80665m/s^2", show_default=True, help="|f| at rest (local gravity)."
)
@click.option(
    "--min-static", default="5s", show_default=True, help="Shortest static interval used."
)
@click.option("--topic", "topics", multiple=True, help="Imu topics to use, in array order.")
@click.option(
    "--jitter-fit",
    type=click.Choice(["level", "moments", "off"]),
    default="level",
    show_default=True,
    help="Sampling-time jitter [jitter] from the motion: level (per-sample test holds 1 %"
    " there), moments (matches the mean), off.",
)
@common_options(json_help="The calibration figures (intervals, per-triad scale, bias, RMS).")
def calibrate(
    source: str,
    output: str,
    start: str | None,
    end: str | None,
    array_path: str | None,
    gravity: str,
    min_static: str,
    topics: tuple[str, ...],
    jitter_fit: str,
    ui: UI,
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
    ui.data_to_stdout(output)
    check_outputs([source, array_path], [("-o", output), ("--json", ui.json_target)])
    window = start_end(start, end)
    base = ArrayConfig.load(array_path) if array_path else None
    result = calibrate_file(
        source,
        window=window,
        base=base,
        gravity=parse_quantity(gravity, "acceleration", name="--gravity"),
        min_static_s=parse_quantity(min_static, "time", name="--min-static"),
        topics=list(topics) or None,
        jitter_fit=jitter_fit,
    )
    write_text(output, result.array.to_toml())
    ui.json(result.to_dict())
    console = ui.summary
    places = ", ".join(f"{i.start_s:.0f}-{i.end_s:.0f}s" for i in result.intervals)
    console.print(
        f"calibrate: {len(result.intervals)} static intervals ({result.static_s:.0f} s:"
        f" {places}), {result.orientations} orientations, direction coverage"
        f" {result.coverage:.2f}; motion {result.motion_s:.0f} s; {result.clipped_rows}"
        " clipped/invalid rows unused"
    )
    ui.print_table(calibrate_table(result, source, output), summary=True)
    for sensor_type, (before, after) in result.residual_rms.items():
        where = "at rest (interval means)" if sensor_type == "accel" else "in motion"
        unit, factor = ("deg/s", 57.29577951308232) if sensor_type == "gyro" else ("m/s^2", 1.0)
        console.print(
            f"{sensor_type}: RMS between triads {where}: {before * factor:.4g} -> "
            f"{after * factor:.4g} {unit}"
        )
    for sensor_type, jitter in result.jitter_s.items():
        console.print(
            f"{sensor_type}: sampling-time jitter sigma_t {jitter * 1e3:.3g} ms in motion"
            " (glt and pca-parity widen their tests by it)"
        )
    console.print(f"runtime {result.runtime_s:.2f} s")
    ui.warn(result.warnings)


def calibrate_table(result: Any, source: str, output: str) -> PlainTable:
    """``imufdi calibrate``'s table: per IMU and sensor type, the scale factors (ppm),
    misalignment (mrad) and biases (deg/s or m/s^2) of the fitted calibration."""
    table = PlainTable(
        ("imu", "sensor", "scale ppm (x y z)", "misalign. mrad", "bias (x y z)"),
        title=f"calibrate: {source} -> {output}",
    )
    for f in result.figures:
        unit, factor = ("deg/s", 57.29577951308232) if f.sensor_type == "gyro" else ("m/s^2", 1.0)
        table.add_row(
            f"imu{f.imu}",
            f.sensor_type,
            " ".join(f"{v:+.0f}" for v in f.scale_ppm),
            f"{f.misalignment_mrad:.2f}",
            " ".join(f"{v * factor:+.4f}" for v in f.bias) + f" {unit}",
        )
    return table


def parse_detector_params(
    detectors: Sequence[str], params: Iterable[str]
) -> list[tuple[str, dict[str, str]]]:
    """Group ``--param det.key=value`` strings by detector.

    Raises DetectorConfigError for a malformed item or one naming a detector not selected.
    """
    from imufdi_cli.detectors import check_selection
    from imufdi_cli.errors import DetectorConfigError

    check_selection(detectors)
    grouped: dict[str, dict[str, str]] = {name: {} for name in detectors}
    for item in params:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise DetectorConfigError(
                f"--param {item!r} is not of the form DETECTOR.KEY=VALUE (e.g. glt.alpha=0.001)"
            )
        key, value = item.split("=", 1)
        detector, name = key.split(".", 1)
        if detector not in grouped:
            raise DetectorConfigError(
                f"--param {item!r} names detector {detector!r}, which is not selected with -d"
                f" (selected: {', '.join(grouped)})"
            )
        grouped[detector][name] = value
    return list(grouped.items())
