"""``log_info``: everything ``imufdi info`` shows about a log, as a JSON-ready dict.

It reads the summary of :mod:`imufdi_cli.mcapio.summary` (no message is decoded unless the
log has no summary) and interprets the records the other commands wrote: the injected
faults (:mod:`imufdi_cli.report.truth`), the detectors' settings and validity counts, the
ingest's counts. A module of its own, above the readers and the report, so that ``imufdi
info`` compiles neither the pipeline nor the detectors (start-up time).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from imufdi_cli.errors import McapInputError
from imufdi_cli.mcapio.summary import summarize


def log_info(
    source: str,
    *,
    topics: Sequence[str] | None = None,
    time_source: str = "auto",
    strict: bool = False,
) -> dict[str, Any]:
    """Everything ``imufdi info`` shows, as a JSON-ready dict (``strict``: a truncated or
    corrupt log raises McapInputError instead of adding a warning).

    :func:`summarize`'s :meth:`LogSummary.to_dict` plus ``source``, the fault windows
    (``faults``), the detectors that wrote the log (``detectors``) and the ingest's
    validity counts (``validity``).
    """
    summary = summarize(source, topics=topics, time_source=time_source, strict=strict)
    data: dict[str, Any] = summary.to_dict()
    if not data.get("imu_topics"):
        found = ", ".join(f"{t['topic']} ({t.get('schema')})" for t in data.get("topics", []))
        problems = data.get("warnings") or []
        raise McapInputError(
            f"{source}: no sensor_msgs/msg/Imu channel (channels: {found or 'none'})"
            + (f"; {problems[0]}" if problems else "")
        )
    data["source"] = source
    nominal = summary.array.rate_hz if summary.array is not None else None
    measured = summary.rate_hz
    if summary.array_from_metadata and nominal and measured and abs(measured / nominal - 1) > 0.01:
        data["warnings"].append(
            f"the array config gives {nominal:g} Hz but the stamps give {measured:.6g} Hz"
        )
    metadata = summary.metadata
    from imufdi_cli.metadata import detect_records  # records checked against their schemas

    if "imufdi.faults" in metadata:
        from imufdi_cli.report.truth import truth_windows

        truth = truth_windows(metadata)
        data["faults"] = truth.descriptions if truth else []
    detectors = {}
    for name, content in detect_records(metadata).items():
        meta = content.get("detector_metadata", {})
        detectors[name] = {
            "params": meta.get("params", meta),
            "calibration_s": content.get("calibration_s"),
            **_validity_counts(content.get("validity")),
        }
    if detectors:
        data["detectors"] = detectors
    ingest_record = summary.ingest_record  # checked against its schema (a warning if not)
    if ingest_record is not None and isinstance(ingest_record.get("validity"), dict):
        data["validity"] = ingest_record["validity"]
    if ingest_record is not None:
        _flight_log(ingest_record, data)
    return data


def _flight_log(record: dict[str, Any], data: dict[str, Any]) -> None:
    """A flight-controller log's ingest (``imufdi ingest log.ulg``): its source, per-IMU
    rates and UTC anchor as ``flight_log``, and its "too low to test" message as a warning."""
    if record.get("format") not in ("px4-ulog", "ardupilot-dataflash"):
        return
    rate: dict[str, Any] = record["rate"] if isinstance(record.get("rate"), dict) else {}
    utc: dict[str, Any] = record["utc"] if isinstance(record.get("utc"), dict) else {}
    data["flight_log"] = {
        "format": record.get("format"),
        "system": record.get("system", {}),
        "imu_data": record.get("imu_data"),
        "n_imus": record.get("n_imus"),
        "imu_rates_hz": record.get("imu_rates_hz"),
        "testable": rate.get("testable"),
        "utc_start": utc.get("start"),
        "streams": record.get("streams", []),
    }
    if rate.get("testable") is False and rate.get("message"):
        data["warnings"].append(str(rate["message"]))


def _validity_counts(record: Any) -> dict[str, Any]:
    """Clipped/invalid/held row counts per sensor type of a detect record's validity."""
    if not isinstance(record, dict) or not isinstance(record.get("types"), dict):
        return {}
    return {
        "validity": {
            s: {k: v for k, v in c.items() if k in ("rows", "clipped", "invalid", "held")}
            for s, c in record["types"].items()
            if isinstance(c, dict)
        }
    }
