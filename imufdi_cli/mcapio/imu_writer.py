"""Writing IMU arrays to MCAP: bulk CDR encoding of ``sensor_msgs/msg/Imu`` /
``MagneticField`` messages and whole Message records from templates (docs/formats.md, docs/performance.md "Writing")."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import IO

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.errors import UsageError
from imufdi_cli.log import ImuBlock
from imufdi_cli.mcapio.imu_codec import ARRAY_METADATA, NS_PER_S
from imufdi_cli.mcapio.records import (
    MESSAGE_FIXED_CONTENT,
    MESSAGE_HEADER_DTYPE,
    MESSAGE_HEADER_SIZE,
    OP_MESSAGE,
    MessageBatch,
)
from imufdi_cli.mcapio.schemas import IMU_SCHEMA, IMU_SCHEMA_NAME, MAG_SCHEMA, MAG_SCHEMA_NAME
from imufdi_cli.mcapio.writer import McapWriter

# --- encoding ---------------------------------------------------------------------------


def _cdr_string(text: str, position: int) -> tuple[bytes, int]:
    raw = text.encode("utf-8") + b"\0"
    pad = (-position) % 4
    return b"\0" * pad + len(raw).to_bytes(4, "little") + raw, position + pad + 4 + len(raw)


def _template(kind: str, frame_id: str) -> tuple[np.ndarray, dict[str, int]]:
    """One CDR_LE message with zero values and the byte offsets of the stamp and vectors."""
    body = bytearray(b"\0" * 8)  # stamp sec, nanosec (CDR positions 0..7)
    string, position = _cdr_string(frame_id, 8)
    body += string
    pad = (-position) % 8
    body += b"\0" * pad
    position += pad
    offsets = {"sec": 4, "nanosec": 8}

    def f8(values: Sequence[float]) -> bytes:
        return np.asarray(values, dtype="<f8").tobytes()

    if kind == "imu":
        body += f8([0.0, 0.0, 0.0, 1.0])  # orientation (unknown)
        body += f8([-1.0] + [0.0] * 8)  # orientation_covariance[0] = -1: no orientation
        offsets["gyro"] = 4 + position + 13 * 8
        body += f8([0.0] * 12)
        offsets["accel"] = 4 + position + 25 * 8
        body += f8([0.0] * 12)
    else:
        offsets["mag"] = 4 + position
        body += f8([0.0] * 12)
    payload = b"\x00\x01\x00\x00" + bytes(body)
    return np.frombuffer(payload, dtype=np.uint8).copy(), offsets


def _encode_into(
    out: np.ndarray,
    kind: str,
    frame_id: str,
    t_ns: np.ndarray,
    vectors: dict[str, np.ndarray | None],
) -> None:
    """Fill ``out`` (N, L) uint8 (may be a strided view) with N encoded messages."""
    n = t_ns.shape[0]
    template, offsets = _template(kind, frame_id)
    out[:] = template
    sec = np.floor_divide(t_ns, NS_PER_S)
    if n and (int(sec.min()) < -(2**31) or int(sec.max()) >= 2**31):
        raise UsageError("timestamps do not fit a ROS 2 builtin_interfaces/Time (int32 seconds)")
    out[:, offsets["sec"] : offsets["sec"] + 4] = sec.astype("<i4").view(np.uint8).reshape(n, 4)
    nanosec = (t_ns - sec * NS_PER_S).astype("<u4")
    out[:, offsets["nanosec"] : offsets["nanosec"] + 4] = nanosec.view(np.uint8).reshape(n, 4)
    for name in ("gyro", "accel") if kind == "imu" else ("mag",):
        value = vectors.get(name)
        array = np.full((n, 3), np.nan) if value is None else np.asarray(value, dtype="<f8")
        if array.shape != (n, 3):
            raise UsageError(f"{name} must have shape ({n}, 3), got {array.shape}")
        start = offsets[name]
        out[:, start : start + 24] = (
            np.ascontiguousarray(array, dtype="<f8").view(np.uint8).reshape(n, 24)
        )


def encode_messages(
    kind: str,
    frame_id: str,
    channel_id: int,
    t_ns: np.ndarray,
    vectors: dict[str, np.ndarray | None],
    *,
    first_sequence: int = 0,
) -> MessageBatch:
    """Bulk CDR encoding of N Imu (``kind="imu"``) or MagneticField (``"mag"``) messages.

    ``vectors`` maps ``gyro``/``accel`` (or ``mag``) to (N, 3) arrays in SI units; a missing
    vector is written as NaN. Log and publish times are the stamps.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    n = t_ns.shape[0]
    length = _template(kind, frame_id)[0].shape[0]
    out = np.empty((n, length), dtype=np.uint8)
    _encode_into(out, kind, frame_id, t_ns, vectors)
    return MessageBatch(
        channel_id=np.full(n, channel_id, np.uint16),
        sequence=(first_sequence + np.arange(n, dtype=np.int64)).astype(np.uint32),
        log_time=t_ns.copy(),
        publish_time=t_ns.copy(),
        data=out.reshape(-1),
        offset=np.arange(n, dtype=np.int64) * length,
        length=np.full(n, length, np.int64),
    )


