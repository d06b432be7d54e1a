"""Detector status channels (``imufdi_msgs/msg/FdiStatus``) and JSON topics.

One status message per sample and sensor type, on ``/imufdi/<detector>/<sensor_type>``,
with channel metadata ``{"sensor_ids": <JSON list>}``. CDR layout (little-endian, offsets
from the start of the payload, n = number of sensors, F = len(frame_id) + 1 for its NUL,
P = 16 + F rounded up to a multiple of 4, S = P + 8 rounded up so that S - 4 is a
multiple of 8)::

    0    encapsulation 00 01 00 00
    4    int32   header.stamp.sec   8  uint32 header.stamp.nanosec   (the sample's time)
    12   uint32  F, then frame_id bytes and a NUL                     (the array body frame)
    P    int32   decided.sec        P+4 uint32 decided.nanosec       (decision time)
    S    float64 statistic          S+8 float64 threshold
    S+16 bool    alarm              S+20 int32 isolated
    S+24 float64 amplitude          S+32 uint32 len(scores) = n
    S+40 float64 scores[n]          (absent, and no padding, when n = 0)
    I = S+40+8n (S+36 when n = 0)  uint32 len(isolated_set) = n, then n bool bytes
    A = I+4+n rounded up to 4 from the CDR origin (offset 4)  uint32 len(amplitudes) = m
    A+4 rounded up to 8 from the origin  float64 amplitudes[m]  (absent when m = 0)

``m = n`` for detectors that estimate every isolated sensor's amplitude
(``DetectionBlock.amplitudes``), else 0: the amplitude is then ``amplitude`` on the
isolated sensor. With the default frame id ``imu_array`` (F = 10): P = 28, S = 36; for
n = 3: I = 100, A = 108, 112 bytes (m = 0) or 140 (m = 3, amplitudes at 116). Status
channels written before the header and decision time existed (``builtin_interfaces/Time
stamp`` first, then ``statistic``) are still read; their decision time is the sample
time. Channels written before ``amplitudes`` existed read as m = 0.
"""

from __future__ import annotations

import functools
import json
import os
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import IO, TYPE_CHECKING, Any, Protocol

import numpy as np

from imufdi_cli.errors import McapInputError, UsageError
from imufdi_cli.mcapio.cdr import CdrCodec, codec_for
from imufdi_cli.mcapio.cdr_message import decode_json_payloads
from imufdi_cli.mcapio.events import decode_events, is_event_channel
from imufdi_cli.mcapio.records import (
    MESSAGE_FIXED_CONTENT,
    MESSAGE_HEADER_DTYPE,
    MESSAGE_HEADER_SIZE,
    OP_MESSAGE,
    ChannelInfo,
    MessageBatch,
    gather_bytes,
)
from imufdi_cli.mcapio.schemas import STATUS_SCHEMA, STATUS_SCHEMA_NAME, scores_schema
from imufdi_cli.mcapio.source import McapSource, iter_topic

if TYPE_CHECKING:  # the writer is imported where status is written (report only reads)
    from imufdi_cli.mcapio.writer import McapWriter


class DetectionRows(Protocol):
    """What a status channel records of a detector's output for N samples: the fields of
    :class:`imufdi_cli.detectors.base.DetectionBlock` (which satisfies this protocol; the
    readers and writers below the detectors do not import them)."""

    statistic: np.ndarray  # (N,) float64
    threshold: np.ndarray  # (N,) float64
    alarm: np.ndarray  # (N,) bool
    isolated: np.ndarray  # (N,) int: sensor index, or a negative code
    amplitude: np.ndarray  # (N,) float64, SI units of the sensor type
    scores: np.ndarray  # (N, n_s) float64
    amplitudes: np.ndarray | None  # (N, n_s) float64, or None

    def __len__(self) -> int: ...

    def isolation_set(self) -> np.ndarray:
        """(N, n_s) bool."""
        ...

    def amplitude_set(self) -> np.ndarray:
        """(N, n_s) float64."""
        ...


