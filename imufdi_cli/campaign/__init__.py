"""Fault-injection campaigns: inject + detect + report over a run matrix, in parallel.

A campaign spec (TOML) names base logs (simulate presets with seeds, or files/globs), the
fault matrix, the detectors with parameter grids and the metrics to aggregate. It expands
to a list of small, JSON-able run descriptions; each run is keyed by the SHA-256 of its
canonical description, executed in a worker (process pool or dask.distributed), and its
result written to ``runs/<key>.json`` as soon as it finishes (atomically), so ``--resume``
skips what is done and an interrupted campaign loses at most the runs in flight. A run
that fails is recorded with its error and the campaign goes on.

Runs use the library in memory (simulate or read the base log once, inject with
:class:`~imufdi_cli.faults.FaultInjector`, stream blocks through the detector, score with
:class:`~imufdi_cli.metrics.MetricsAccumulator`, rows stamped with their decision time as
:mod:`imufdi_cli.detect` does): the same maths as ``inject | detect | report
--match-far``, without writing intermediate MCAP files.

Spec example::

    [campaign]
    name = "compare"
    seeds = [0, 1, 2, 3, 4]
    calibrate = "0s:2s"
    match_far = "1%"
    metrics = ["far", "mar", "fir", "detection_delay_s", "mar_at_far"]

    [[base]]
    preset = "paper-table4"

    [[fault]]
    model = "step"
    sensor = ["imu0.gyro.x", "imu7.gyro.z"]
    at = "2.5s"
    at_jitter = "0.5s"
    amp = ["0.3deg/s", "0.6deg/s", "0.9deg/s"]

    [[detector]]
    name = "glt"
    params = { alpha = [0.01, 0.001] }

The package by concern: :mod:`~imufdi_cli.campaign.spec` (TOML -> validated run
descriptions), :mod:`~imufdi_cli.campaign.run` (one run in memory),
:mod:`~imufdi_cli.campaign.executors` (in-process, local pool, dask),
:mod:`~imufdi_cli.campaign.summary` (rows, groups over seeds, curves, Markdown, gates),
:mod:`~imufdi_cli.campaign.plots` (the figure) and :mod:`~imufdi_cli.campaign.driver`
(results directory, lock, resume). The public names are re-exported here.
"""

from imufdi_cli.campaign.driver import (
    LOCK_NAME,
    RESULT_FILES,
    CampaignResult,
    check_all_failed,
    results_lock,
    run_campaign,
)
from imufdi_cli.campaign.executors import (
    WORKER_THREAD_ENV,
    DaskExecutor,
    LocalExecutor,
    worker_thread_env,
)
from imufdi_cli.campaign.plots import plot_curves
from imufdi_cli.campaign.run import BLOCK_SAMPLES, NS_PER_S, execute_run, jittered_specs
from imufdi_cli.campaign.spec import (
    DEFAULT_MATCH_BUDGET,
    DEFAULT_MATCH_FAR,
    DEFAULT_METRICS,
    CampaignSpec,
    load_spec,
    run_key,
)
from imufdi_cli.campaign.summary import (
    detection_curves,
    evaluate_summary_gates,
    summarize,
    summary_markdown,
)

__all__ = [
    "BLOCK_SAMPLES",
    "DEFAULT_MATCH_BUDGET",
    "DEFAULT_MATCH_FAR",
    "DEFAULT_METRICS",
    "LOCK_NAME",
    "NS_PER_S",
    "RESULT_FILES",
    "WORKER_THREAD_ENV",
    "CampaignResult",
    "CampaignSpec",
    "DaskExecutor",
    "LocalExecutor",
    "check_all_failed",
    "detection_curves",
    "evaluate_summary_gates",
    "execute_run",
    "jittered_specs",
    "load_spec",
    "plot_curves",
    "results_lock",
    "run_campaign",
    "run_key",
    "summarize",
    "summary_markdown",
    "worker_thread_env",
]
