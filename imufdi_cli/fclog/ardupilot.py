"""ArduPilot DataFlash: which messages hold the IMUs, and how they become SI triads.

- ``IMU`` with an instance column ``I`` (``IMU``, ``IMU2``, ``IMU3`` in logs before
  ArduPilot 4.0): every IMU's gyro (rad/s) and accel (m/s²) as the attitude code uses them
  (calibrated, filtered by ``INS_GYRO_FILTER``/``INS_ACCEL_FILTER`` and the notches,
  rotated to the body frame by ``AHRS_ORIENTATION``), all instances written with one
  ``TimeUS`` (``AP_InertialSensor::Write_IMU``), at 25 Hz with ``LOG_BITMASK``'s IMU bit
  (Copter) or at the main loop rate with its IMU_FAST bit (Copter: bit 18).
- ``ACC`` / ``GYR`` with ``I`` (``ACC1``.., ``GYR1``.. before 4.0): every sample as the
  sensor delivers it (``SampleUS``), with ``LOG_BITMASK``'s IMU_RAW bit (Copter: bit 19);
  ``INS_RAW_LOG_OPT`` logs ``GYR`` only (bit 0 the primary gyro, bit 1 all gyros, bit 2
  after the filters, bit 3 before and after: the post-filter copies are instances
  ``I + number of gyros``, left out here).
- ``ISBH`` / ``ISBD``: the batch sampler (``INS_LOG_BAT_MASK``, ``INS_LOG_BAT_OPT``,
  ``INS_LOG_BAT_CNT``): bursts of ``INS_LOG_BAT_CNT`` raw samples of *one* sensor at a time
  (accel then gyro of each IMU in the mask, in turn), ``value = raw / mul``. No two IMUs
  are ever sampled together, so these bursts cannot form array samples; they are counted
  and described in the ingest record.
- ``GPS``: ``GWk``/``GMS`` (``Week``/``TimeMS`` with boot time ``T`` in older logs) against
  the log clock gives UTC; ``PARM``: the parameters; ``MSG``: firmware and board.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from typing import Any, Final

import numpy as np

from imufdi_cli.fclog.dataflash import DataFlashCounts, DataFlashFile
from imufdi_cli.fclog.streams import (
    UTC_RANGE_US,
    LogScan,
    Stream,
    gps_to_unix_us,
    has_fields,
    plausible,
)

FORMAT: Final[str] = "ardupilot-dataflash"
#: message name -> (source, sensors, instance when the message has no I column)
IMU_MESSAGES: Final[dict[str, tuple[str, tuple[str, ...], int]]] = {
    "IMU": ("imu", ("gyro", "accel"), 0),
    "IMU2": ("imu", ("gyro", "accel"), 1),
    "IMU3": ("imu", ("gyro", "accel"), 2),
    "GYR": ("raw", ("gyro",), 0),
    "GYR1": ("raw", ("gyro",), 0),
    "GYR2": ("raw", ("gyro",), 1),
    "GYR3": ("raw", ("gyro",), 2),
    "ACC": ("raw", ("accel",), 0),
    "ACC1": ("raw", ("accel",), 0),
    "ACC2": ("raw", ("accel",), 1),
    "ACC3": ("raw", ("accel",), 2),
}
_COLUMNS: Final[dict[str, tuple[str, ...]]] = {
    "gyro": ("GyrX", "GyrY", "GyrZ"),
    "accel": ("AccX", "AccY", "AccZ"),
}
_TIME: Final[tuple[str, ...]] = ("TimeUS", "TimeMS", "SampleUS", "I")
PARAMETERS: Final[tuple[str, ...]] = (
    "LOG_BITMASK",
    "LOG_DISARMED",
    "INS_RAW_LOG_OPT",
    "INS_LOG_BAT_MASK",
    "INS_LOG_BAT_OPT",
    "INS_LOG_BAT_CNT",
    "INS_LOG_BAT_LGIN",
    "INS_LOG_BAT_LGCT",
    "INS_FAST_SAMPLE",
    "INS_GYRO_RATE",
    "INS_GYRO_FILTER",
    "INS_ACCEL_FILTER",
    "INS_USE",
    "INS_USE2",
    "INS_USE3",
    "INS_GYR_ID",
    "INS_GYR2_ID",
    "INS_GYR3_ID",
    "INS_ACC_ID",
    "INS_ACC2_ID",
    "INS_ACC3_ID",
    "AHRS_ORIENTATION",
    "SCHED_LOOP_RATE",
    *(f"INS_POS{k}_{a}" for k in (1, 2, 3) for a in "XYZ"),
)
LOGGING_HINT: Final[str] = (
    "ArduPilot logs IMU at 25 Hz with LOG_BITMASK's IMU bit (Copter); its IMU_FAST bit"
    " (Copter: bit 18) logs IMU at the main loop rate and its IMU_RAW bit (Copter: bit 19)"
    " logs ACC/GYR at the sensor rate; INS_RAW_LOG_OPT logs raw gyros only; the batch"
    " sampler (INS_LOG_BAT_MASK) logs one sensor at a time, so it cannot compare IMUs"
)
_GYR_IDS: Final[tuple[str, ...]] = ("INS_GYR_ID", "INS_GYR2_ID", "INS_GYR3_ID")
_ACC_IDS: Final[tuple[str, ...]] = ("INS_ACC_ID", "INS_ACC2_ID", "INS_ACC3_ID")


def _names(values: np.ndarray) -> tuple[str, ...]:
    return values.dtype.names or ()


def _times(values: np.ndarray, *, sample: bool) -> np.ndarray:
    """Sample times in µs: ``SampleUS`` (raw messages), else ``TimeUS``, else ``TimeMS``."""
    names = _names(values)
    if sample and "SampleUS" in names:
        return values["SampleUS"].astype(np.int64)
    if "TimeUS" in names:
        return values["TimeUS"].astype(np.int64)
    return values["TimeMS"].astype(np.int64) * 1000


def _usable(name: str, values: np.ndarray) -> np.ndarray | None:
    """The rows of a chunk of an IMU message that are samples (a plausible time), or None
    when its format lacks a time or a sensor column (a damaged or unknown FMT); the same
    rule in scan and convert."""
    source, sensors, _ = IMU_MESSAGES[name]
    names = _names(values)
    if not ("TimeUS" in names or "TimeMS" in names):
        return None
    if not has_fields(values, [c for s in sensors for c in _COLUMNS[s]]):
        return None
    return values[plausible(_times(values, sample=source == "raw"))]


def _instances(name: str, values: np.ndarray) -> np.ndarray:
    if "I" in _names(values):
        return values["I"].astype(np.int64)
    return np.full(values.shape[0], IMU_MESSAGES[name][2], np.int64)


class ArduPilotLog:
    """An ArduPilot DataFlash log as a flight-controller log
    (:class:`~imufdi_cli.fclog.streams.FlightLogReader`)."""

    format = FORMAT

    def __init__(self, path: str | os.PathLike[str], *, chunk_size: int = 4 << 20) -> None:
        self.log = DataFlashFile(path)
        self.chunk_size = chunk_size

    def scan(self, progress: Any = None) -> LogScan:
        wanted: dict[str, Sequence[str]] = {
            name: (*_TIME, *(c for s in sensors for c in _COLUMNS[s]))
            for name, (_, sensors, _) in IMU_MESSAGES.items()
        }
        wanted["GPS"] = ("TimeUS", "TimeMS", "T", "GMS", "GWk", "Week", "I")
        wanted["PARM"] = ("Name", "Value")
        wanted["MSG"] = ("Message",)
        wanted["ISBH"] = (
            "TimeUS",
            "N",
            "type",
            "instance",
            "mul",
            "smp_cnt",
            "SampleUS",
            "smp_rate",
        )
        scan = LogScan(format=FORMAT)
        streams: dict[tuple[str, int], Stream] = {}
        params: dict[str, Any] = {}
        messages: list[str] = []
        counts = DataFlashCounts()
        for chunk in self.log.read(
            wanted, chunk_size=self.chunk_size, counts=counts, progress=progress
        ):
            for name, values in chunk.data.items():
                if name in IMU_MESSAGES:
                    source, sensors, _ = IMU_MESSAGES[name]
                    usable = _usable(name, values)
                    if usable is None:
                        note = f"{name} messages lack a time or sensor column: left out"
                        if note not in scan.notes:
                            scan.notes.append(note)
                        continue
                    values = usable
                    t = _times(values, sample=source == "raw")
                    instance = _instances(name, values)
                    for k in np.unique(instance).tolist():
                        label = "".join(c for c in name if not c.isdigit())
                        key = (label, int(k))
                        stream = streams.get(key)
                        if stream is None:
                            stream = streams[key] = Stream(f"{label} {k}", source, int(k), sensors)
                        stream.seen(t[instance == k])
                elif name == "PARM":
                    for raw_name, value in zip(values["Name"].tolist(), values["Value"].tolist()):
                        key = raw_name.split(b"\0", 1)[0].decode("ascii", "replace")
                        if key in PARAMETERS and key not in params:
                            params[key] = float(value)
                elif name == "MSG" and len(messages) < 8:
                    for raw in values["Message"].tolist()[: 8 - len(messages)]:
                        messages.append(raw.split(b"\0", 1)[0].decode("ascii", "replace"))
                elif name == "GPS" and scan.utc_offset_us is None:
                    self._utc(scan, values)
                elif name == "ISBH":
                    self._batches(scan, values)
        scan.parameters = {k: (int(v) if float(v).is_integer() else v) for k, v in params.items()}
        self._describe(scan, messages)
        scan.streams = self._physical(
            scan, sorted(streams.values(), key=lambda s: (s.source, s.sensors, s.instance))
        )
        scan.counts = {
            "messages": counts.messages,
            "corrupt_bytes": counts.corrupt_bytes,
            "truncated": counts.truncated,
        }
        return scan

    @staticmethod
    def _describe(scan: LogScan, messages: list[str]) -> None:
        firmware = next((m for m in messages if " V" in m and ("Ardu" in m or "APM" in m)), None)
        if firmware:
            scan.system["firmware"] = firmware
        board = next(
            (
                m
                for m in messages
                if m != firmware
                and not m.startswith(
                    ("ChibiOS", "RC", "Param", "New", "GPS", "u-blox", "Frame", "IMU")
                )
            ),
            None,
        )
        if board:
            scan.system["board"] = board

    def _physical(self, scan: LogScan, streams: list[Stream]) -> list[Stream]:
        """Device ids from the INS_*_ID parameters; the post-filter copies of raw streams
        (instance >= the number of gyros/accels) left out with a note."""
        params = scan.parameters
        counts = {
            "gyro": sum(1 for p in _GYR_IDS if params.get(p)),
            "accel": sum(1 for p in _ACC_IDS if params.get(p)),
        }
        kept = []
        for stream in streams:
            sensor = stream.sensors[0] if len(stream.sensors) == 1 else "gyro"
            ids = _GYR_IDS if sensor == "gyro" else _ACC_IDS
            if stream.instance < len(ids) and params.get(ids[stream.instance]):
                stream.device_id = int(params[ids[stream.instance]])
            physical = counts[sensor]
            if stream.source == "raw" and physical and stream.instance >= physical:
                scan.notes.append(
                    f"{stream.name} is the post-filter copy of instance"
                    f" {stream.instance - physical} (INS_RAW_LOG_OPT bit 3): left out"
                )
                continue
            kept.append(stream)
        return kept

    @staticmethod
    def _utc(scan: LogScan, values: np.ndarray) -> None:
        if has_fields(values, ("GWk", "GMS", "TimeUS")):
            week, ms = values["GWk"].astype(np.int64), values["GMS"].astype(np.int64)
            boot_us = values["TimeUS"].astype(np.int64)
            fields = "GPS.GWk/GMS against TimeUS"
        elif has_fields(values, ("Week", "TimeMS", "T")):
            week, ms = values["Week"].astype(np.int64), values["TimeMS"].astype(np.int64)
            boot_us = values["T"].astype(np.int64) * 1000
            fields = "GPS.Week/TimeMS against T"
        else:
            return
        # the first GPS message with a week number: the receiver knows GPS time (as
        # pymavlink's clock does; a time fix can precede a position fix)
        good = np.flatnonzero((week > 0) & (boot_us > 0))
        low, high = UTC_RANGE_US
        for i in good[:16].tolist():
            unix_us = gps_to_unix_us(int(week[i]), int(ms[i]))
            if not (low < unix_us < high and plausible(boot_us[i : i + 1])[0]):
                continue  # a damaged GPS message
            scan.utc_offset_us = unix_us - int(boot_us[i])
            scan.utc_source = f"{fields} (first GPS time in the log; leap seconds of its date)"
            return

    @staticmethod
    def _batches(scan: LogScan, values: np.ndarray) -> None:
        """Count the batch sampler's bursts (ISBH) per IMU and sensor (memory flat)."""
        if not has_fields(values, ("type", "instance")):
            return
        names = _names(values)
        for row in values:
            sensor = "accel" if int(row["type"]) == 0 else "gyro"
            entry = scan.batches.setdefault(
                f"imu{int(row['instance'])}.{sensor}", {"batches": 0, "samples": 0, "rate_hz": None}
            )
            entry["batches"] += 1
            if "smp_cnt" in names:
                entry["samples"] += int(row["smp_cnt"])
            if "smp_rate" in names and entry["rate_hz"] is None and np.isfinite(row["smp_rate"]):
                entry["rate_hz"] = float(row["smp_rate"])

    def chunks(
        self, streams: Sequence[Stream], progress: Any = None
    ) -> Iterator[list[tuple[int, np.ndarray, np.ndarray]]]:
        index = {(s.name.split(" ")[0], s.instance): k for k, s in enumerate(streams)}
        wanted: dict[str, Sequence[str]] = {}
        for name, (_, sensors, _) in IMU_MESSAGES.items():
            label = "".join(c for c in name if not c.isdigit())
            if any(key[0] == label for key in index):
                wanted[name] = (*_TIME, *(c for s in sensors for c in _COLUMNS[s]))
        for chunk in self.log.read(wanted, chunk_size=self.chunk_size, progress=progress):
            out = []
            for name, raw in chunk.data.items():
                source, sensors, _ = IMU_MESSAGES[name]
                label = "".join(c for c in name if not c.isdigit())
                values = _usable(name, raw)
                if values is None:
                    continue
                t = _times(values, sample=source == "raw")
                instance = _instances(name, values)
                # whatever bits a damaged log holds (signalling NaNs): no warnings; the
                # validity counts flag them
                with np.errstate(all="ignore"):
                    triads = np.column_stack(
                        [values[c].astype(np.float64) for s in sensors for c in _COLUMNS[s]]
                    )
                for k in np.unique(instance).tolist():
                    stream = index.get((label, int(k)))
                    if stream is None:
                        continue
                    rows = instance == k
                    out.append((stream, t[rows], triads[rows]))
            if out:
                yield out