NS_PER_S = 1_000_000_000
STATUS_TOPIC_PREFIX = "/imufdi/"
#: ``header.frame_id`` of status messages: the array body frame the sensors are tested in.
STATUS_FRAME_ID = "imu_array"


@dataclass
class StatusArrays:
    """Detector output read back from status channels (N samples, n sensors).

    Attributes
    ----------
    t_ns : ndarray (N,) int64
        Sample time (``header.stamp``), ns.
    statistic, threshold, amplitude : ndarray (N,) float64
    alarm : ndarray (N,) bool
    isolated : ndarray (N,) int32
    scores : ndarray (N, n) float64
    sensor_ids : list of str
    isolated_set : ndarray (N, n) bool
        Every sensor isolated at each sample.
    amplitudes : ndarray (N, n) float64
        Estimated fault amplitude of every sensor, SI, NaN where not estimated; for
        messages without per-sensor amplitudes (single-isolation detectors, channels
        written before the field existed) ``amplitude`` on the ``isolated`` column.
    decided_ns : ndarray (N,) int64
        When the decision on each sample became available (``decided``), ns; equal to
        ``t_ns`` for channels written without it (``has_decided`` False).
    has_decided : bool
        Whether the channel carries decision times.
    """

    t_ns: np.ndarray
    statistic: np.ndarray
    threshold: np.ndarray
    alarm: np.ndarray
    isolated: np.ndarray
    amplitude: np.ndarray
    scores: np.ndarray
    sensor_ids: list[str]
    isolated_set: np.ndarray | None = None
    decided_ns: np.ndarray | None = None
    has_decided: bool = False
    amplitudes: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


def status_topic(detector: str, sensor_type: str) -> str:
    return f"{STATUS_TOPIC_PREFIX}{detector}/{sensor_type}"


def register_status_channel(
    writer: McapWriter, detector: str, sensor_type: str, sensor_ids: list[str]
) -> int:
    """Register the status channel of a detector and sensor type; returns its channel id."""
    schema_id = writer.register_schema(STATUS_SCHEMA_NAME, "ros2msg", STATUS_SCHEMA)
    return writer.register_channel(
        status_topic(detector, sensor_type),
        "cdr",
        schema_id,
        {"sensor_ids": json.dumps(list(sensor_ids))},
    )


#: the named-scores companion of a status topic: ``/imufdi/<detector>/<type>/scores``
SCORES_TOPIC_SUFFIX = "/scores"


def scores_topic(detector: str, sensor_type: str) -> str:
    """The named-scores companion topic of a status channel."""
    return status_topic(detector, sensor_type) + SCORES_TOPIC_SUFFIX


def scores_fields(sensor_ids: list[str]) -> list[str]:
    """ROS field names of the sensors: ``imu0.gyro.x`` -> ``imu0_gyro_x`` (lower case,
    anything but letters, digits and ``_`` replaced, a leading ``s_`` if the id does not
    start with a letter).

    Raises
    ------
    UsageError
        Two ids give the same field name.
    """
    import re

    fields = []
    for sid in sensor_ids:
        name = re.sub(r"[^a-z0-9_]", "_", sid.lower())
        fields.append(name if name[:1].isalpha() else f"s_{name}")
    if len(set(fields)) != len(fields):
        raise UsageError(f"sensor ids {sensor_ids} do not give distinct field names")
    return fields


def register_scores_channel(
    writer: McapWriter, detector: str, sensor_type: str, sensor_ids: list[str]
) -> int:
    """Register the named-scores companion of a status channel (``scores_topic``; its
    schema has one ``float64`` per sensor, named by :func:`scores_fields`); returns its
    channel id."""
    name, text = scores_schema(scores_fields(list(sensor_ids)))
    schema_id = writer.register_schema(name, "ros2msg", text)
    return writer.register_channel(
        scores_topic(detector, sensor_type),
        "cdr",
        schema_id,
        {
            "sensor_ids": json.dumps(list(sensor_ids)),
            "status_topic": status_topic(detector, sensor_type),
        },
    )


