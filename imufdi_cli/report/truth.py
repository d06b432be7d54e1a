"""Ground truth and calibration windows of an annotated log, from its metadata records
(``imufdi.faults`` written by ``imufdi inject``, ``imufdi.detect.<name>`` by ``imufdi
detect``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class TruthWindow:
    """An injected fault with absolute times, as recorded in ``imufdi.faults``."""

    fault_id: str
    sensors: tuple[str, ...]
    start_ns: int
    end_ns: int | None
    model: str = ""
    size: float | None = None  # step amp or drift rate, SI (FaultWindow.size)


@dataclass
class Truth:
    windows: list[TruthWindow]
    descriptions: list[dict[str, Any]]


def truth_windows(metadata: dict[str, dict[str, str]]) -> Truth | None:
    """Ground truth of a log from its ``imufdi.faults`` record (None when there is none).

    Each injection run records its log start ``t0_ns``; fault times are relative to it.
    """
    from imufdi_cli.errors import TruthError
    from imufdi_cli.faults.models import METADATA_NAME
    from imufdi_cli.metadata import faults_record

    record = faults_record(metadata)  # checked against its schema
    if record is None:
        return None
    try:
        return truth_of_runs([*record.get("previous", []), record])
    except TruthError as err:  # a fault the schema let through but Fault refuses
        raise TruthError(f"{METADATA_NAME} metadata: {err}") from err
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise TruthError(f"{METADATA_NAME} metadata is malformed ({err})") from err


def truth_of_runs(runs: list[dict[str, Any]]) -> Truth:
    """Ground truth from injection runs, each ``{"t0_ns": log start, "faults": [Fault
    dicts]}`` (what ``imufdi inject`` records, and what a campaign run applied in memory).

    Raises KeyError, TypeError or ValueError on a malformed run."""
    from imufdi_cli.faults.models import Fault

    windows = []
    descriptions = []
    for run in runs:
        t0 = int(run["t0_ns"])
        for item in run.get("faults", []):
            fault = Fault.from_dict(item)
            end = None if fault.until_ns is None else t0 + fault.until_ns
            size = fault.params.get({"step": "amp", "drift": "rate"}.get(fault.model, ""))
            windows.append(
                TruthWindow(
                    fault.id,
                    tuple(fault.sensors),
                    t0 + fault.at_ns,
                    end,
                    fault.model,
                    None if size is None else float(size),
                )
            )
            descriptions.append(fault.to_dict())
    return Truth(windows=windows, descriptions=descriptions)


def calibration_windows(
    metadata: dict[str, dict[str, str]],
) -> dict[str, tuple[int, int] | None]:
    """Detector name -> calibration window ``(start_ns, end_ns)`` from the
    ``imufdi.detect.<name>`` records; a detector absent from the result recorded none
    (a log from an imufdi before the window was recorded)."""
    from imufdi_cli.metadata import detect_records

    out: dict[str, tuple[int, int] | None] = {}
    for detector, record in detect_records(metadata).items():  # checked: McapInputError
        if "calibration_window_ns" not in record:
            continue
        window = record["calibration_window_ns"]
        out[detector] = None if window is None else (int(window[0]), int(window[1]))
    return out
