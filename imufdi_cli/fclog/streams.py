"""What a flight-controller log holds: IMU sensor streams, the log's own description, and
the logging settings that decide their rates (shared by the PX4 and ArduPilot readers)."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from typing import Any, Final, Protocol

import numpy as np

#: Below this many samples per second per IMU a log is too sparse to test: the default
#: calibration window (2 s) would hold fewer than the 10 samples a calibration needs
#: with a 5 Hz log, and each sample of such a log is one snapshot in a second or more of
#: flight (PX4's default logging profile: 1 Hz). Documented in docs/flight-controllers.md.
MIN_TEST_RATE_HZ: Final[float] = 10.0
#: intervals whose median gives a stream's nominal rate
HEAD_INTERVALS: Final[int] = 4096


@dataclass
class Stream:
    """One stream of IMU samples in a log.

    Attributes
    ----------
    name : str
        Message and instance, e.g. ``sensor_gyro 1``, ``vehicle_imu 0``, ``IMU 2``, ``GYR 0``.
    source : str
        The kind of data (:data:`SOURCE_HELP` keys): ``sensor``, ``vehicle_imu``, ``imu``,
        ``raw``.
    instance : int
        The IMU instance the log gives it.
    sensors : tuple of str
        Sensor types of its values, in column order (``("gyro",)``, ``("gyro", "accel")``).
    device_id : int or None
        Device id (PX4 ``device_id``; ArduPilot ``INS_GYR*_ID``/``INS_ACC*_ID``).
    count, first_us, last_us
        Samples and their time span (µs, the log's clock), filled in by the scan.
    intervals : list of int
        The first :data:`HEAD_INTERVALS` intervals between samples, µs (their median is
        the nominal period: gaps and dropouts do not lower it).
    """

    name: str
    source: str
    instance: int
    sensors: tuple[str, ...]
    device_id: int | None = None
    count: int = 0
    first_us: int | None = None
    last_us: int | None = None
    intervals: list[int] = field(default_factory=list)

    @property
    def width(self) -> int:
        return 3 * len(self.sensors)

    @property
    def rate_hz(self) -> float | None:
        """Nominal samples per second: 1 / the median interval between samples (of the
        first :data:`HEAD_INTERVALS`); None with fewer than 2 samples."""
        positive = [i for i in self.intervals if i > 0]
        if not positive:
            return None
        return 1e6 / float(np.median(positive))

    @property
    def mean_rate_hz(self) -> float | None:
        """Samples per second over the whole span (lower than the nominal rate by gaps)."""
        if self.count < 2 or self.first_us is None or self.last_us is None:
            return None
        span = self.last_us - self.first_us
        return (self.count - 1) * 1e6 / span if span > 0 else None

    def seen(self, t_us: np.ndarray) -> None:
        """Count samples at times ``t_us`` (the scan, in file order)."""
        if t_us.shape[0] == 0:
            return
        if len(self.intervals) < HEAD_INTERVALS:
            head = t_us[: HEAD_INTERVALS + 1]
            if self.last_us is not None:
                head = np.concatenate([[self.last_us], head])
            self.intervals.extend(np.diff(head).tolist()[: HEAD_INTERVALS - len(self.intervals)])
        self.count += int(t_us.shape[0])
        low, high = int(t_us.min()), int(t_us.max())
        self.first_us = low if self.first_us is None else min(self.first_us, low)
        self.last_us = high if self.last_us is None else max(self.last_us, high)

    def to_dict(self) -> dict[str, Any]:
        rate, mean = self.rate_hz, self.mean_rate_hz
        return {
            "name": self.name,
            "source": self.source,
            "instance": self.instance,
            "sensors": list(self.sensors),
            "device_id": self.device_id,
            "samples": self.count,
            "rate_hz": None if rate is None else round(rate, 4),
            "mean_rate_hz": None if mean is None else round(mean, 4),
            "span_s": None
            if self.first_us is None or self.last_us is None
            else round((self.last_us - self.first_us) * 1e-6, 6),
        }


#: what each kind of data is, in words (the ingest record and ``--imu-data``'s help)
SOURCE_HELP: Final[dict[str, str]] = {
    "sensor": "PX4 sensor_accel/sensor_gyro: each IMU's samples as its driver publishes them"
    " (board frame, before the thermal and offset calibration)",
    "vehicle_imu": "PX4 vehicle_imu: each IMU's delta angle and delta velocity over PX4's"
    " integration interval (IMU_INTEG_RATE), divided by it: the mean rate and specific force"
    " over the interval, calibrated, in the body frame",
    "imu": "ArduPilot IMU (IMU2, IMU3 in older logs): each IMU's filtered, calibrated body-frame"
    " values at the logging rate",
    "raw": "ArduPilot ACC/GYR (ACC1.., GYR1.. in older logs): each IMU's samples at the sensor"
    " rate (IMU_RAW logging or INS_RAW_LOG_OPT, gyros only)",
}


@dataclass
class LogScan:
    """A flight-controller log after one pass: its streams, clock and description.

    Attributes
    ----------
    format : str
        ``px4-ulog`` or ``ardupilot-dataflash``.
    system : dict
        The log's own description (firmware, hardware, vehicle), strings.
    streams : list of Stream
        Every IMU stream found, all sources.
    utc_offset_us : int or None
        UTC (µs since the Unix epoch) minus the log clock (µs since boot), from the first
        GPS time in the log; None when the log has none.
    utc_source : str
        Where ``utc_offset_us`` came from, in words.
    parameters : dict
        The logging and IMU parameters that explain the streams (name -> value).
    counts : dict
        The reader's counts (messages, corrupt bytes, dropouts, truncation).
    notes : list of str
        What the scan found worth saying (streams left out and why).
    batches : dict
        ArduPilot batch-sampler bursts (ISBH) per ``imu<k>.<sensor>``: ``batches``,
        ``samples``, ``rate_hz``.
    """

    format: str
    system: dict[str, str] = field(default_factory=dict)
    streams: list[Stream] = field(default_factory=list)
    utc_offset_us: int | None = None
    utc_source: str = ""
    parameters: dict[str, Any] = field(default_factory=dict)
    counts: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    batches: dict[str, dict[str, Any]] = field(default_factory=dict)

    def sources(self) -> dict[str, list[Stream]]:
        out: dict[str, list[Stream]] = {}
        for stream in self.streams:
            if stream.count:
                out.setdefault(stream.source, []).append(stream)
        return out


class FlightLogReader(Protocol):
    """What :mod:`imufdi_cli.fclog.ingest` needs of a format's reader."""

    format: str

    def scan(self, progress: Any = None) -> LogScan: ...

    def chunks(
        self, streams: Sequence[Stream], progress: Any = None
    ) -> Iterator[list[tuple[int, np.ndarray, np.ndarray]]]:
        """Per chunk of the log: (index into ``streams``, times (K,) µs, values (K, width))."""
        ...


# --- GPS time ---------------------------------------------------------------------------

GPS_EPOCH: Final[datetime] = datetime(1980, 1, 6, tzinfo=timezone.utc)
#: GPS - UTC offset in seconds from each UTC date on (IERS leap seconds since 1980)
LEAP_SECONDS: Final[tuple[tuple[datetime, int], ...]] = tuple(
    (datetime(y, m, 1, tzinfo=timezone.utc), s)
    for y, m, s in (
        (1981, 7, 1),
        (1982, 7, 2),
        (1983, 7, 3),
        (1985, 7, 4),
        (1988, 1, 5),
        (1990, 1, 6),
        (1991, 1, 7),
        (1992, 7, 8),
        (1993, 7, 9),
        (1994, 7, 10),
        (1996, 1, 11),
        (1997, 7, 12),
        (1999, 1, 13),
        (2006, 1, 14),
        (2009, 1, 15),
        (2012, 7, 16),
        (2015, 7, 17),
        (2017, 1, 18),
    )
)


def gps_to_unix_us(week: int, ms_of_week: int) -> int:
    """UTC µs since the Unix epoch of a GPS week and millisecond of week (leap seconds
    subtracted)."""
    gps = GPS_EPOCH + timedelta(weeks=int(week), milliseconds=int(ms_of_week))
    leap = 0
    for start, seconds in LEAP_SECONDS:
        if gps - timedelta(seconds=seconds) >= start:
            leap = seconds
    utc = gps - timedelta(seconds=leap)
    epoch = datetime(1970, 1, 1, tzinfo=timezone.utc)
    delta = utc - epoch
    return (delta.days * 86_400 + delta.seconds) * 1_000_000 + delta.microseconds


def iso_utc(unix_us: int) -> str:
    """``2024-05-01T12:00:00.250000Z``."""
    moment = datetime(1970, 1, 1, tzinfo=timezone.utc) + timedelta(microseconds=int(unix_us))
    return moment.strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def rate_problem(metadata: Mapping[str, Mapping[str, str]]) -> str | None:
    """The "too low to test" message of a log's ``imufdi.ingest`` record (a flight log
    ingested at a per-IMU rate below :data:`MIN_TEST_RATE_HZ`), else None."""
    record = metadata.get("imufdi.ingest")
    if record is None:
        return None
    from imufdi_cli.errors import InputDataError
    from imufdi_cli.jsonin import loads

    try:  # nesting bounded (a malformed record is info's warning, not this one's)
        content = loads(record.get("json", "{}"), "imufdi.ingest metadata")
    except (InputDataError, AttributeError):
        return None
    rate = content.get("rate") if isinstance(content, dict) else None
    if isinstance(rate, dict) and rate.get("testable") is False and rate.get("message"):
        return str(rate["message"])
    return None


#: sample times a log can hold, µs of its clock: above 0 and below 2^48 (8.9 years since
#: boot); anything else is a damaged message (dropped, the same way by scan and convert)
MAX_LOG_TIME_US: Final[int] = 1 << 48
#: a GPS time outside these years is damaged (not a UTC anchor)
UTC_RANGE_US: Final[tuple[int, int]] = (946_684_800_000_000, 4_102_444_800_000_000)


def plausible(t_us: np.ndarray) -> np.ndarray:
    """Which sample times (µs of the log clock) a log can hold (see :data:`MAX_LOG_TIME_US`)."""
    return (t_us > 0) & (t_us < MAX_LOG_TIME_US)


def has_fields(values: np.ndarray, names: Sequence[str]) -> bool:
    """Whether a structured array has every field of ``names`` (a damaged or unknown
    format may not)."""
    present = values.dtype.names or ()
    return all(name in present for name in names)