@functools.lru_cache(maxsize=64)
def _scores_template(channel_id: int, frame: bytes, n_scores: int) -> tuple[bytes, int]:
    """The constant bytes of a named-scores Message record and the payload offset of its
    first score (CDR: header, then n float64 aligned to 8 from the origin at offset 4)."""
    scores_at = 4 + _up(12 + len(frame), 8)
    length = scores_at + 8 * n_scores
    payload = bytearray(length)
    payload[0:4] = b"\x00\x01\x00\x00"
    payload[12:16] = struct.pack("<I", len(frame))
    payload[16 : 16 + len(frame)] = frame
    header = np.zeros(1, MESSAGE_HEADER_DTYPE)
    header["opcode"] = OP_MESSAGE
    header["record_length"] = MESSAGE_FIXED_CONTENT + length
    header["channel_id"] = channel_id
    return header.tobytes() + bytes(payload), scores_at


def scores_records(
    channel_id: int, t_ns: np.ndarray, scores: np.ndarray, *, frame_id: str = STATUS_FRAME_ID
) -> np.ndarray:
    """Whole Message records of the named-scores companion, one per sample (the status
    rows' ``scores``; sequence 0..N-1, log and publish time = ``t_ns``).

    Parameters
    ----------
    channel_id : int
    t_ns : ndarray, shape (N,), int64
    scores : ndarray, shape (N, n), float64

    Returns
    -------
    ndarray, shape (N, 31 + L), uint8
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    n = t_ns.shape[0]
    values = np.asarray(scores, dtype=np.float64).reshape(n, -1)
    template, at = _scores_template(
        int(channel_id), frame_id.encode("utf-8") + b"\0", values.shape[1]
    )
    h = MESSAGE_HEADER_SIZE
    records = np.empty((n, len(template)), np.uint8)
    records[:] = np.frombuffer(template, np.uint8)
    _put(records, _HEADER_AT["sequence"], np.arange(n, dtype=np.uint32), "<u4")
    _put(records, _HEADER_AT["log_time"], t_ns, "<u8")
    _put(records, _HEADER_AT["publish_time"], t_ns, "<u8")
    sec = np.floor_divide(t_ns, NS_PER_S)
    _put(records, h + 4, sec, "<i4")
    _put(records, h + 8, t_ns - sec * NS_PER_S, "<u4")
    if values.shape[1]:
        _put(records, h + at, values, "<f8")
    return records


def _up(value: int, align: int) -> int:
    return -(-value // align) * align


def _put(out: np.ndarray, offset: int, values: np.ndarray, dtype: str) -> None:
    """Write one little-endian column (N,) or (N, k) at byte ``offset`` of every row.

    Copied as one ``width``-byte item per row (a 1-D strided copy of N items), not as an
    (N, width) byte block (numpy's byte loop per row costs several times more)."""
    raw = np.ascontiguousarray(values, dtype=dtype)
    count = raw.shape[1] if raw.ndim == 2 else 1
    width = raw.dtype.itemsize * count
    item = np.dtype((np.void, width))
    rows = raw.reshape(out.shape[0], count).view(item)[:, 0]
    out[:, offset : offset + width].view(item)[:, 0] = rows


#: Byte offsets of the Message record header's fields.
_HEADER_AT = {name: int(field[1]) for name, field in (MESSAGE_HEADER_DTYPE.fields or {}).items()}


@functools.lru_cache(maxsize=64)
def _status_template(
    channel_id: int, frame: bytes, n_scores: int, n_amplitudes: int
) -> tuple[bytes, dict[str, int]]:
    """The constant bytes of a status Message record (header and CDR payload: opcode,
    record length, channel id, encapsulation, frame id, sequence lengths, zero padding) and
    the payload offsets of the fields that change (module docstring)."""
    body_decided = _up(12 + len(frame), 4)  # CDR body offsets (payload offset - 4)
    body_stat = _up(body_decided + 8, 8)
    p = 4 + body_stat  # payload offset of statistic
    scores_at = p + 40 if n_scores else p + 36
    set_at = scores_at + 8 * n_scores
    amplitudes_len_at = 4 + _up(set_at + 4 + n_scores - 4, 4)  # CDR aligns from offset 4
    amplitudes_at = 4 + _up(amplitudes_len_at, 8) if n_amplitudes else amplitudes_len_at + 4
    length = amplitudes_at + 8 * n_amplitudes
    payload = bytearray(length)
    payload[0:4] = b"\x00\x01\x00\x00"  # CDR little-endian
    payload[12:16] = struct.pack("<I", len(frame))
    payload[16 : 16 + len(frame)] = frame
    payload[p + 32 : p + 36] = struct.pack("<I", n_scores)
    payload[set_at : set_at + 4] = struct.pack("<I", n_scores)
    payload[amplitudes_len_at : amplitudes_len_at + 4] = struct.pack("<I", n_amplitudes)
    header = np.zeros(1, MESSAGE_HEADER_DTYPE)
    header["opcode"] = OP_MESSAGE
    header["record_length"] = MESSAGE_FIXED_CONTENT + length
    header["channel_id"] = channel_id
    at = {
        "decided": 4 + body_decided,
        "statistic": p,
        "scores": scores_at,
        "set": set_at + 4,
        "amplitudes": amplitudes_at,
        "length": length,
    }
    return header.tobytes() + bytes(payload), at


def status_records(
    channel_id: int,
    t_ns: np.ndarray,
    det: DetectionRows,
    decided_ns: np.ndarray | None = None,
    *,
    frame_id: str = STATUS_FRAME_ID,
) -> np.ndarray:
    """Whole Message records of one status message per sample, for
    :meth:`~imufdi_cli.mcapio.writer.McapWriter.add_records`: the bytes
    :func:`encode_status` + ``add_batch`` write (sequence 0..N-1, log and publish time =
    ``t_ns``), built from a template of the constant bytes and one column write per
    field.

    Parameters
    ----------
    channel_id : int
    t_ns : ndarray, shape (N,), int64
        Sample times, ns (``header.stamp``, the log and publish times).
    det : DetectionRows
        N rows.
    decided_ns : ndarray, shape (N,), int64, optional
        Decision times, ns (default: the sample times, a causal detector).
    frame_id : str
        ``header.frame_id``.

    Returns
    -------
    ndarray, shape (N, 31 + L), uint8
        Row i: the Message record header, then the L-byte CDR payload.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    n = t_ns.shape[0]
    if len(det) != n:
        raise UsageError(f"{len(det)} detector rows for {n} timestamps")
    decided = t_ns if decided_ns is None else np.asarray(decided_ns, dtype=np.int64)
    if decided.shape != t_ns.shape:
        raise UsageError(f"{decided.shape[0]} decision times for {n} timestamps")
    scores = np.asarray(det.scores, dtype=np.float64).reshape(n, -1)
    n_scores = scores.shape[1]
    # per-sensor amplitudes only for detectors that give them (else an empty sequence)
    n_amplitudes = n_scores if det.amplitudes is not None else 0
    template, at = _status_template(
        int(channel_id), frame_id.encode("utf-8") + b"\0", n_scores, n_amplitudes
    )
    h = MESSAGE_HEADER_SIZE
    records = np.empty((n, len(template)), np.uint8)
    records[:] = np.frombuffer(template, np.uint8)
    _put(records, _HEADER_AT["sequence"], np.arange(n, dtype=np.uint32), "<u4")
    _put(records, _HEADER_AT["log_time"], t_ns, "<u8")
    _put(records, _HEADER_AT["publish_time"], t_ns, "<u8")
    sec = np.floor_divide(t_ns, NS_PER_S)
    _put(records, h + 4, sec, "<i4")
    _put(records, h + 8, t_ns - sec * NS_PER_S, "<u4")
    dsec = np.floor_divide(decided, NS_PER_S)
    _put(records, h + at["decided"], dsec, "<i4")
    _put(records, h + at["decided"] + 4, decided - dsec * NS_PER_S, "<u4")
    p = h + at["statistic"]
    _put(records, p, det.statistic, "<f8")
    _put(records, p + 8, det.threshold, "<f8")
    records[:, p + 16] = np.asarray(det.alarm, dtype=bool)
    _put(records, p + 20, det.isolated, "<i4")
    _put(records, p + 24, det.amplitude, "<f8")
    if n_scores:
        _put(records, h + at["scores"], scores, "<f8")
        _put(records, h + at["set"], det.isolation_set().reshape(n, n_scores), "u1")
    if n_amplitudes:
        _put(records, h + at["amplitudes"], det.amplitude_set().reshape(n, n_amplitudes), "<f8")
    return records


def encode_status(
    channel_id: int,
    t_ns: np.ndarray,
    det: DetectionRows,
    decided_ns: np.ndarray | None = None,
    *,
    frame_id: str = STATUS_FRAME_ID,
) -> MessageBatch:
    """Bulk CDR encoding of one status message per sample (log time = ``t_ns``): the
    messages of :func:`status_records` as a batch (its payloads are views into the
    records).

    Parameters
    ----------
    channel_id : int
    t_ns : ndarray, shape (N,), int64
        Sample times, ns (``header.stamp`` and the message log time).
    det : DetectionRows
        N rows.
    decided_ns : ndarray, shape (N,), int64, optional
        Decision times, ns (default: the sample times, a causal detector).
    frame_id : str
        ``header.frame_id``.
    """
    records = status_records(channel_id, t_ns, det, decided_ns, frame_id=frame_id)
    n, size = records.shape
    t_ns = np.asarray(t_ns, dtype=np.int64)
    return MessageBatch(
        channel_id=np.full(n, channel_id, np.uint16),
        sequence=np.arange(n, dtype=np.int64).astype(np.uint32),
        log_time=t_ns.copy(),
        publish_time=t_ns.copy(),
        data=records.reshape(-1),
        offset=np.arange(n, dtype=np.int64) * size + MESSAGE_HEADER_SIZE,
        length=np.full(n, size - MESSAGE_HEADER_SIZE, np.int64),
    )


def _is_status(channel: ChannelInfo) -> bool:
    return (
        channel.schema is not None
        and channel.schema.name == STATUS_SCHEMA_NAME
        and channel.message_encoding == "cdr"
        and channel.topic.startswith(STATUS_TOPIC_PREFIX)
        and channel.topic.count("/") == 3
    )


def _decode_status(
    batch: MessageBatch,
    channel: ChannelInfo,
    amplitude_columns: bool = True,
    score_columns: bool = True,
) -> dict[str, np.ndarray]:
    assert channel.schema is not None
    codec = codec_for(channel.schema.name, channel.schema.data)
    stamp = "header.stamp" if "header.stamp.sec" in codec.layout.leaves else "stamp"
    scalars = {
        "sec": (f"{stamp}.sec", "i4"),
        "nanosec": (f"{stamp}.nanosec", "u4"),
        "statistic": ("statistic", "f8"),
        "threshold": ("threshold", "f8"),
        "alarm": ("alarm", "u1"),
        "isolated": ("isolated", "i4"),
        "amplitude": ("amplitude", "f8"),
    }
    if "decided.sec" in codec.layout.leaves:
        scalars["decided_sec"] = ("decided.sec", "i4")
        scalars["decided_nanosec"] = ("decided.nanosec", "u4")
    has_amplitudes = "amplitudes" in codec.layout.leaves
    paths = [p for p, _ in scalars.values()] + ["scores", "isolated_set"]
    paths += ["amplitudes"] if has_amplitudes else []
    uniform = codec.uniform_rows(batch, paths)
    if uniform is not None:
        return _decode_uniform(*uniform, scalars, amplitude_columns, score_columns)
    little, positions, sizes = codec.positions(batch, paths)
    raw = {
        key: codec.read(batch, little, positions[path], code, 1)[:, 0]
        for key, (path, code) in scalars.items()
    }
    out = _scalar_fields(raw)
    counts = sizes["scores"]
    n = len(batch)
    width = int(counts.max()) if n else 0
    scores = np.full((n, width), np.nan)
    if n and width and bool(np.all(counts == width)):
        scores = codec.read(batch, little, positions["scores"], "f8", width).astype(np.float64)
    elif n and width:
        for i in range(n):  # ragged scores (not written by imufdi): rare, slow path
            raw_scores = gather_bytes(
                batch.data, positions["scores"][i : i + 1], 8 * int(counts[i])
            )
            scores[i, : counts[i]] = raw_scores.view("<f8" if little[i] else ">f8")[0]
    out["scores"] = scores
    set_counts = sizes["isolated_set"]
    isolated_set = np.zeros((n, width), dtype=bool)
    if n and width and bool(np.all(set_counts == width)):
        isolated_set = codec.read(batch, little, positions["isolated_set"], "u1", width) != 0
    out["isolated_set"] = isolated_set
    out["amplitudes"] = _amplitudes(batch, codec, little, positions, sizes, out, width)
    return out


def _scalar_fields(raw: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The per-message fields of a status batch from its raw scalar columns (copies)."""
    out: dict[str, np.ndarray] = {
        "t_ns": raw["sec"].astype(np.int64) * NS_PER_S + raw["nanosec"].astype(np.int64),
        "statistic": raw["statistic"].astype(np.float64),
        "threshold": raw["threshold"].astype(np.float64),
        "alarm": raw["alarm"] != 0,
        "isolated": raw["isolated"].astype(np.int32),
        "amplitude": raw["amplitude"].astype(np.float64),
    }
    if "decided_sec" in raw:
        out["decided_ns"] = raw["decided_sec"].astype(np.int64) * NS_PER_S + raw[
            "decided_nanosec"
        ].astype(np.int64)
    return out


def _decode_uniform(
    rows: np.ndarray,
    at: dict[str, int],
    sizes: dict[str, int],
    scalars: dict[str, tuple[str, str]],
    amplitude_columns: bool = True,
    score_columns: bool = True,
) -> dict[str, np.ndarray]:
    """:func:`_decode_status` of messages that all have their fields at the same offsets
    (:meth:`~imufdi_cli.mcapio.cdr.CdrCodec.uniform_rows`: the same length, little-endian,
    the same frame id length and sequence counts; what ``detect`` writes): each field is
    one strided copy out of the (N, L) payload bytes ``rows``, at its offset ``at``. The
    same arrays as the general path, every one a copy (``rows`` may view a buffer that
    is reused); without ``amplitude_columns``, no ``amplitudes`` when the messages carry
    none per sensor, without ``score_columns`` ``best_score`` instead of ``scores``
    (:func:`iter_status`)."""
    n = rows.shape[0]

    def column(path: str, code: str, count: int = 1) -> np.ndarray:
        width = int(np.dtype(code).itemsize) * count
        return rows[:, at[path] : at[path] + width].view("<" + code)

    raw = {key: column(path, code)[:, 0] for key, (path, code) in scalars.items()}
    out = _scalar_fields(raw)
    width = sizes["scores"]
    if not score_columns:
        from imufdi_cli.sweep import best_columns

        # read in place: the (k, n) scores are not copied
        scores = column("scores", "f8", width) if width else np.full((n, 0), np.nan)
        out["best_score"] = best_columns(scores)
    elif width:
        out["scores"] = column("scores", "f8", width).astype(np.float64)
    else:
        out["scores"] = np.full((n, 0), np.nan)
    if width and sizes["isolated_set"] == width:
        out["isolated_set"] = column("isolated_set", "u1", width) != 0
    else:
        out["isolated_set"] = np.zeros((n, width), dtype=bool)
    if width and sizes.get("amplitudes") == width:
        out["amplitudes"] = column("amplitudes", "f8", width).astype(np.float64)
    elif amplitude_columns:
        amplitudes = np.full((n, width), np.nan)
        isolated = out["isolated"]
        one = np.flatnonzero((isolated >= 0) & (isolated < width))
        amplitudes[one, isolated[one]] = out["amplitude"][one]
        out["amplitudes"] = amplitudes
    return out


def _amplitudes(
    batch: MessageBatch,
    codec: CdrCodec,
    little: np.ndarray,
    positions: dict[str, np.ndarray],
    sizes: dict[str, np.ndarray],
    rows: dict[str, np.ndarray],
    width: int,
) -> np.ndarray:
    """(N, width) per-sensor amplitudes: the ``amplitudes`` field where a message carries
    one per sensor; elsewhere (an empty field, or a channel written before it existed)
    ``amplitude`` on the column of ``isolated`` and NaN on the others, as
    :meth:`DetectionBlock.amplitude_set` gives for detectors that estimate one."""
    n = len(batch)
    out = np.full((n, width), np.nan)
    isolated = rows["isolated"]
    one = np.flatnonzero((isolated >= 0) & (isolated < width))
    out[one, isolated[one]] = rows["amplitude"][one]
    if "amplitudes" not in positions or not (n and width):
        return out
    full = sizes["amplitudes"] == width
    if bool(full.any()):
        out[full] = codec.read(
            batch.select(full), little[full], positions["amplitudes"][full], "f8", width
        )
    return out


def _channel_ids(channel: ChannelInfo) -> list[str]:
    from imufdi_cli.jsonin import ListOf, Str, check, loads

    where = f"{channel.topic}: sensor_ids metadata"
    ids = loads(channel.metadata.get("sensor_ids", "[]"), where, McapInputError)
    return list(check(ids, ListOf(Str()), where, McapInputError))


def iter_status(
    source: McapSource,
    detector: str | None = None,
    *,
    others: Callable[[MessageBatch, ChannelInfo], None] | None = None,
    others_wanted: Callable[[ChannelInfo], bool] | None = None,
    amplitude_columns: bool = True,
    score_columns: bool = True,
) -> Iterator[tuple[str, str, list[str], dict[str, np.ndarray]]]:
    """Stream the status channels batch by batch (memory: one chunk). ``others`` is called
    with the messages of every other channel, batch by batch, in the same pass.

    Chunks that hold none of the status channels read (and, with ``others``, no channel
    ``others_wanted`` accepts) are stepped over without being decompressed
    (:meth:`~imufdi_cli.mcapio.source.McapSource.skip_chunks_without`: an annotated
    log's IMU chunks, most of its bytes); ``others`` without ``others_wanted`` is called
    for everything.

    Yields
    ------
    detector, sensor_type, sensor_ids, rows
        ``rows`` maps ``t_ns``, ``statistic``, ``threshold``, ``alarm``, ``isolated``,
        ``amplitude``, ``scores`` (k, n), ``isolated_set`` (k, n), ``amplitudes`` (k, n)
        and, when the channel carries it, ``decided_ns`` to the next k rows of that
        channel, in file order. With ``amplitude_columns`` False, ``amplitudes`` is
        left out of rows whose messages carry no per-sensor amplitudes (the
        single-isolation detectors'): ``amplitude`` on the ``isolated`` column is the
        whole of it (:meth:`~imufdi_cli.metrics.MetricsAccumulator.update` takes
        either), and the (k, n) array of NaN is not made. With ``score_columns`` False,
        rows of channels laid out alike (what ``detect`` writes) carry ``best_score``
        (k,) int64 instead of ``scores``: the column of each row's first largest finite
        score, -1 where none is finite (:func:`imufdi_cli.sweep.best_columns`, all the
        scoring reads of the scores), found in the payloads without copying the (k, n)
        scores out; other rows still carry ``scores``.
    """
    if others is None or others_wanted is not None:

        def wanted(channel: ChannelInfo) -> bool:
            if _is_status(channel):
                return detector is None or channel.topic.split("/")[2] == detector
            return others_wanted is not None and others_wanted(channel)

        source.skip_chunks_without(wanted)
    ids_of: dict[int, tuple[ChannelInfo, list[str]]] = {}  # sensor ids, parsed once
    for batch in source.batches():
        # (np.flatnonzero(bincount): np.unique's first call imports numpy.ma, 20 ms)
        for cid in np.flatnonzero(np.bincount(batch.channel_id)).tolist():
            channel = source.channels[cid]
            if not _is_status(channel):
                if others is not None:
                    others(batch.select(batch.channel_id == cid), channel)
                continue
            det = channel.topic.split("/")[2]
            if detector is not None and det != detector:
                continue
            sub = batch.select(batch.channel_id == cid)
            known = ids_of.get(cid)
            if known is None or known[0] is not channel:
                known = ids_of[cid] = (channel, _channel_ids(channel))
            yield (
                det,
                channel.topic.split("/")[3],
                list(known[1]),
                _decode_status(sub, channel, amplitude_columns, score_columns),
            )


def read_status(
    source: str | os.PathLike[str] | IO[bytes] | McapSource, detector: str | None = None
) -> dict[tuple[str, str], StatusArrays]:
    """Read every status channel (optionally of one detector) into memory.

    Returns
    -------
    dict
        ``(detector, sensor_type)`` -> StatusArrays, in file order of the messages.
    """
    own = not isinstance(source, McapSource)
    src = McapSource(source) if not isinstance(source, McapSource) else source
    parts: dict[tuple[str, str], list[dict[str, np.ndarray]]] = {}
    ids_of: dict[tuple[str, str], list[str]] = {}
    try:
        for det, sensor_type, ids, rows in iter_status(src, detector):
            parts.setdefault((det, sensor_type), []).append(rows)
            ids_of[(det, sensor_type)] = ids
    finally:
        if own:
            src.close()
    result: dict[tuple[str, str], StatusArrays] = {}
    for key, pieces in parts.items():
        width = max(p["scores"].shape[1] for p in pieces)

        def cat(name: str, pieces: list[dict[str, np.ndarray]] = pieces) -> np.ndarray:
            return np.concatenate([p[name] for p in pieces])

        def padded(
            name: str, fill: Any, pieces: list[dict[str, np.ndarray]] = pieces, width: int = width
        ) -> np.ndarray:
            return np.concatenate(
                [
                    np.pad(p[name], ((0, 0), (0, width - p[name].shape[1])), constant_values=fill)
                    for p in pieces
                ]
            )

        t_ns = cat("t_ns")
        has_decided = all("decided_ns" in p for p in pieces)
        result[key] = StatusArrays(
            t_ns=t_ns,
            statistic=cat("statistic"),
            threshold=cat("threshold"),
            alarm=cat("alarm"),
            isolated=cat("isolated"),
            amplitude=cat("amplitude"),
            scores=padded("scores", np.nan),
            sensor_ids=ids_of[key],
            isolated_set=padded("isolated_set", False),
            amplitudes=padded("amplitudes", np.nan),
            decided_ns=cat("decided_ns") if has_decided else t_ns.copy(),
            has_decided=has_decided,
        )
    return result


def read_json_topic(
    source: str | os.PathLike[str] | IO[bytes] | McapSource, topic: str
) -> list[tuple[int, Any]]:
    """All messages of a JSON channel as ``(log_time ns, decoded object)``, in file order.

    The imufdi event topics (``/imufdi/truth``, ``/imufdi/events``), CDR since this version,
    are decoded to the same dicts (see :func:`imufdi_cli.mcapio.events.read_events`).
    """
    out: list[tuple[int, Any]] = []
    for channel, sub in iter_topic(source, topic):
        if channel.message_encoding != "json" and is_event_channel(channel):
            out.extend(zip(sub.log_time.tolist(), decode_events(sub, channel)))
            continue
        if channel.message_encoding != "json":
            raise McapInputError(
                f"topic {topic} has message encoding {channel.message_encoding!r}, not json"
            )
        out.extend(zip(sub.log_time.tolist(), decode_json_payloads(sub)))
    return out
