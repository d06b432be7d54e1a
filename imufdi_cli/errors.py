"""The one exception hierarchy of imufdi.

Every error the library raises on purpose derives from :class:`ImufdiError`. The CLI turns
it into a one-line message on stderr and exits with ``exc.exit_code``:

===== ==========================================================
code  meaning
===== ==========================================================
0     ok
1     a CI gate (``--fail-if``) failed
2     usage: bad option, parameter, spec, layout or gate expression
3     bad input data: unreadable, malformed or inconsistent files
4     internal error (a bug); also every run of a campaign failing on one
===== ==========================================================

Messages are a single line that names the problem and, where there is a finite set of
valid values, lists them. Third-party errors are wrapped (``raise XError(...) from err``).
"""

from __future__ import annotations

EXIT_OK = 0
EXIT_GATE_FAILED = 1
EXIT_USAGE = 2
EXIT_BAD_INPUT = 3
EXIT_INTERNAL = 4


class ImufdiError(Exception):
    """Base of every error raised by imufdi on purpose."""

    exit_code: int = EXIT_BAD_INPUT

    def __init__(self, message: str) -> None:
        # Keep messages on one line whatever the caller passed.
        super().__init__(" ".join(str(message).split()))


# --- usage errors (exit 2): the user asked for something that is not valid -------------


class UsageError(ImufdiError):
    """An option, parameter or expression given by the user is not valid."""

    exit_code = EXIT_USAGE


class UnitError(UsageError):
    """A quantity string has an unknown unit or the wrong dimension."""


class ArrayConfigError(UsageError):
    """An ArrayConfig (TOML or embedded JSON) is malformed."""


class FaultSpecError(UsageError):
    """A fault specification (CLI grammar or TOML) is not valid."""


class DetectorConfigError(UsageError):
    """Unknown detector, unknown parameter or parameter value out of range."""


class LayoutError(UsageError):
    """A capture frame layout (built-in options or TOML file) is not valid."""


class GateError(UsageError):
    """A ``--fail-if`` expression cannot be parsed or names unknown things."""


class CampaignSpecError(UsageError):
    """A campaign specification is not valid."""


# --- input data errors (exit 3): the data handed to us is unusable ---------------------


class InputDataError(ImufdiError):
    """Input data is missing, unreadable or malformed."""

    exit_code = EXIT_BAD_INPUT


class McapInputError(InputDataError):
    """An MCAP file is missing, not MCAP, truncated (with --strict) or has no IMU data."""


class OutputError(InputDataError):
    """An output file could not be written: disk full, file size limit, I/O error (exit 3;
    the partial output has been removed)."""


class CaptureError(InputDataError):
    """A raw serial capture could not be parsed (or, with --strict, had dropped bytes)."""


class FlightLogError(InputDataError):
    """A flight-controller log (PX4 ULog, ArduPilot DataFlash) is not readable, holds no
    IMU data, or (with --strict) is corrupt."""


class TruthError(InputDataError):
    """Ground-truth records in a log are missing or inconsistent with what was asked."""


class CalibrationError(InputDataError):
    """The calibration window is empty, too short or degenerate."""


class ArrayTooSmallError(CalibrationError):
    """The log's array has too few IMUs or sensors for a detector (exit 3, like any other
    data the detector cannot check, whichever detector it is). The message ends with
    :data:`ARRAY_TOO_SMALL_HINT`."""

    def __init__(self, message: str) -> None:
        super().__init__(f"{message}; {ARRAY_TOO_SMALL_HINT}")


#: what a user can do about a log with too few sensors for a detector
ARRAY_TOO_SMALL_HINT = (
    "redundancy checks compare sensors, so they need more of them than this log has:"
    " `imufdi info LOG` shows its IMUs; use a log of the whole array, choose --topic"
    " so that enough IMUs are read, or a detector for this case: health checks each IMU"
    " alone (stuck output, variance drop or growth, spikes, clipping, dropouts and gaps),"
    " bank mode=marg a single IMU that has a magnetometer"
)


class CampaignFailedError(ImufdiError):
    """Every run of a campaign failed: exit 3 when they failed on the data (imufdi errors),
    4 when any failed on an internal error (a bug)."""

    def __init__(self, message: str, *, internal: bool) -> None:
        super().__init__(message)
        self.exit_code = EXIT_INTERNAL if internal else EXIT_BAD_INPUT
