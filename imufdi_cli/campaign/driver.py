"""The campaign proper: results directory, lock, resume, executor, summary files."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from imufdi_cli.campaign.executors import DaskExecutor, LocalExecutor, _Executor
from imufdi_cli.campaign.plots import plot_curves
from imufdi_cli.campaign.run import run_order, write_json_atomic
from imufdi_cli.campaign.spec import CampaignSpec, run_key
from imufdi_cli.campaign.summary import (
    _rows,
    _rows_csv,
    pooled_budgets,
    summarize,
    summary_markdown,
)
from imufdi_cli.errors import CampaignFailedError, UsageError
from imufdi_cli.fileio import check_outputs, write_text


@dataclass
class CampaignResult:
    directory: str
    total: int
    executed: int
    skipped: int
    failed: int
    rows: list[dict[str, Any]] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0
    results: list[dict[str, Any]] = field(default_factory=list)


#: Files a campaign writes in its results directory (besides runs/<key>.json).
RESULT_FILES = ("runs.csv", "summary.json", "summary.md", "detection.png")


#: Lock file in the results directory: one campaign at a time per directory.
LOCK_NAME = ".imufdi-campaign.lock"


@contextmanager
def results_lock(out: Path) -> Iterator[None]:
    """Hold an exclusive lock on a results directory for the block.

    The lock is an ``flock`` on ``<out>/.imufdi-campaign.lock``, which holds the PID and
    host of its holder. The kernel releases it when the holder exits, however it exits
    (SIGKILL included), so a lock file left by a dead campaign is simply taken over.

    Raises
    ------
    UsageError
        Another live campaign holds the lock (the message names its PID).
    """
    import fcntl
    import socket

    path = out / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o666)
    except OSError as err:
        raise UsageError(f"-o {out}: cannot create the lock file {path} ({err.strerror})") from err
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode("utf-8", "replace").split()
            who = (
                f"pid {holder[0]}" + (f" on {holder[1]}" if len(holder) > 1 else "")
                if holder
                else "a process that is starting"
            )
            raise UsageError(
                f"-o {out}: another campaign ({who}) is running on this results directory"
                f" (lock {path}); wait for it to finish or choose another directory"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} {socket.gethostname()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock


def run_campaign(
    spec: CampaignSpec,
    results_dir: str | Path,
    *,
    jobs: int | None = None,
    scheduler: str | None = None,
    resume: bool = False,
    progress: Callable[[int, int, dict[str, Any] | None], None] | None = None,
) -> CampaignResult:
    """Execute a campaign and write runs/, runs.csv, summary.json, summary.md.

    ``progress(done, total, result)`` is called after each finished run.
    """
    start = time.perf_counter()
    out = Path(results_dir)
    if out.exists() and not out.is_dir():
        raise UsageError(f"-o {out}: exists and is not a directory")
    check_outputs(
        [spec.source, *(r["base"]["file"] for r in spec.runs if "file" in r["base"])],
        [(f"-o {out}", out / name) for name in RESULT_FILES],
    )
    _check_fresh(out, resume)
    executor: _Executor
    if scheduler:
        executor = DaskExecutor(scheduler)  # a bad address fails before anything is written
    else:
        executor = LocalExecutor(jobs or default_jobs())
    try:
        executor.start(len(_todo(spec, out / "runs", resume)))  # before the lock: see start()
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise UsageError(f"-o {out}: cannot create the directory ({err.strerror})") from err
        with results_lock(out):
            _check_fresh(out, resume)  # again: another campaign may have finished meanwhile
            return _run_locked(spec, out, executor, resume=resume, progress=progress, start=start)
    finally:
        executor.close()


def default_jobs() -> int:
    """``--jobs`` by default: the cores this process may run on.

    Pool workers fork from the campaign process in milliseconds with everything imported
    and write their own results, so a worker per core is the fastest setting even for a
    few short runs (docs/campaign.md, "Throughput"); a pool is not started for one run.
    """
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def _todo(spec: CampaignSpec, runs_dir: Path, resume: bool) -> list[dict[str, Any]]:
    """The runs still to execute (with --resume: those without a result file), one per
    key, grouped by base and seed (:func:`~imufdi_cli.campaign.run.run_order`)."""
    keyed = {run_key(desc): desc for desc in spec.runs}
    done = {p.stem for p in runs_dir.glob("*.json")} if resume and runs_dir.is_dir() else set()
    todo = [desc for key, desc in keyed.items() if key not in done]
    return sorted(todo, key=run_order)


def _check_fresh(out: Path, resume: bool) -> None:
    """Without --resume, refuse a results directory that already holds run results."""
    runs_dir = out / "runs"
    existing = list(runs_dir.glob("*.json")) if runs_dir.is_dir() else []
    if existing and not resume:
        raise UsageError(
            f"{out} already holds {len(existing)} run results; use --resume to continue"
            " or choose another directory"
        )


def _run_locked(
    spec: CampaignSpec,
    out: Path,
    executor: _Executor,
    *,
    resume: bool,
    progress: Callable[[int, int, dict[str, Any] | None], None] | None,
    start: float,
) -> CampaignResult:
    """The campaign proper, with the results directory locked by this process."""
    runs_dir = out / "runs"
    keyed = {run_key(desc): desc for desc in spec.runs}
    todo = _todo(spec, runs_dir, resume)
    done_keys = set(keyed) - {run_key(desc) for desc in todo}
    total = len(keyed)
    executed = 0
    runs_dir.mkdir(parents=True, exist_ok=True)
    # left by a campaign killed while writing (safe: we hold the directory's lock)
    for stale in runs_dir.glob(".*.json.*.tmp"):
        stale.unlink(missing_ok=True)
    if progress:
        progress(len(done_keys), total, None)
    for result in executor.run(todo, runs_dir):  # each result written as it finishes
        executed += 1
        if progress:
            progress(len(done_keys) + executed, total, result)
    results = []
    for key in keyed:
        path = runs_dir / f"{key}.json"
        if path.exists():
            results.append(json.loads(path.read_text(encoding="utf-8")))
    rows = _rows(pooled_budgets(results, spec.match_budget)[0])
    summary = summarize(spec, results)
    write_text(str(out / "runs.csv"), _rows_csv(rows))
    write_json_atomic(out / "summary.json", summary)
    write_text(str(out / "summary.md"), summary_markdown(summary))
    try:
        plot_curves(summary, out)
    except UsageError:
        pass  # matplotlib not installed: figures are optional
    return CampaignResult(
        directory=str(out),
        total=total,
        executed=executed,
        skipped=len(done_keys),
        failed=sum(1 for r in results if not r["ok"]),
        rows=rows,
        summary=summary,
        seconds=time.perf_counter() - start,
        results=results,
    )


def check_all_failed(result: CampaignResult) -> None:
    """Raise :class:`CampaignFailedError` when every run of the campaign failed.

    Exit 4 when any run failed on an internal error (a bug), else 3 (the runs failed on
    their data). A campaign where only some runs failed succeeds: the failures are in
    ``summary.json``/``summary.md`` and counted on the console.
    """
    if not result.results or any(r["ok"] for r in result.results):
        return
    internal = any(_is_internal(r) for r in result.results)
    first = result.results[0]
    raise CampaignFailedError(
        f"all {len(result.results)} runs failed (first: run {first['key']}:"
        f" {first.get('error') or 'no message'});"
        f" details in {Path(result.directory) / 'summary.md'}",
        internal=internal,
    )


def _is_internal(result: Mapping[str, Any]) -> bool:
    """A failed run failed on a bug (not an imufdi error); older results: a traceback."""
    if result.get("ok"):
        return False
    return bool(result.get("internal", bool(result.get("traceback"))))
