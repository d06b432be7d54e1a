"""Commands that make logs: ``simulate``, ``ingest``, ``inject``."""

from __future__ import annotations

import os
from typing import Any

import click

from imufdi_cli.cli.app import cli, complete_file, stamps_option, time_source, topic_option
from imufdi_cli.cli.choices import LazyChoice, motions, presets
from imufdi_cli.cli.plain import PlainTable
from imufdi_cli.cli.ui import UI, common_options

# --- simulate --------------------------------------------------------------------------


@cli.command()
@click.option(
    "--preset",
    "preset_name",
    type=LazyChoice(presets),
    help="Reference scenario (docs/simulate.md).",
)
@click.option("--imus", type=int, help="Number of IMUs (free simulation or preset override).")
@click.option("--rate", help="Sample rate, e.g. 100Hz, 1kHz.")
@click.option("--duration", help="Log length, e.g. 5s, 1h.")
@click.option("--motion", type=LazyChoice(motions), help="Motion of the array.")
@click.option("--gyro-noise", help="Gyro white noise sigma, e.g. 0.15deg/s.")
@click.option("--accel-noise", help="Accel white noise sigma, e.g. 0.02m/s^2.")
@click.option("--outliers/--no-outliers", default=None, help="Gyro outliers on or off.")
@click.option("--chip-bias", help="Constant chip-to-chip gyro bias sigma, e.g. 0.5deg/s.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@click.option(
    "-o",
    "--output",
    required=True,
    help="Output MCAP, or - for stdout.",
    shell_complete=complete_file,
)
@click.option(
    "--capture",
    "capture",
    help="Also write a raw serial capture (mpu6500-array).",
    shell_complete=complete_file,
)
@click.option(
    "--corrupt/--no-corrupt",
    default=False,
    help="With --capture: add a few corrupted stretches (garbage, bad CRC, cut and lost frames).",
)
@common_options(json_help="Summary: samples, IMUs, rate, duration, outputs.")
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
    ui: UI,
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

    ui.data_to_stdout(output, capture, labels=("-o", "--capture"))
    check_outputs([], [("-o", output), ("--capture", capture), ("--json", ui.json_target)])
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
    ui.summary.print(
        f"simulate: {result.samples} samples of {result.n_imus} IMUs "
        f"({result.duration_s:g} s at {result.rate_hz:g} Hz) -> {output}"
    )
    if capture:
        ui.summary.print(f"raw capture -> {capture} ({result.capture_bytes} bytes)")
    ui.json(
        {
            "command": "simulate",
            "preset": preset_name,
            "seed": seed,
            "output": output,
            "samples": result.samples,
            "n_imus": result.n_imus,
            "duration_s": result.duration_s,
            "rate_hz": result.rate_hz,
            "capture": capture,
            "capture_bytes": result.capture_bytes if capture else None,
        }
    )


# --- ingest ----------------------------------------------------------------------------


