"""Detector status channels (``imufdi_msgs/msg/FdiStatus``) and JSON topics.

One status message per sample and sensor type, on ``/imufdi/<detector>/<sensor_type>``,
with channel metadata ``{"sensor_ids": <JSON list>}``. Fixed CDR layout (little-endian,
offsets from the start of the payload, n = number of sensors)::

    0   encapsulation 00 01 00 00
    4   int32   stamp.sec          8  uint32 stamp.nanosec
    12  float64 statistic          20 float64 threshold
    28  bool    alarm              32 int32   isolated
    36  float64 amplitude          44 uint32  len(scores) = n
    52  float64 scores[n]          (absent, and no padding, when n = 0)
    52+8n (48 when n = 0)  uint32 len(isolated_set) = n, then n bool bytes
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from typing import IO, TYPE_CHECKING, Any

import numpy as np

from imufdi_cli.errors import McapInputError, UsageError
from imufdi_cli.mcapio.cdr import codec_for, decode_json_payloads
from imufdi_cli.mcapio.events import decode_events, is_event_channel
from imufdi_cli.mcapio.records import ChannelInfo, McapWriter, MessageBatch, gather_bytes
from imufdi_cli.mcapio.schemas import STATUS_SCHEMA, STATUS_SCHEMA_NAME
from imufdi_cli.mcapio.source import McapSource

if TYPE_CHECKING:
    from imufdi_cli.detectors.base import DetectionBlock

NS_PER_S = 1_000_000_000
STATUS_TOPIC_PREFIX = "/imufdi/"

_FIXED = np.dtype(
    [
        ("encapsulation", "<u4"),
        ("sec", "<i4"),
        ("nanosec", "<u4"),
        ("statistic", "<f8"),
        ("threshold", "<f8"),
        ("alarm", "u1"),
        ("pad", "u1", (3,)),
        ("isolated", "<i4"),
        ("amplitude", "<f8"),
        ("n_scores", "<u4"),
    ]
)


@dataclass
class StatusArrays:
    """Detector output read back from status channels (N samples, n sensors).

    Attributes
    ----------
    t_ns : ndarray (N,) int64
    statistic, threshold, amplitude : ndarray (N,) float64
    alarm : ndarray (N,) bool
    isolated : ndarray (N,) int32
    scores : ndarray (N, n) float64
    sensor_ids : list of str
    isolated_set : ndarray (N, n) bool
        Every sensor isolated at each sample.
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


