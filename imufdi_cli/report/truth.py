"""Ground truth and calibration windows of an annotated log, from its metadata records
(``imufdi.faults`` written by ``imufdi inject``, ``imufdi.detect.<name>`` by ``imufdi
detect``)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from imufdi_cli.errors import McapInputError


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
    from imufdi_cli.faults import METADATA_NAME

    record_meta = metadata.get(METADATA_NAME)
    if record_meta is None:
        return None
    try:
        record = json.loads(record_meta["json"])
        return truth_of_runs([*record.get("previous", []), record])
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise TruthError(f"{METADATA_NAME} metadata is malformed ({err})") from err


def truth_of_runs(runs: list[dict[str, Any]]) -> Truth:
    """Ground truth from injection runs, each ``{"t0_ns": log start, "faults": [Fault
    dicts]}`` (what ``imufdi inject`` records, and what a campaign run applied in memory).

    Raises KeyError, TypeError or ValueError on a malformed run."""
    from imufdi_cli.faults import Fault

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
    out: dict[str, tuple[int, int] | None] = {}
    for name, data in metadata.items():
        if not name.startswith("imufdi.detect."):
            continue
        try:
            record = json.loads(data.get("json", "{}"))
        except ValueError:
            continue
        if not isinstance(record, dict) or "calibration_window_ns" not in record:
            continue
        window = record["calibration_window_ns"]
        detector = name.removeprefix("imufdi.detect.")
        if window is None:
            out[detector] = None
        else:
            try:
                out[detector] = (int(window[0]), int(window[1]))
            except (TypeError, ValueError, IndexError) as err:
                raise McapInputError(
                    f"{name}: calibration_window_ns is malformed ({window!r})"
                ) from err
    return out