@cli.command()
@click.argument("capture", shell_complete=complete_file)
@click.option(
    "-o",
    "--output",
    help="Output MCAP (default: CAPTURE with .mcap), - for stdout.",
    shell_complete=complete_file,
)
@click.option(
    "--layout",
    help="Frame layout of a raw capture: mpu6500-array (default), csv, or a TOML layout file."
    " PX4 ULog and ArduPilot DataFlash logs are recognised by content and need none.",
    shell_complete=complete_file,
)
@click.option(
    "--imu-data",
    type=click.Choice(["auto", "sensor", "vehicle_imu", "imu", "raw"]),
    help="Flight-controller logs: which IMU data (PX4: sensor, vehicle_imu; ArduPilot: imu,"
    " raw). Default auto: the most IMUs, then sensor types, then the highest rate"
    " (docs/flight-controllers.md).",
)
@click.option(
    "--array",
    "array_path",
    help="ArrayConfig TOML (rotations, positions, axes).",
    shell_complete=complete_file,
)
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
@common_options(json_help="Summary: the frame, byte and gap counts.")
def ingest(
    capture: str,
    output: str | None,
    layout: str | None,
    imu_data: str | None,
    array_path: str | None,
    rate: str | None,
    gyro_fs: str | None,
    accel_fs: str | None,
    strict: bool,
    start_time: str | None,
    ui: UI,
) -> None:
    """Convert a raw serial capture (or CSV), or a PX4 ULog / ArduPilot DataFlash flight
    log, into an IMU array MCAP.

    Captures: resynchronises after garbage, drops frames with bad checksums, unwraps
    counters and timestamps, counts every dropped byte, frame and gap. Flight logs
    (recognised by content, whatever the extension): one Imu channel per IMU instance,
    aligned without resampling, stamped in UTC from the log's GPS time.

    Example:


    \b
        imufdi ingest board.bin --layout my_board.toml --array array.toml -o board.mcap
        imufdi ingest flight.ulg -o flight.mcap
        cat capture.bin | imufdi ingest - -o - | imufdi info -
    """
    from imufdi_cli.fileio import check_input, check_outputs
    from imufdi_cli.pipeline import ingest_file

    check_input(capture)
    if output is None:
        output = "-" if capture == "-" else os.path.splitext(capture)[0] + ".mcap"
    ui.data_to_stdout(output)
    layout_file = layout if layout is not None and layout.lower().endswith(".toml") else None
    check_outputs([capture, layout_file, array_path], [("-o", output), ("--json", ui.json_target)])
    with ui.progress(f"ingest {capture}", unit="B") as progress:
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
            imu_data=imu_data,
            progress=progress,
        )
    ui.print_table(ingest_table(capture, output, stats.as_rows()), summary=True)
    ui.warn(getattr(stats, "warnings", []))
    ui.json({"command": "ingest", "capture": capture, "output": output, **stats.to_dict()})


def ingest_table(capture: str, output: str, rows: Any) -> PlainTable:
    """``imufdi ingest``'s summary table of ``(count, value)`` rows (frames, losses...)."""
    table = PlainTable(
        ("count", "value"), title=f"ingest: {capture} -> {output}", justify=("left", "right")
    )
    for key, value in rows:
        table.add_row(key, str(value))
    return table


# --- inject ----------------------------------------------------------------------------


@cli.command()
@click.argument("source", metavar="IN", shell_complete=complete_file)
@click.option(
    "-o",
    "--output",
    help="Output MCAP (default: IN-faults.mcap), - for stdout.",
    shell_complete=complete_file,
)
@click.option(
    "--fault",
    "faults",
    multiple=True,
    help="Fault spec, e.g. step:imu0.gyro.x,at=2.5s,amp=0.9deg/s.",
)
@click.option(
    "--faults",
    "fault_files",
    multiple=True,
    help="TOML file of [[fault]] tables.",
    shell_complete=complete_file,
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed for random faults.")
@topic_option
@stamps_option
@common_options(json_help="Summary: the injected faults, output and warnings.")
def inject(
    source: str,
    output: str | None,
    faults: tuple[str, ...],
    fault_files: tuple[str, ...],
    seed: int,
    topics: tuple[str, ...],
    stamps: str,
    ui: UI,
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
    output = default_output(source, "faults") if output is None else output
    ui.data_to_stdout(output)
    check_outputs([source, *fault_files], [("-o", output), ("--json", ui.json_target)])
    with ui.progress(f"inject {source} (2 passes)") as progress:
        result = inject_file(
            source,
            output,
            list(faults),
            list(fault_files),
            seed=seed,
            topics=list(topics) or None,
            time_source=time_source(stamps),
            progress=progress,
        )
    for fault in result.faults:
        ui.summary.print(f"inject: {fault.spec}")
    ui.summary.print(f"inject: -> {output}")
    ui.warn(result.warnings)
    ui.json(
        {
            "command": "inject",
            "source": source,
            "output": output,
            "seed": result.seed,
            "faults": [fault.to_dict() for fault in result.faults],
            "warnings": list(result.warnings),
        }
    )