def _stamp_fields(t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ROS 2 ``builtin_interfaces/Time`` (sec int32, nanosec uint32) of stamps in ns."""
    sec = np.floor_divide(t_ns, NS_PER_S)
    if t_ns.shape[0] and (int(sec.min()) < -(2**31) or int(sec.max()) >= 2**31):
        raise UsageError("timestamps do not fit a ROS 2 builtin_interfaces/Time (int32 seconds)")
    return sec.astype("<i4"), (t_ns - sec * NS_PER_S).astype("<u4")


def _field_view(records: np.ndarray, start: int, dtype: str, count: int = 1) -> np.ndarray:
    """Writable view of ``count`` ``dtype`` values at byte ``start`` of every record.

    ``records`` is (..., R) uint8 with a contiguous last axis; the result is (..., count).
    """
    width = np.dtype(dtype).itemsize * count
    return records[..., start : start + width].view(dtype)


class _RecordTemplate:
    """Whole Message records (header + CDR Imu payload) of the array's Imu channels, with
    every constant byte filled in, and the byte offsets of the fields that change."""

    def __init__(self, frame_ids: Sequence[str], channel_ids: Sequence[int]) -> None:
        payloads = [_template("imu", frame) for frame in frame_ids]
        lengths = {payload.shape[0] for payload, _ in payloads}
        offsets = {tuple(sorted(o.items())) for _, o in payloads}
        self.uniform = len(lengths) == 1 and len(offsets) == 1
        if not self.uniform:
            return
        length = next(iter(lengths))
        self.record_size = MESSAGE_HEADER_SIZE + length
        self.records = np.empty((len(frame_ids), self.record_size), np.uint8)
        header = np.zeros(len(frame_ids), MESSAGE_HEADER_DTYPE)
        header["opcode"] = OP_MESSAGE
        header["record_length"] = MESSAGE_FIXED_CONTENT + length
        header["channel_id"] = np.asarray(channel_ids, np.uint16)
        self.records[:, :MESSAGE_HEADER_SIZE] = header.view(np.uint8).reshape(len(frame_ids), -1)
        for k, (payload, _) in enumerate(payloads):
            self.records[k, MESSAGE_HEADER_SIZE:] = payload
        fields = MESSAGE_HEADER_DTYPE.fields
        assert fields is not None
        self.at = {name: int(fields[name][1]) for name in ("sequence", "log_time", "publish_time")}
        for name, offset in payloads[0][1].items():
            self.at[name] = MESSAGE_HEADER_SIZE + offset
        # The sequence, log and publish times (end of the record header), the CDR
        # encapsulation and the stamp are one run of bytes, the same for every IMU of a
        # sample: built once per sample and copied as one 32-byte item per record.
        self.stamp_span = (self.at["sequence"], self.at["nanosec"] + 4)
        lo, hi = self.stamp_span
        assert (self.records[:, lo:hi] == self.records[0, lo:hi]).all()

    def stamps(self, t_ns: np.ndarray, sequence: np.ndarray) -> np.ndarray:
        """The bytes of the stamp run (sequence, log and publish times, encapsulation,
        ROS 2 stamp) of N samples, (N, S) uint8, the same for every IMU of a sample.

        ``t_ns`` (N,) int64 ns, ``sequence`` (N,) uint32.

        Raises
        ------
        UsageError
            A stamp outside a ROS 2 ``builtin_interfaces/Time`` (int32 seconds).
        """
        at = self.at
        n = t_ns.shape[0]
        sec, nanosec = _stamp_fields(t_ns)
        lo, hi = self.stamp_span
        stamp = np.empty((n, hi - lo), np.uint8)
        stamp[:] = self.records[0, lo:hi]
        _field_view(stamp, at["sequence"] - lo, "<u4")[:, 0] = sequence
        _field_view(stamp, at["log_time"] - lo, "<u8")[:, 0] = t_ns
        _field_view(stamp, at["publish_time"] - lo, "<u8")[:, 0] = t_ns
        _field_view(stamp, at["sec"] - lo, "<i4")[:, 0] = sec
        _field_view(stamp, at["nanosec"] - lo, "<u4")[:, 0] = nanosec
        return stamp

    def fill(
        self,
        out: np.ndarray,
        stamp: np.ndarray,
        gyro: np.ndarray | None,
        accel: np.ndarray | None,
        *,
        constant: bool = True,
    ) -> None:
        """Write the records of N samples of the m IMUs into ``out`` (N, m, R) uint8.

        ``stamp`` (N, S) uint8 from :meth:`stamps`, gyro/accel (N, m, 3) float64 in SI
        (None: NaN). With ``constant=False`` only the bytes that change (stamp run and
        triads) are written: ``out`` already holds ``self.records`` in every sample. A
        few large copies: the worker thread that runs this needs the GIL only between
        them.
        """
        if constant:
            out[...] = self.records
        lo, hi = self.stamp_span
        item = np.dtype((np.void, hi - lo))
        out[..., lo:hi].view(item)[..., 0] = stamp.view(item)[:, 0][:, None]
        triad = np.dtype((np.void, 24))
        for name, values in (("gyro", gyro), ("accel", accel)):
            at = self.at[name]
            target = out[..., at : at + 24].view(triad)[..., 0]
            if values is None:
                target[...] = np.full(3, np.nan, "<f8").view(triad)[0]
            else:
                # one 24-byte item (x, y, z as little-endian float64) per record
                target[...] = np.ascontiguousarray(values, "<f8").view(triad)[..., 0]


class _ImuRecords:
    """The Message records of a slice of samples, for every IMU (sample-major: for each
    stamp imu0..imu(m-1)), built on the writer's worker thread
    (:class:`~imufdi_cli.mcapio.writer.RecordSource`). Holds its own copies of the
    samples, so the caller may reuse its arrays once ``write_block`` returns, unless
    ``owned``: then the caller has handed the triads over (it never modifies them
    afterwards) and they are kept as they are when already little-endian float64."""

    def __init__(
        self,
        template: _RecordTemplate,
        m: int,
        t_ns: np.ndarray,
        first_sequence: int,
        gyro: np.ndarray | None,
        accel: np.ndarray | None,
        *,
        owned: bool = False,
    ) -> None:
        self.template = template
        self.m = m
        t_ns = np.asarray(t_ns, dtype=np.int64)
        sequence = np.arange(first_sequence, first_sequence + t_ns.shape[0], dtype=np.int64)
        # built here, on the caller's thread (small arrays), so the worker thread's fill is
        # a few large copies; these and the triads are this source's own copies
        self.stamp = template.stamps(t_ns, sequence.astype(np.uint32))
        keep = np.asarray if owned else np.array  # (asarray: no copy of "<f8" arrays)
        self.gyro = None if gyro is None else keep(gyro, dtype="<f8")
        self.accel = None if accel is None else keep(accel, dtype="<f8")

    @property
    def record_size(self) -> int:
        return self.template.record_size

    @property
    def template_rows(self) -> np.ndarray:
        """(m, R) uint8: record ``k`` is row ``k % m`` outside its stamp and triads."""
        return self.template.records

    def __len__(self) -> int:
        return int(self.stamp.shape[0]) * self.m

    def _fill_samples(
        self, out: np.ndarray, first: int, last: int, *, constant: bool = True
    ) -> None:
        """Records of samples ``first..last-1`` into ``out`` ((last - first) m, R)."""
        view = slice(first, last)
        self.template.fill(
            out.reshape(last - first, self.m, -1),
            self.stamp[view],
            None if self.gyro is None else self.gyro[view],
            None if self.accel is None else self.accel[view],
            constant=constant,
        )

    def fill_changing(self, out: np.ndarray, start: int, stop: int) -> None:
        """As :meth:`fill`, into rows that already hold the template (row ``i`` is
        template row ``(start + i) % m``): only stamps and triads are written."""
        self.fill(out, start, stop, constant=False)

    def fill(self, out: np.ndarray, start: int, stop: int, *, constant: bool = True) -> None:
        """Records ``start..stop-1`` (record k: sample k // m, IMU k % m) into ``out``."""
        m = self.m
        position = start
        while position < stop:
            sample, imu = divmod(position, m)
            whole = (stop - position) // m
            if imu == 0 and whole:
                # whole samples, straight into the chunk buffer
                end = position + whole * m
                self._fill_samples(
                    out[position - start : end - start], sample, sample + whole, constant=constant
                )
            else:
                # a sample cut by a chunk boundary: built whole, the rows needed copied
                end = min(stop, (sample + 1) * m)
                one = np.empty((m, self.record_size), np.uint8)
                self._fill_samples(one, sample, sample + 1)
                out[position - start : end - start] = one[imu : imu + end - position]
            position = end


class ImuArrayWriter:
    """Writes an IMU array's samples as one Imu channel per IMU (and MagneticField channels
    when the array has magnetometers), docs/formats.md.

    Parameters
    ----------
    writer : McapWriter
    array : ArrayConfig
        Written as the ``imufdi.array`` metadata record.
    topics : sequence of str, optional
        Imu topic per IMU (default ``/imu<k>/data_raw``); magnetometer topics are the
        same namespace + ``/mag``.
    frame_ids : sequence of str, optional
        ``header.frame_id`` per IMU (default ``imu<k>``).
    """

    def __init__(
        self,
        writer: McapWriter,
        array: ArrayConfig,
        *,
        topics: Sequence[str] | None = None,
        frame_ids: Sequence[str] | None = None,
    ) -> None:
        m = array.n_imus
        self.writer = writer
        self.array = array
        self.topics = (
            list(topics) if topics is not None else [f"/imu{k}/data_raw" for k in range(m)]
        )
        self.frame_ids = list(frame_ids) if frame_ids is not None else [f"imu{k}" for k in range(m)]
        if len(self.topics) != m or len(self.frame_ids) != m:
            raise UsageError(f"need {m} topics and frame ids (one per IMU)")
        imu_schema = writer.register_schema(IMU_SCHEMA_NAME, "ros2msg", IMU_SCHEMA)
        self.imu_channels = [writer.register_channel(t, "cdr", imu_schema) for t in self.topics]
        self.mag_channels: list[int] = []
        if array.has("mag"):
            mag_schema = writer.register_schema(MAG_SCHEMA_NAME, "ros2msg", MAG_SCHEMA)
            self.mag_channels = [
                writer.register_channel(t.rsplit("/", 1)[0] + "/mag", "cdr", mag_schema)
                for t in self.topics
            ]
        writer.add_metadata(ARRAY_METADATA, {"json": array.to_json()})
        self._written = 0
        self._imu_records = _RecordTemplate(self.frame_ids, self.imu_channels)

    def write_block(self, block: ImuBlock, *, owned: bool = False) -> None:
        """Bulk-encode a block (all IMUs) and queue it, messages in time order.

        With ``owned`` the caller hands the block's arrays over: it never modifies them
        afterwards (e.g. ``ingest``, whose parser makes new arrays for every block), so
        the writer keeps them until their records are built instead of copying them. The
        output is the same bytes either way.
        """
        n = len(block)
        if n == 0:
            return
        if block.n_imus != self.array.n_imus:
            raise UsageError(f"block has {block.n_imus} IMUs but the array has {self.array.n_imus}")
        if self._imu_records.uniform and not (self.mag_channels and block.mag is not None):
            self._write_imu_records(block, owned=owned)
            return
        # (kind, frame id, channel id, vectors) of every channel, in message order per sample
        channels: list[tuple[str, str, int, dict[str, np.ndarray | None]]] = []
        for k, channel_id in enumerate(self.imu_channels):
            vectors = {
                "gyro": None if block.gyro is None else block.gyro[:, k],
                "accel": None if block.accel is None else block.accel[:, k],
            }
            channels.append(("imu", self.frame_ids[k], channel_id, vectors))
        if self.mag_channels and block.mag is not None:
            for k, channel_id in enumerate(self.mag_channels):
                channels.append(("mag", self.frame_ids[k], channel_id, {"mag": block.mag[:, k]}))
        lengths = {_template(kind, frame)[0].shape[0] for kind, frame, _, _ in channels}
        c = len(channels)
        ids = np.array([cid for _, _, cid, _ in channels], np.uint16)
        # Bounded memory and cache-friendly: encode in slices of samples.
        step = max(1, (4 << 20) // (c * max(lengths)))
        for start in range(0, n, step):
            stop = min(n, start + step)
            ns = stop - start
            t_ns = block.t_ns[start:stop]
            sequence = np.repeat(
                np.arange(self._written + start, self._written + stop, dtype=np.int64), c
            ).astype(np.uint32)
            if len(lengths) == 1:
                # Sample-major order: for each stamp imu0..imu(m-1) (then magnetometers).
                length = next(iter(lengths))
                out = np.empty((ns, c, length), np.uint8)
                for j, (kind, frame, _, vectors) in enumerate(channels):
                    sliced = {
                        key: None if v is None else v[start:stop] for key, v in vectors.items()
                    }
                    _encode_into(out[:, j, :], kind, frame, t_ns, sliced)
                batch = MessageBatch(
                    channel_id=np.tile(ids, ns),
                    sequence=sequence,
                    log_time=np.repeat(t_ns, c),
                    publish_time=np.repeat(t_ns, c),
                    data=out.reshape(-1),
                    offset=np.arange(ns * c, dtype=np.int64) * length,
                    length=np.full(ns * c, length, np.int64),
                )
            else:
                parts = [
                    encode_messages(
                        kind,
                        frame,
                        cid,
                        t_ns,
                        {key: None if v is None else v[start:stop] for key, v in vectors.items()},
                        first_sequence=self._written + start,
                    )
                    for kind, frame, cid, vectors in channels
                ]
                joined = MessageBatch.concatenate(parts)
                index = np.arange(len(joined))
                batch = joined.select(np.argsort((index % ns) * c + index // ns, kind="stable"))
            self.writer.add_batch(batch)
        self._written += n

    def _write_imu_records(self, block: ImuBlock, *, owned: bool = False) -> None:
        """Imu messages only: queue the block's records, in slices of about 4 MB, to be
        built (constant bytes from a template, then one stamp item and two triad items
        per record) straight into the chunk buffers on the writer's worker threads. The
        stamps are checked here, so a bad one is reported by this call."""
        template = self._imu_records
        m = self.array.n_imus
        n = len(block)
        step = max(1, (4 << 20) // (m * template.record_size))
        ids = np.asarray(self.imu_channels, np.uint16)
        for start in range(0, n, step):
            stop = min(n, start + step)
            source = _ImuRecords(
                template,
                m,
                block.t_ns[start:stop],
                self._written + start,
                None if block.gyro is None else block.gyro[start:stop],
                None if block.accel is None else block.accel[start:stop],
                owned=owned,
            )
            self.writer.add_record_source(
                source, np.tile(ids, stop - start), np.repeat(block.t_ns[start:stop], m)
            )
        self._written += n


def write_array(
    output: str | Path | IO[bytes],
    array: ArrayConfig,
    block: ImuBlock,
    *,
    metadata: dict[str, dict[str, str]] | None = None,
    compression: str = "zstd",
) -> None:
    """Write a whole in-memory array log (``imufdi.array`` metadata plus ``metadata``)."""
    with McapWriter(output, compression=compression) as writer:
        array_writer = ImuArrayWriter(writer, array)
        for name, values in (metadata or {}).items():
            writer.add_metadata(name, values)
        array_writer.write_block(block)
