"""PX4 ULog: which topics hold the IMUs, and how their values become SI triads.

- ``sensor_accel`` / ``sensor_gyro`` (one instance per IMU): ``x, y, z`` in m/s² and
  rad/s as the driver publishes them, in the board frame (the driver applies the chip's
  mounting rotation), before PX4's calibration (offsets, scale, ``SENS_BOARD_ROT``);
  stamped ``timestamp_sample``.
- ``vehicle_imu`` (one instance per IMU): ``delta_angle`` (rad) and ``delta_velocity``
  (m/s) integrated over ``delta_angle_dt`` / ``delta_velocity_dt`` (µs, PX4's
  ``IMU_INTEG_RATE``, 200 Hz by default), calibrated and in the body frame. Divided by
  their intervals they are the mean angular rate and specific force over the interval
  (coning-corrected by PX4); stamped ``timestamp_sample``, the end of the interval.
- ``vehicle_gps_position`` / ``sensor_gps``: ``time_utc_usec`` against the log clock gives
  UTC.

Logging rates (``src/modules/logger/logged_topics.cpp``): the default profile logs
``sensor_accel``/``sensor_gyro`` every 1000 ms and ``vehicle_imu`` every 500 ms per
instance; ``SDLOG_PROFILE`` bit 2 (thermal calibration) or bit 6 (sensor comparison) log
``sensor_accel``/``sensor_gyro`` every 100 ms; bit 4 (high rate) and bit 3 (system
identification) log ``sensor_combined`` at full rate, the *selected* IMU only; bits 8 and
9 log the raw FIFO of the first IMU only. Every instance at full rate needs a topic list
on the SD card, ``etc/logging/logger_topics.txt``, with the lines ``sensor_accel 0`` and
``sensor_gyro 0`` (interval 0: every sample, all instances).
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from typing import Any, Final

import numpy as np

from imufdi_cli.fclog.streams import UTC_RANGE_US, LogScan, Stream, has_fields, plausible
from imufdi_cli.fclog.ulog import ULogCounts, ULogFile

FORMAT: Final[str] = "px4-ulog"
SENSOR_TOPICS: Final[dict[str, str]] = {"sensor_gyro": "gyro", "sensor_accel": "accel"}
GPS_TOPICS: Final[tuple[str, ...]] = ("vehicle_gps_position", "sensor_gps")
#: parameters recorded with the ingest (they explain what was logged and how)
PARAMETERS: Final[tuple[str, ...]] = (
    "SDLOG_PROFILE",
    "SDLOG_MODE",
    "IMU_GYRO_RATEMAX",
    "IMU_INTEG_RATE",
    "SENS_BOARD_ROT",
    "SENS_BOARD_X_OFF",
    "SENS_BOARD_Y_OFF",
    "SENS_BOARD_Z_OFF",
    "SENS_IMU_MODE",
)
LOGGING_HINT: Final[str] = (
    "PX4's default logging profile logs sensor_accel/sensor_gyro once a second and"
    " vehicle_imu twice a second per IMU; SDLOG_PROFILE bit 2 (thermal calibration) or"
    " bit 6 (sensor comparison) raises sensor_accel/sensor_gyro to 10 Hz, and every IMU at"
    " full rate needs etc/logging/logger_topics.txt on the SD card with the lines"
    " 'sensor_accel 0' and 'sensor_gyro 0' (SDLOG_PROFILE bit 4, high rate, logs"
    " sensor_combined at full rate, which is the selected IMU only)"
)

_TIME_FIELDS: Final[tuple[str, ...]] = ("timestamp", "timestamp_sample")
_IMU_FIELDS: Final[tuple[str, ...]] = (
    *_TIME_FIELDS,
    "accel_device_id",
    "gyro_device_id",
    "delta_angle",
    "delta_velocity",
    "delta_angle_dt",
    "delta_velocity_dt",
)


def _stamps(values: np.ndarray) -> np.ndarray:
    """``timestamp_sample`` where the topic has it (and it is set), else ``timestamp``
    (µs; a value past int64 reads as negative: implausible, dropped by :func:`_usable`)."""
    t = values["timestamp"].astype(np.int64)
    names = values.dtype.names or ()
    if "timestamp_sample" in names:
        sample = values["timestamp_sample"].astype(np.int64)
        t = np.where(sample > 0, sample, t)
    return t


#: the fields each IMU topic needs
_NEEDS: Final[dict[str, tuple[str, ...]]] = {
    "sensor_gyro": ("timestamp", "x", "y", "z"),
    "sensor_accel": ("timestamp", "x", "y", "z"),
    "vehicle_imu": (
        "timestamp",
        "delta_angle",
        "delta_velocity",
        "delta_angle_dt",
        "delta_velocity_dt",
    ),
}


def _usable(topic: str, values: np.ndarray) -> np.ndarray:
    """The rows of a chunk of an IMU topic that are samples: a plausible time and, for
    ``vehicle_imu``, integration intervals above 0 (the same rule in scan and convert)."""
    keep = plausible(_stamps(values))
    if topic == "vehicle_imu":
        keep &= (values["delta_angle_dt"] > 0) & (values["delta_velocity_dt"] > 0)
    return values[keep]


def _triads(topic: str, values: np.ndarray) -> np.ndarray:
    """(K, 6) gyro and accel of ``vehicle_imu`` rows (deltas over their intervals), or
    (K, 3) of ``sensor_*`` rows, float64."""
    # whatever bits a damaged log holds (signalling NaNs, huge values): no warnings; the
    # validity counts of the ingest flag them
    with np.errstate(all="ignore"):
        if topic == "vehicle_imu":
            gyro = values["delta_angle"].astype(np.float64) / (
                values["delta_angle_dt"].astype(np.float64)[:, None] * 1e-6
            )
            accel = values["delta_velocity"].astype(np.float64) / (
                values["delta_velocity_dt"].astype(np.float64)[:, None] * 1e-6
            )
            return np.concatenate([gyro, accel], axis=1)
        return np.column_stack([values[a].astype(np.float64) for a in ("x", "y", "z")])


def _version(value: Any) -> str | None:
    """``ver_sw_release`` (0xMMmmppTT) as ``v1.14.0`` (with the release type)."""
    if not isinstance(value, int) or value <= 0:
        return None
    major, minor, patch, kind = value >> 24 & 255, value >> 16 & 255, value >> 8 & 255, value & 255
    tag = (
        ""
        if kind == 255
        else " rc"
        if kind >= 192
        else " beta"
        if kind >= 128
        else " alpha"
        if kind >= 64
        else " dev"
    )
    return f"v{major}.{minor}.{patch}{tag}"


class PX4Log:
    """A PX4 ULog as a flight-controller log (:class:`~imufdi_cli.fclog.streams.FlightLogReader`)."""

    format = FORMAT

    def __init__(self, path: str | os.PathLike[str], *, chunk_size: int = 4 << 20) -> None:
        self.ulog = ULogFile(path)
        self.chunk_size = chunk_size

    @staticmethod
    def _wanted(topics: Sequence[str]) -> dict[str, Sequence[str]]:
        return {
            t: _IMU_FIELDS if t == "vehicle_imu" else (*_TIME_FIELDS, "device_id", "x", "y", "z")
            for t in topics
        }

    def scan(self, progress: Any = None) -> LogScan:
        ulog = self.ulog
        wanted = self._wanted([*SENSOR_TOPICS, "vehicle_imu"])
        for topic in GPS_TOPICS:
            wanted[topic] = (*_TIME_FIELDS, "time_utc_usec")
        scan = LogScan(format=FORMAT)
        info = ulog.info
        scan.system = {
            k: str(v)
            for k, v in {
                "sys_name": info.get("sys_name"),
                "ver_hw": info.get("ver_hw"),
                "ver_sw": info.get("ver_sw"),
                "version": _version(info.get("ver_sw_release")),
                "sys_os_name": info.get("sys_os_name"),
                "sys_uuid": info.get("sys_uuid"),
            }.items()
            if v not in (None, "")
        }
        streams: dict[tuple[str, int], Stream] = {}
        params = {k: v for k, v in ulog.parameters.items() if k in PARAMETERS}
        counts = ULogCounts()
        for chunk in ulog.read(
            wanted, chunk_size=self.chunk_size, counts=counts, progress=progress
        ):
            for key, value in chunk.parameters:
                if key in PARAMETERS and key not in params:
                    params[key] = value
            for (topic, multi), values in chunk.data.items():
                if topic in GPS_TOPICS:
                    if scan.utc_offset_us is None:
                        self._utc(scan, topic, values)
                    continue
                if not has_fields(values, _NEEDS[topic]):
                    note = f"{topic} {multi} lacks fields of {', '.join(_NEEDS[topic])}: left out"
                    if note not in scan.notes:
                        scan.notes.append(note)
                    continue
                stream = streams.get((topic, multi))
                if stream is None:
                    if topic == "vehicle_imu":
                        stream = Stream(
                            f"vehicle_imu {multi}", "vehicle_imu", multi, ("gyro", "accel")
                        )
                    else:
                        stream = Stream(
                            f"{topic} {multi}", "sensor", multi, (SENSOR_TOPICS[topic],)
                        )
                    streams[(topic, multi)] = stream
                if stream.device_id is None and values.shape[0]:
                    field = "device_id" if topic != "vehicle_imu" else "gyro_device_id"
                    if field in (values.dtype.names or ()):
                        stream.device_id = int(values[field][0])
                stream.seen(_stamps(_usable(topic, values)))
        scan.streams = sorted(streams.values(), key=lambda s: (s.source, s.sensors, s.instance))
        scan.parameters = params
        scan.counts = {
            "messages": counts.messages,
            "corrupt_bytes": counts.corrupt_bytes,
            "corrupt_messages": counts.corrupt_messages,
            "dropouts": counts.dropouts,
            "dropout_ms": counts.dropout_ms,
            "truncated": counts.truncated,
        }
        if ulog.appended_offsets:
            scan.notes.append(f"the log has data appended at {len(ulog.appended_offsets)} offsets")
        return scan

    @staticmethod
    def _utc(scan: LogScan, topic: str, values: np.ndarray) -> None:
        """UTC from the first GPS message with a plausible UTC time."""
        if not has_fields(values, ("timestamp", "time_utc_usec")):
            return
        utc = values["time_utc_usec"].astype(np.int64)
        low, high = UTC_RANGE_US
        good = np.flatnonzero((utc > low) & (utc < high) & plausible(_stamps(values)))
        if good.size:
            i = int(good[0])
            scan.utc_offset_us = int(utc[i]) - int(_stamps(values[i : i + 1])[0])
            scan.utc_source = (
                f"{topic}.time_utc_usec against its timestamp (first GPS time in the log)"
            )

    def chunks(
        self, streams: Sequence[Stream], progress: Any = None
    ) -> Iterator[list[tuple[int, np.ndarray, np.ndarray]]]:
        index: dict[tuple[str, int], int] = {}
        for k, stream in enumerate(streams):
            topic, _, multi = stream.name.rpartition(" ")
            index[(topic, int(multi))] = k
        wanted = self._wanted(sorted({key[0] for key in index}))
        for chunk in self.ulog.read(wanted, chunk_size=self.chunk_size, progress=progress):
            out = []
            for key, values in chunk.data.items():
                found = index.get(key)
                if found is None:
                    continue
                values = _usable(key[0], values)
                out.append((found, _stamps(values), _triads(key[0], values)))
            if out:
                yield out
