"""Library entry points: parse a capture into ImuBlocks, or ingest it into MCAP."""

from __future__ import annotations

import itertools
import json
import os
import sys
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.capture.binary import iter_binary_blocks
from imufdi_cli.capture.csvcap import iter_csv_blocks
from imufdi_cli.capture.fullscale import layout_ranges
from imufdi_cli.capture.layout import Layout
from imufdi_cli.capture.stats import IngestStats
from imufdi_cli.errors import CaptureError, ImufdiError
from imufdi_cli.log import ImuBlock
from imufdi_cli.validity import ValidityCounter, apply_calibration

#: default bytes read per round
DEFAULT_CHUNK_SIZE = 1 << 20
#: default uncompressed bytes of Message records per MCAP chunk written by :func:`ingest`
#: (the writer's default is 1 MiB): 4 MiB chunks cost about 10-15 % less CPU per capture
#: byte (fewer per-chunk steps on the writer's threads) and make the file 0.8 % smaller;
#: a chunk then holds about 7 s of a 16-IMU array at 100 Hz (docs/performance.md)
DEFAULT_MCAP_CHUNK_SIZE = 4 << 20

CaptureSource = BinaryIO | bytes | bytearray | memoryview | str | os.PathLike


def _chunks(source: CaptureSource, chunk_size: int) -> Iterator[bytes]:
    if isinstance(source, (bytes, bytearray, memoryview)):
        view = memoryview(source).cast("B")
        for start in range(0, len(view), chunk_size):
            yield bytes(view[start : start + chunk_size])
        return
    if isinstance(source, str) and source == "-":
        yield from _read(sys.stdin.buffer, chunk_size, "stdin")
        return
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        try:
            handle: BinaryIO = open(path, "rb")
        except OSError as err:
            raise CaptureError(f"cannot read capture {path}: {err.strerror}") from err
        with handle:
            yield from _read(handle, chunk_size, str(path))
        return
    yield from _read(source, chunk_size, getattr(source, "name", "capture stream"))


def _read(handle: BinaryIO, chunk_size: int, name: str) -> Iterator[bytes]:
    while True:
        try:
            chunk = handle.read(chunk_size)
        except (OSError, ValueError) as err:
            raise CaptureError(f"cannot read capture {name}: {err}") from err
        if not chunk:
            return
        yield bytes(chunk)


