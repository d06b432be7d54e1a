"""``imufdi demo``'s run: ingest (or simulate) -> inject -> detect -> report on the bundled
sample log, each step printed as the equivalent command line (the CLI prints; the steps
are the library's)."""

from __future__ import annotations

import shlex
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from imufdi_cli.cli.plain import PlainTable
from imufdi_cli.cli.ui import print_table
from imufdi_cli.pipeline import SAMPLE_LOGS, ingest_file

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
                # the bundled capture by its full path: the command works from any directory
                f"imufdi ingest {shlex.quote(str(capture))} -o {base}",
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
