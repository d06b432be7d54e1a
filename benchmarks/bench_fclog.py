"""Flight-controller log readers: imufdi's streaming readers against pyulog and pymavlink.

Why imufdi reads ULog and DataFlash itself instead of through pyulog / pymavlink's
DFReader, measured: the time to read the IMU messages of a log and the peak traced memory
(tracemalloc) for a log of length L and 4 L, on logs made at run time:

- ULog: 3 IMUs, ``sensor_accel`` and ``sensor_gyro`` at ``--rate`` Hz each (the topics of a
  full-rate ``logger_topics.txt``), plus a 50 Hz ``vehicle_attitude``-sized topic;
  pyulog ``ULog(path, message_name_filter_list=[...])`` (it loads every message of the
  topics asked for into memory) against ``ULogFile.read`` of the same topics, chunk by
  chunk;
- DataFlash: 3 IMUs in ``IMU`` messages at ``--rate`` Hz (IMU_FAST logging) plus a 50 Hz
  attitude message; pymavlink ``DFReader_binary`` + ``recv_match(type="IMU")`` (one Python
  object per message) against ``DataFlashFile.read``;
- the full ``imufdi ingest`` of the same logs (both passes, alignment, MCAP write).

Ratios are against the library measured in the same run. Memory is bounded by the
readers' 4 MiB chunks: flat in log length once L is a few chunks (the default 60 s logs
are 18 and 10 MB; with ``--seconds 10`` L is under one chunk and 4 L above it, so the
ratio is above 1). Prints the load average.

Usage: python benchmarks/bench_fclog.py [--seconds 60] [--rate 1000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import gc
import os
import struct
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ULOG_ACCEL = (
    "uint64_t timestamp;uint64_t timestamp_sample;uint32_t device_id;float x;float y;float z;"
    "float temperature;uint32_t error_count;uint8_t[3] clip_counter;uint8_t samples;"
)
ULOG_OTHER = "uint64_t timestamp;float[4] q;float[4] delta_q_reset;uint8_t quat_reset_counter;"


def _ulog_message(kind: str, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def make_ulog(path: Path, seconds: float, rate: float, seed: int = 0) -> int:
    """A ULog of 3 IMUs' sensor_accel/sensor_gyro at ``rate`` and a 50 Hz other topic."""
    rng = np.random.default_rng(seed)
    head = b"ULog\x01\x12\x35\x01" + struct.pack("<Q", 0)
    head += _ulog_message("B", bytes(40))
    head += _ulog_message("F", f"sensor_accel:{ULOG_ACCEL}".encode())
    head += _ulog_message("F", f"sensor_gyro:{ULOG_ACCEL}".encode())
    head += _ulog_message("F", f"vehicle_attitude:{ULOG_OTHER}".encode())
    key = b"char[3] sys_name"
    head += _ulog_message("I", bytes([len(key)]) + key + b"PX4")
    topics = [("sensor_accel", k) for k in range(3)] + [("sensor_gyro", k) for k in range(3)]
    for msg_id, (topic, multi) in enumerate([*topics, ("vehicle_attitude", 0)]):
        head += _ulog_message("A", bytes([multi]) + struct.pack("<H", msg_id) + topic.encode())
    n = int(seconds * rate)
    payload = np.dtype(
        [("size", "<u2"), ("kind", "u1"), ("id", "<u2"), ("t", "<u8"), ("ts", "<u8"),
         ("dev", "<u4"), ("xyz", "<f4", (3,)), ("temp", "<f4"), ("err", "<u4"),
         ("clip", "u1", (3,)), ("samples", "u1")]
    )  # fmt: skip
    parts = []
    times = []
    for msg_id, (_, multi) in enumerate(topics):
        rows = np.zeros(n, payload)
        rows["size"] = payload.itemsize - 3
        rows["kind"] = ord("D")
        rows["id"] = msg_id
        t = 1_000_000 + (np.arange(n) * (1e6 / rate)).astype(np.int64) + 37 * multi
        rows["t"], rows["ts"], rows["dev"] = t + 100, t, 1000 + multi
        rows["xyz"] = rng.normal(0.0, 0.1, (n, 3))
        parts.append(rows.tobytes())
        times.append(t)
    other = np.dtype(
        [
            ("size", "<u2"),
            ("kind", "u1"),
            ("id", "<u2"),
            ("t", "<u8"),
            ("q", "<f4", (9,)),
            ("r", "u1"),
        ]
    )
    m = int(seconds * 50)
    rows = np.zeros(m, other)
    rows["size"], rows["kind"], rows["id"] = other.itemsize - 3, ord("D"), len(topics)
    rows["t"] = 1_000_000 + np.arange(m) * 20_000
    # interleave in time order, as the logger writes them
    sizes = [payload.itemsize] * len(topics)
    records = [np.frombuffer(p, dtype=(np.void, s)) for p, s in zip(parts, sizes)]
    stamps = np.concatenate([*times, rows["t"].astype(np.int64)])
    blobs = [bytes(r) for group in records for r in group] + [
        bytes(r) for r in rows.view((np.void, other.itemsize))
    ]
    order = np.argsort(stamps, kind="stable")
    data = head + b"".join(blobs[i] for i in order.tolist())
    path.write_bytes(data)
    return len(data)