def parse_capture(
    source: CaptureSource,
    layout: Layout,
    *,
    rate_hz: float | None = None,
    strict: bool = False,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> tuple[Iterator[ImuBlock], IngestStats]:
    """Parse a raw capture into consecutive ImuBlocks, streaming.

    Parameters
    ----------
    source : bytes, binary file object or path
        The capture.
    layout : Layout
        From :func:`load_layout`.
    rate_hz : float or None
        Nominal sample rate, Hz; needed only when the layout has no timestamp field
        (timestamps = counter x period, or row/frame index x period).
    strict : bool
        Raise :class:`CaptureError` at the first dropped byte (garbage, bad checksum,
        truncated or duplicated frame, malformed CSV row).
    chunk_size : int
        Bytes read per round (raised to four of the largest frames); memory use is a few
        times this, whatever the capture size.

    Returns
    -------
    blocks : iterator of ImuBlock
        At most one block per chunk; gyro/accel/mag (N, m, 3) in SI, IMU frames.
    stats : IngestStats
        Filled in while iterating; ``stats.complete`` once the iterator is exhausted.

    Raises
    ------
    CaptureError
        Unreadable source, no timestamp and no rate, (strict) dropped bytes. Never any
        other exception, whatever the bytes.
    """
    stats = IngestStats()
    if rate_hz is not None and not (np.isfinite(rate_hz) and rate_hz > 0):
        raise CaptureError(f"rate_hz must be a positive number, got {rate_hz!r}")
    if isinstance(source, (str, os.PathLike)) and str(source) != "-" and not Path(source).is_file():
        raise CaptureError(f"capture {source} does not exist or is not a file")
    if layout.kind == "csv":
        chunks = _chunks(source, max(int(chunk_size), 1))
        return iter_csv_blocks(chunks, layout, stats, rate_hz=rate_hz, strict=strict), stats
    chunk_size = max(int(chunk_size), 4 * layout.max_frame_size, 64)
    chunks = _chunks(source, chunk_size)
    blocks = iter_binary_blocks(chunks, layout, stats, rate_hz=rate_hz, strict=strict)
    # construct the parser now so that a layout without timestamps and rate fails early
    if layout.role("timestamp") is None and rate_hz is None and layout.rate_hz is None:
        raise CaptureError(
            f"layout {layout.name!r} has no timestamp field: give the sample rate (rate_hz)"
        )
    return blocks, stats


def _estimate_rate(block: ImuBlock) -> float:
    if len(block) < 2:
        return 100.0
    steps = np.diff(block.t_ns)
    steps = steps[steps > 0]
    if steps.size == 0:
        return 100.0
    return float(1e9 / np.median(steps))


def ingest(
    source: CaptureSource,
    output: str | os.PathLike | BinaryIO,
    *,
    layout: Layout,
    array: ArrayConfig | None = None,
    rate_hz: float | None = None,
    strict: bool = False,
    compression: str = "zstd",
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    start_time_ns: int | None = None,
    progress: Any = None,
    mcap_chunk_size: int = DEFAULT_MCAP_CHUNK_SIZE,
) -> IngestStats:
    """Parse a capture and write it as an MCAP log (``imufdi ingest``).

    Parameters
    ----------
    source : bytes, binary file object or path
        The capture.
    output : path or binary file object
        The MCAP to write (renamed into place only on success).
    layout : Layout
    array : ArrayConfig or None
        Default: co-aligned, the IMU count of the frames, the rate from the timestamps.
        Its per-IMU calibration, if any, is applied to the samples (``M (raw - b)``) and
        recorded with it in ``imufdi.array``; its ``range`` defaults to the layout's full
        scale (:func:`~imufdi_cli.capture.fullscale.layout_ranges`).
    rate_hz, strict, chunk_size
        As in :func:`parse_capture`.
    compression : str
        MCAP chunk compression (``zstd``, ``lz4``, ``none``).
    start_time_ns : int, optional
        Wall-clock time (ns since the Unix epoch) of the first frame: every stamp is shifted
        by the same offset, so intervals keep the device's timing. Default: the device's own
        time (timestamp field, counter x period, or frame index x period, from 0 at the
        device's epoch), which viewers show as a date near 1970.
    progress : callable, optional
        ``progress(bytes read, capture size in bytes or None)`` (:mod:`imufdi_cli.progress`).
    mcap_chunk_size : int
        Uncompressed bytes of Message records per MCAP chunk (:class:`McapWriter`).

    Returns
    -------
    IngestStats
        Also stored, with the layout and parameters, in the ``imufdi.ingest`` metadata.
    """
    from imufdi_cli import mcapio

    blocks, stats = parse_capture(
        source, layout, rate_hz=rate_hz, strict=strict, chunk_size=chunk_size
    )
    first = next(blocks, None)
    if first is None:
        raise CaptureError(
            f"no frames of layout {layout.name!r} found in the capture "
            f"({stats.bytes_total} bytes read, {stats.frames_bad_checksum} bad checksums, "
            f"{stats.frames_truncated} truncated)"
        )
    if array is None:
        array = ArrayConfig.co_aligned(
            first.n_imus,
            rate_hz=rate_hz or layout.rate_hz or _estimate_rate(first),
            sensors=tuple(s for s in ("gyro", "accel", "mag") if first.get(s) is not None),
        )
    elif array.n_imus != first.n_imus:
        raise CaptureError(
            f"the capture has {first.n_imus} IMUs per sample, the array config {array.n_imus}"
        )
    array = array.with_range(layout_ranges(layout))  # full scale, for the clipping flags
    counter = ValidityCounter(array)
    blocks = (counter.count(b) for b in itertools.chain([first], blocks))
    if array.calibrated:
        blocks = (apply_calibration(b, array) for b in blocks)
    first = next(blocks)
    offset_ns = 0 if start_time_ns is None else int(start_time_ns) - int(first.t_ns[0])

    def anchored(block: ImuBlock) -> ImuBlock:
        return block if offset_ns == 0 else replace(block, t_ns=block.t_ns + offset_ns)

    writer_options: dict[str, Any] = {"compression": compression, "chunk_size": mcap_chunk_size}
    try:
        target = Path(output) if isinstance(output, os.PathLike) else output
        with mcapio.McapWriter(target, **writer_options) as writer:
            imu_writer = mcapio.ImuArrayWriter(writer, array)
            # the parser (and the calibration) make new arrays for every block and nothing
            # here touches them afterwards: handed over to the writer without copies
            imu_writer.write_block(anchored(first), owned=True)
            size = _capture_size(source) if progress is not None else None
            for block in blocks:
                imu_writer.write_block(anchored(block), owned=True)
                if progress is not None:
                    progress(float(stats.bytes_total), size)
            if progress is not None:
                progress(float(stats.bytes_total), size)
            record = {
                "layout": _jsonable(layout.description),
                "layout_name": layout.name,
                "parameters": {
                    "strict": strict,
                    "rate_hz": rate_hz,
                    "compression": compression,
                    "chunk_size": chunk_size,
                    "mcap_chunk_size": mcap_chunk_size,
                    "start_time_ns": start_time_ns,
                    "time_offset_ns": offset_ns,
                },
                "stats": stats.to_dict(),
                "validity": counter.counts,
            }
            writer.add_metadata("imufdi.ingest", {"json": json.dumps(record)})
    except ImufdiError:
        raise
    except (OSError, ValueError) as err:
        raise CaptureError(f"cannot write {output}: {err}") from err
    return stats


def _capture_size(source: Any) -> float | None:
    """Bytes in a capture (a path or bytes), None for streams."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        return float(len(source))
    if isinstance(source, (str, os.PathLike)) and os.fspath(source) != "-":
        try:
            return float(os.path.getsize(source))
        except OSError:
            return None
    return None


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    if isinstance(value, bytes):
        return value.hex(" ")
    return str(value)
