"""Flight-controller logs: PX4 ULog and ArduPilot DataFlash into IMU array MCAP.

>>> fmt = sniff_format(open("flight.ulg", "rb").read(SNIFF_BYTES))   # "px4-ulog"
>>> result = ingest_flight_log("flight.ulg", "flight.mcap")          # FlightLogIngest
>>> result.record["imu_rates_hz"], result.warnings

The readers (:mod:`~imufdi_cli.fclog.ulog`, :mod:`~imufdi_cli.fclog.dataflash`) stream a
log in chunks, vectorised with numpy; :mod:`~imufdi_cli.fclog.px4` and
:mod:`~imufdi_cli.fclog.ardupilot` know which messages hold the IMUs;
:mod:`~imufdi_cli.fclog.align` makes array samples of the asynchronous streams. This
package imports neither the detectors nor the report nor the CLI. The user's guide is
docs/flight-controllers.md.
"""

from imufdi_cli.fclog.ingest import (
    FORMAT_NAMES,
    IMU_DATA_CHOICES,
    SNIFF_BYTES,
    FlightLogIngest,
    ingest_flight_log,
    select,
    sniff_format,
)
from imufdi_cli.fclog.streams import MIN_TEST_RATE_HZ, LogScan, Stream, rate_problem

__all__ = [
    "FORMAT_NAMES",
    "IMU_DATA_CHOICES",
    "MIN_TEST_RATE_HZ",
    "SNIFF_BYTES",
    "FlightLogIngest",
    "LogScan",
    "Stream",
    "ingest_flight_log",
    "rate_problem",
    "select",
    "sniff_format",
]