def encode_status(channel_id: int, t_ns: np.ndarray, det: DetectionBlock) -> MessageBatch:
    """Bulk CDR encoding of one status message per sample (log time = ``t_ns``)."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    n = t_ns.shape[0]
    if len(det) != n:
        raise UsageError(f"{len(det)} detector rows for {n} timestamps")
    scores = np.asarray(det.scores, dtype=np.float64).reshape(n, -1)
    n_scores = scores.shape[1]
    # scores start at CDR position 48 (payload byte 52): 4 bytes of padding after n_scores.
    scores_end = _FIXED.itemsize + (4 + 8 * n_scores if n_scores else 0)
    length = scores_end + 4 + n_scores  # isolated_set: u32 count (4-aligned) + n bools
    isolated_set = det.isolation_set().reshape(n, n_scores)
    out = np.zeros((n, length), dtype=np.uint8)
    fixed = np.zeros(n, dtype=_FIXED)
    fixed["encapsulation"] = 0x0100  # bytes 00 01 00 00: CDR little-endian
    sec = np.floor_divide(t_ns, NS_PER_S)
    fixed["sec"] = sec
    fixed["nanosec"] = t_ns - sec * NS_PER_S
    fixed["statistic"] = det.statistic
    fixed["threshold"] = det.threshold
    fixed["alarm"] = np.asarray(det.alarm, dtype=bool)
    fixed["isolated"] = det.isolated
    fixed["amplitude"] = det.amplitude
    fixed["n_scores"] = n_scores
    out[:, : _FIXED.itemsize] = fixed.view(np.uint8).reshape(n, _FIXED.itemsize)
    if n_scores:
        out[:, _FIXED.itemsize + 4 : scores_end] = np.ascontiguousarray(scores, "<f8").view(
            np.uint8
        )
    out[:, scores_end : scores_end + 4] = np.array([n_scores], "<u4").view(np.uint8)
    out[:, scores_end + 4 :] = isolated_set
    return MessageBatch(
        channel_id=np.full(n, channel_id, np.uint16),
        sequence=np.arange(n, dtype=np.int64).astype(np.uint32),
        log_time=t_ns.copy(),
        publish_time=t_ns.copy(),
        data=out.reshape(-1),
        offset=np.arange(n, dtype=np.int64) * length,
        length=np.full(n, length, np.int64),
    )


def _is_status(channel: ChannelInfo) -> bool:
    return (
        channel.schema is not None
        and channel.schema.name == STATUS_SCHEMA_NAME
        and channel.message_encoding == "cdr"
        and channel.topic.startswith(STATUS_TOPIC_PREFIX)
        and channel.topic.count("/") == 3
    )


def _decode_status(batch: MessageBatch, channel: ChannelInfo) -> dict[str, np.ndarray]:
    assert channel.schema is not None
    codec = codec_for(channel.schema.name, channel.schema.data)
    scalars = {
        "sec": ("stamp.sec", "i4"),
        "nanosec": ("stamp.nanosec", "u4"),
        "statistic": ("statistic", "f8"),
        "threshold": ("threshold", "f8"),
        "alarm": ("alarm", "u1"),
        "isolated": ("isolated", "i4"),
        "amplitude": ("amplitude", "f8"),
    }
    paths = [p for p, _ in scalars.values()] + ["scores", "isolated_set"]
    little, positions, sizes = codec.positions(batch, paths)
    out = {
        key: codec.read(batch, little, positions[path], code, 1)[:, 0]
        for key, (path, code) in scalars.items()
    }
    counts = sizes["scores"]
    n = len(batch)
    width = int(counts.max()) if n else 0
    scores = np.full((n, width), np.nan)
    if n and width and bool(np.all(counts == width)):
        scores = codec.read(batch, little, positions["scores"], "f8", width).astype(np.float64)
    elif n and width:
        for i in range(n):  # ragged scores (not written by imufdi): rare, slow path
            raw = gather_bytes(batch.data, positions["scores"][i : i + 1], 8 * int(counts[i]))
            scores[i, : counts[i]] = raw.view("<f8" if little[i] else ">f8")[0]
    out["scores"] = scores
    set_counts = sizes["isolated_set"]
    isolated_set = np.zeros((n, width), dtype=bool)
    if n and width and bool(np.all(set_counts == width)):
        isolated_set = codec.read(batch, little, positions["isolated_set"], "u1", width) != 0
    out["isolated_set"] = isolated_set
    return out


def read_status(
    source: str | os.PathLike[str] | IO[bytes] | McapSource, detector: str | None = None
) -> dict[tuple[str, str], StatusArrays]:
    """Read every status channel (optionally of one detector).

    Returns
    -------
    dict
        ``(detector, sensor_type)`` -> StatusArrays, in file order of the messages.
    """
    own = not isinstance(source, McapSource)
    src = McapSource(source) if not isinstance(source, McapSource) else source
    parts: dict[int, list[dict[str, np.ndarray]]] = {}
    try:
        for batch in src.batches():
            for cid in np.unique(batch.channel_id).tolist():
                channel = src.channels[cid]
                if not _is_status(channel):
                    continue
                det = channel.topic.split("/")[2]
                if detector is not None and det != detector:
                    continue
                sub = batch.select(batch.channel_id == cid)
                parts.setdefault(cid, []).append(_decode_status(sub, channel))
    finally:
        if own:
            src.close()
    result: dict[tuple[str, str], StatusArrays] = {}
    for cid, pieces in parts.items():
        channel = src.channels[cid]
        _, _, det, sensor_type = channel.topic.split("/")
        try:
            ids = list(json.loads(channel.metadata.get("sensor_ids", "[]")))
        except ValueError as err:
            raise McapInputError(f"{channel.topic}: sensor_ids metadata is not JSON") from err
        width = max(p["scores"].shape[1] for p in pieces)

        def cat(key: str, pieces: list[dict[str, np.ndarray]] = pieces) -> np.ndarray:
            return np.concatenate([p[key] for p in pieces])

        scores = np.concatenate(
            [
                np.pad(
                    p["scores"], ((0, 0), (0, width - p["scores"].shape[1])), constant_values=np.nan
                )
                for p in pieces
            ]
        )
        result[(det, sensor_type)] = StatusArrays(
            t_ns=cat("sec").astype(np.int64) * NS_PER_S + cat("nanosec").astype(np.int64),
            statistic=cat("statistic").astype(np.float64),
            threshold=cat("threshold").astype(np.float64),
            alarm=cat("alarm") != 0,
            isolated=cat("isolated").astype(np.int32),
            amplitude=cat("amplitude").astype(np.float64),
            scores=scores,
            sensor_ids=ids,
            isolated_set=np.concatenate(
                [
                    np.pad(p["isolated_set"], ((0, 0), (0, width - p["isolated_set"].shape[1])))
                    for p in pieces
                ]
            ),
        )
    return result


def read_json_topic(
    source: str | os.PathLike[str] | IO[bytes] | McapSource, topic: str
) -> list[tuple[int, Any]]:
    """All messages of a JSON channel as ``(log_time ns, decoded object)``, in file order.

    The imufdi event topics (``/imufdi/truth``, ``/imufdi/events``), CDR since this version,
    are decoded to the same dicts (see :func:`imufdi_cli.mcapio.events.read_events`).
    """
    own = not isinstance(source, McapSource)
    src = McapSource(source) if not isinstance(source, McapSource) else source
    out: list[tuple[int, Any]] = []
    try:
        for batch in src.batches():
            for cid in np.unique(batch.channel_id).tolist():
                channel = src.channels[cid]
                if channel.topic != topic:
                    continue
                sub = batch.select(batch.channel_id == cid)
                if channel.message_encoding != "json" and is_event_channel(channel):
                    out.extend(zip(sub.log_time.tolist(), decode_events(sub, channel)))
                    continue
                if channel.message_encoding != "json":
                    raise McapInputError(
                        f"topic {topic} has message encoding {channel.message_encoding!r}, not json"
                    )
                out.extend(zip(sub.log_time.tolist(), decode_json_payloads(sub)))
    finally:
        if own:
            src.close()
    return out
