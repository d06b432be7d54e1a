"""The ``imufdi.*`` metadata records of a log: their schemas, checked before use.

Every record imufdi writes holds one JSON document under the key ``json``
(docs/formats.md, "Metadata"). A record is decoded with bounded nesting
(:func:`imufdi_cli.jsonin.loads`) and checked against its schema here before any
command reads a field of it, so a damaged or hand-edited record is one line naming the
record and the bad value (``imufdi.faults metadata: faults[0].at_s: expected a finite
number, got the string 'x'``), exit 3, never a crash or a silently ignored record:

==========================  =========================================================
record                      read by, and what a malformed one does
==========================  =========================================================
``imufdi.array``            every reader of IMU data: a warning, and the array is
                            inferred from the topics (co-aligned, measured rate)
``imufdi.faults``           ``info``, ``inject`` (adds to it), ``report`` (the truth):
                            exit 3
``imufdi.detect.<name>``    ``info``, ``report`` (calibration window, validity
                            exclusions, time origin): exit 3
``imufdi.ingest``           ``info``: a warning, the capture counts not shown
==========================  =========================================================

``detect`` copies the records it does not write without reading them; ``calibrate``
reads only ``imufdi.array``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from imufdi_cli.errors import ImufdiError, McapInputError, TruthError
from imufdi_cli.jsonin import (
    Anything,
    Int,
    Int64,
    ListOf,
    MapOf,
    Node,
    Number,
    Obj,
    Optional,
    Str,
    check,
    loads,
)

FAULTS = "imufdi.faults"
DETECT_PREFIX = "imufdi.detect."
INGEST = "imufdi.ingest"

#: fault times, seconds from the log start: within int64 nanoseconds (292 years)
_SECONDS = Number(limit=9.2e9)
#: one fault as Fault.to_dict writes it (SI)
FAULT_SCHEMA = Obj(
    required={
        "model": Str(),
        "sensors": ListOf(Str()),
        "at_s": _SECONDS,
        "params": MapOf(Number()),
    },
    optional={"until_s": Optional(_SECONDS), "id": Str(), "spec": Str()},
)
#: one injection run: its log start and faults
_RUN = {"t0_ns": Int64(), "faults": ListOf(FAULT_SCHEMA)}
FAULTS_SCHEMA = Obj(
    required=_RUN,
    optional={
        "format": Str(),
        "seed": Int(),
        "previous": ListOf(Obj(required=_RUN, optional={"format": Str(), "seed": Int()})),
    },
)

_RUNS = ListOf(ListOf(Int64(), length=2))
_TYPE_VALIDITY = Obj(
    optional={
        **{
            key: Int(low=0)
            for key in (
                "rows",
                "clipped",
                "invalid",
                "held",
                "missing",
                "clipped_values",
                "invalid_values",
            )
        },
        "clipped_ns": _RUNS,
        "invalid_ns": _RUNS,
        "held_ns": _RUNS,
        "missing_ns": _RUNS,
    }
)
#: ``imufdi.detect.<name>``, as detect writes it; every key optional (older logs lack some)
DETECT_SCHEMA = Obj(
    optional={
        "detector": Str(),
        "version": Str(),
        "calibration_s": ListOf(Optional(_SECONDS), length=2),
        "calibration_window_ns": Optional(ListOf(Int64(), length=2)),
        "calibration_samples": Int(low=0),
        "lookahead_samples": Optional(Int(low=0)),
        "detector_metadata": MapOf(Anything()),
        "t0_ns": Optional(Int64()),
        "window_s": ListOf(Optional(_SECONDS), length=2),
        "array_source": Str(),
        "validity": Obj(optional={"types": MapOf(_TYPE_VALIDITY), "range": MapOf(Number())}),
        "array": MapOf(Anything()),
        "description": Str(),
    }
)
#: ``imufdi.ingest``: what info shows of it
INGEST_SCHEMA = Obj(
    optional={
        "stats": MapOf(Anything()),
        "validity": MapOf(Obj(optional={k: Int(low=0) for k in ("rows", "clipped", "invalid")})),
    }
)


def decode(
    metadata: Mapping[str, Mapping[str, str]],
    name: str,
    schema: Node,
    error: type[ImufdiError] = McapInputError,
) -> dict[str, Any] | None:
    """Record ``name``'s JSON, checked against ``schema`` (None when the log has no such
    record). Raises ``error`` naming the record when it has no ``json`` entry, is not
    JSON, is nested too deeply or does not match the schema."""
    record = metadata.get(name)
    if record is None:
        return None
    where = f"{name} metadata"
    if not isinstance(record, Mapping) or "json" not in record:
        raise error(f"{where} has no 'json' entry")
    value = loads(record["json"], where, error)
    return check(value, schema, where, error)  # type: ignore[no-any-return]


def faults_record(metadata: Mapping[str, Mapping[str, str]]) -> dict[str, Any] | None:
    """The checked ``imufdi.faults`` record, or None (TruthError when malformed)."""
    return decode(metadata, FAULTS, FAULTS_SCHEMA, TruthError)


def detect_record(
    metadata: Mapping[str, Mapping[str, str]], detector: str
) -> dict[str, Any] | None:
    """The checked ``imufdi.detect.<detector>`` record, or None (McapInputError when
    malformed)."""
    return decode(metadata, DETECT_PREFIX + detector, DETECT_SCHEMA)


def detect_records(metadata: Mapping[str, Mapping[str, str]]) -> dict[str, dict[str, Any]]:
    """Every checked ``imufdi.detect.<name>`` record, by detector name."""
    out = {}
    for name in metadata:
        if name.startswith(DETECT_PREFIX):
            detector = name.removeprefix(DETECT_PREFIX)
            record = detect_record(metadata, detector)
            assert record is not None
            out[detector] = record
    return out


def ingest_record(
    metadata: Mapping[str, Mapping[str, str]], warnings: list[str]
) -> dict[str, Any] | None:
    """The checked ``imufdi.ingest`` record; None when absent, or malformed (then a
    warning is added: the record only describes the capture a log came from)."""
    try:
        return decode(metadata, INGEST, INGEST_SCHEMA)
    except McapInputError as err:
        warnings.append(f"{err}; the capture counts are not shown")
        return None


def check_all(metadata: Mapping[str, Mapping[str, str]]) -> None:
    """Check the records ``info`` and ``report`` use (faults and detect records); raise
    on the first malformed one."""
    faults_record(metadata)
    detect_records(metadata)


__all__ = [
    "DETECT_SCHEMA",
    "FAULTS_SCHEMA",
    "FAULT_SCHEMA",
    "INGEST_SCHEMA",
    "check_all",
    "decode",
    "detect_record",
    "detect_records",
    "faults_record",
    "ingest_record",
]
