"""``imufdi report``: metrics of an annotated log, renderers and CI gates.

:func:`build_report` reads the detector status channels and the ground truth of an
annotated MCAP and computes the metrics of docs/metrics.md per detector and sensor type.
Renderers turn a :class:`Report` into JSON, Markdown (the layout of Li et al. Table 4), CSV
and JUnit XML; :func:`parse_gate` / :func:`evaluate_gates` implement ``--fail-if``.

Modules: :mod:`~imufdi_cli.report.model` (:class:`Report`, :class:`ReportEntry`),
:mod:`~imufdi_cli.report.truth` (ground truth and calibration windows from the metadata),
:mod:`~imufdi_cli.report.scan` (:func:`build_report`: the streaming pass over the status
channels and the explained episodes), :mod:`~imufdi_cli.report.gates` (``--fail-if`` and
``--match-far``) and :mod:`~imufdi_cli.report.formats` (table rows, JSON, Markdown, CSV,
JUnit, ROC and episode renderers). Everything public is re-exported here: import from
``imufdi_cli.report``. The modules import only downwards (formats -> gates -> model,
scan -> truth, model), never in a circle.
"""

from __future__ import annotations

from imufdi_cli.report.formats import (
    BUDGET_COLUMNS,
    CONSOLE_OMITS,
    CSV_FIELDS,
    EPISODE_COLUMNS,
    FAULT_FREE_COLUMNS,
    MATCHED_COLUMNS,
    REFERENCE_COLUMNS,
    ROC_FIELDS,
    TABLE_COLUMNS,
    episode_rows,
    fault_free,
    format_amplitudes,
    format_size,
    format_value,
    table_columns,
    table_rows,
    to_csv,
    to_episodes_csv,
    to_json,
    to_junit,
    to_markdown,
    to_roc_csv,
)
from imufdi_cli.report.gates import (
    OPERATORS,
    Gate,
    GateResult,
    evaluate_gates,
    parse_budget,
    parse_far,
    parse_gate,
)
from imufdi_cli.report.model import Report, ReportEntry
from imufdi_cli.report.scan import EPISODES_LISTED, PLOT_POINTS, build_report
from imufdi_cli.report.truth import Truth, TruthWindow, calibration_windows, truth_windows

__all__ = [
    "BUDGET_COLUMNS",
    "CONSOLE_OMITS",
    "CSV_FIELDS",
    "EPISODES_LISTED",
    "EPISODE_COLUMNS",
    "FAULT_FREE_COLUMNS",
    "MATCHED_COLUMNS",
    "OPERATORS",
    "PLOT_POINTS",
    "REFERENCE_COLUMNS",
    "ROC_FIELDS",
    "TABLE_COLUMNS",
    "Gate",
    "GateResult",
    "Report",
    "ReportEntry",
    "Truth",
    "TruthWindow",
    "build_report",
    "calibration_windows",
    "episode_rows",
    "evaluate_gates",
    "fault_free",
    "format_amplitudes",
    "format_size",
    "format_value",
    "parse_budget",
    "parse_far",
    "parse_gate",
    "table_columns",
    "table_rows",
    "to_csv",
    "to_episodes_csv",
    "to_json",
    "to_junit",
    "to_markdown",
    "to_roc_csv",
    "truth_windows",
]