def make_dataflash(path: Path, seconds: float, rate: float, seed: int = 0) -> int:
    """A DataFlash log of 3 IMUs' IMU messages at ``rate`` and a 50 Hz attitude message."""
    rng = np.random.default_rng(seed)

    def fmt(kind: int, length: int, name: str, chars: str, columns: str) -> bytes:
        return b"\xa3\x95\x80" + struct.pack(
            "<BB4s16s64s", kind, length, name.encode(), chars.encode(), columns.encode()
        )

    imu = np.dtype(
        [("h", "u1", (3,)), ("t", "<u8"), ("i", "u1"), ("g", "<f4", (3,)), ("a", "<f4", (3,)),
         ("eg", "<u4"), ("ea", "<u4"), ("temp", "<f4"), ("gh", "u1"), ("ah", "u1"),
         ("ghz", "<u2"), ("ahz", "<u2")]
    )  # fmt: skip
    att = np.dtype([("h", "u1", (3,)), ("t", "<u8"), ("v", "<f4", (8,))])
    head = fmt(128, 89, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")
    head += fmt(
        129,
        imu.itemsize,
        "IMU",
        "QBffffffIIfBBHH",
        "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz",
    )
    head += fmt(130, att.itemsize, "ATT", "Qffffffff", "TimeUS,a,b,c,d,e,f,g,h")
    n = int(seconds * rate)
    rows = np.zeros((n, 3), imu)
    rows["h"] = [0xA3, 0x95, 129]
    rows["t"] = (1_000_000 + np.arange(n) * (1e6 / rate)).astype(np.int64)[:, None]
    rows["i"] = np.arange(3)
    rows["g"] = rng.normal(0.0, 0.01, (n, 3, 3))
    rows["a"] = rng.normal(0.0, 0.1, (n, 3, 3))
    m = int(seconds * 50)
    other = np.zeros(m, att)
    other["h"] = [0xA3, 0x95, 130]
    other["t"] = 1_000_000 + np.arange(m) * 20_000
    stamps = np.concatenate([rows["t"].reshape(-1).astype(np.int64), other["t"].astype(np.int64)])
    blobs = [r.tobytes() for r in rows.reshape(-1)] + [r.tobytes() for r in other]
    order = np.argsort(stamps, kind="stable")
    data = head + b"".join(blobs[i] for i in order.tolist())
    path.write_bytes(data)
    return len(data)


def read_pyulog(path: Path) -> int:
    from pyulog import ULog

    log = ULog(str(path), message_name_filter_list=["sensor_accel", "sensor_gyro"])
    return sum(len(d.data["timestamp"]) for d in log.data_list)


def read_imufdi_ulog(path: Path) -> int:
    from imufdi_cli.fclog.ulog import ULogFile

    wanted = {
        t: ("timestamp", "timestamp_sample", "x", "y", "z") for t in ("sensor_accel", "sensor_gyro")
    }
    return sum(len(v) for chunk in ULogFile(path).read(wanted) for v in chunk.data.values())


def read_dfreader(path: Path) -> int:
    from pymavlink import DFReader

    reader = DFReader.DFReader_binary(str(path), zero_time_base=True)
    rows = []
    while True:
        message = reader.recv_match(type="IMU")
        if message is None:
            return len(rows)
        rows.append(
            (
                message.TimeUS,
                message.I,
                message.GyrX,
                message.GyrY,
                message.GyrZ,
                message.AccX,
                message.AccY,
                message.AccZ,
            )
        )


def read_imufdi_dataflash(path: Path) -> int:
    from imufdi_cli.fclog.dataflash import DataFlashFile

    columns = ("TimeUS", "I", "GyrX", "GyrY", "GyrZ", "AccX", "AccY", "AccZ")
    return sum(
        len(v) for chunk in DataFlashFile(path).read({"IMU": columns}) for v in chunk.data.values()
    )


def ingest(path: Path) -> int:
    from imufdi_cli.fclog import ingest_flight_log

    with tempfile.TemporaryDirectory() as out:
        return int(ingest_flight_log(path, Path(out) / "out.mcap").record["alignment"]["samples"])


def timed(fn: Callable[[Path], int], path: Path, repeat: int) -> tuple[float, int]:
    best = float("inf")
    count = 0
    for _ in range(repeat):
        gc.collect()
        start = time.perf_counter()
        count = fn(path)
        best = min(best, time.perf_counter() - start)
    return best, count


def peak(fn: Callable[[Path], Any], path: Path) -> float:
    gc.collect()
    tracemalloc.start()
    fn(path)
    _, top = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return top / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="log length L")
    parser.add_argument("--rate", type=float, default=1000.0, help="IMU message rate, Hz")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    print(f"load average before: {os.getloadavg()}")
    with tempfile.TemporaryDirectory() as folder:
        for label, make, library, ours, lib_name in (
            ("ULog", make_ulog, read_pyulog, read_imufdi_ulog, "pyulog"),
            ("DataFlash", make_dataflash, read_dfreader, read_imufdi_dataflash, "DFReader"),
        ):
            paths = {}
            for factor in (1, 4):
                path = Path(folder) / f"{label}-{factor}.log"
                size = make(path, args.seconds * factor, args.rate)
                paths[factor] = path
                print(f"{label}: {args.seconds * factor:g} s, {size / 1e6:.1f} MB")
            path = paths[1]
            t_lib, n_lib = timed(library, path, 1 if lib_name == "DFReader" else args.repeat)
            t_ours, n_ours = timed(ours, path, args.repeat)
            t_ingest, samples = timed(ingest, path, args.repeat)
            assert n_lib == n_ours, (n_lib, n_ours)
            size = path.stat().st_size / 1e6
            print(
                f"  {lib_name:9s} read  {t_lib:7.3f} s  {size / t_lib:7.1f} MB/s  ({n_lib} messages)"
            )
            print(
                f"  imufdi    read  {t_ours:7.3f} s  {size / t_ours:7.1f} MB/s  ratio {t_lib / t_ours:5.1f}x faster"
            )
            print(
                f"  imufdi ingest   {t_ingest:7.3f} s  {size / t_ingest:7.1f} MB/s  ({samples} array samples, both passes + MCAP)"
            )
            for name, fn in ((lib_name, library), ("imufdi", ours)):
                small, large = peak(fn, paths[1]), peak(fn, paths[4])
                print(
                    f"  peak memory {name:9s} L: {small:7.1f} MB  4L: {large:7.1f} MB  ratio {large / small:4.2f}"
                )
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
