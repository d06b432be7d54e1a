"""Event channels: injected-fault ground truth (``imufdi_msgs/msg/FaultEvent`` on
``/imufdi/truth``) and detector alarm events (``imufdi_msgs/msg/FdiEvent`` on
``/imufdi/events``), both ros2msg/CDR so every ROS 2 tool opens the files.

Events are read back as the plain dicts imufdi used before (older logs carry them on JSON
channels, which are still read):

- truth: ``{"event": "start"|"end", "t_ns", "t_s", "fault_id", "fault": Fault.to_dict()}``
- alarms: ``{"detector", "sensor_type", "event": "alarm_start"|"alarm_end"|"episode",
  "t_ns", "isolated": sensor id or None, "isolable", "amplitude": float or None,
  "statistic"}``, and for ``episode`` events ``"episode"``: the explanation
  (:meth:`imufdi_cli.episodes.Episode.to_dict`)

``imufdi report`` reads episodes with :func:`decode_episode_events` instead: the typed
fields of each ``episode`` message (:class:`EpisodeEvent`), its JSON parsed only on
demand, the alarm starts and ends skipped without being decoded.
"""

from __future__ import annotations

import json
import math
import os
import struct
from collections.abc import Iterable, Sequence
from typing import IO, TYPE_CHECKING, Any

import numpy as np

from imufdi_cli.errors import McapInputError, UsageError
from imufdi_cli.jsonin import loads
from imufdi_cli.mcapio.cdr import codec_for
from imufdi_cli.mcapio.cdr_message import decode_json_payloads
from imufdi_cli.mcapio.records import ChannelInfo, MessageBatch
from imufdi_cli.mcapio.schemas import (
    FAULT_EVENT_SCHEMA,
    FAULT_EVENT_SCHEMA_NAME,
    FDI_EVENT_SCHEMA,
    FDI_EVENT_SCHEMA_NAME,
)
from imufdi_cli.mcapio.source import McapSource, iter_topic

if TYPE_CHECKING:  # the writer is imported where it writes (report only reads events)
    from imufdi_cli.mcapio.writer import McapWriter

NS_PER_S = 1_000_000_000
TRUTH_TOPIC = "/imufdi/truth"
EVENTS_TOPIC = "/imufdi/events"
#: Schema names that older imufdi versions gave the JSON event channels.
LEGACY_SCHEMA_NAMES = ("imufdi/FaultEvent", "imufdi_msgs/FdiEvent")


_FORMATS = {"u1": "B", "i4": "i", "u4": "I", "f8": "d", "i8": "q"}
#: code -> (size, packer) of each primitive, little-endian
_PACKERS = {
    code: (struct.calcsize(fmt), struct.Struct("<" + fmt).pack) for code, fmt in _FORMATS.items()
}
#: the episode JSON of an FdiEvent (what ``json.dumps(episode, allow_nan=False)`` makes)
_EPISODE_JSON = json.JSONEncoder(allow_nan=False)


class _CdrBuilder:
    """Little-endian CDR payload built field by field; returns the offset of each field
    (from the start of the payload, encapsulation header included)."""

    def __init__(self) -> None:
        self.body = bytearray()

    def _align(self, size: int) -> None:
        self.body += b"\0" * ((-len(self.body)) % size)

    def prim(self, code: str, value: float | int) -> int:
        size, pack = _PACKERS[code]
        body = self.body
        pad = (-len(body)) % size
        if pad:
            body += b"\0" * pad
        offset = len(body) + 4
        body += pack(value)
        return offset

    def string(self, text: str) -> None:
        raw = text.encode("utf-8") + b"\0"
        self.prim("u4", len(raw))
        self.body += raw

    def strings(self, texts: Sequence[str]) -> None:
        self.prim("u4", len(texts))
        for text in texts:
            self.string(text)

    def f8_sequence(self, values: Sequence[float]) -> None:
        self.prim("u4", len(values))
        for value in values:
            self.prim("f8", value)

    def header(self, t_ns: int = 0, frame_id: str = "") -> tuple[int, int]:
        sec, nanosec = divmod(int(t_ns), NS_PER_S)
        at_sec = self.prim("i4", sec)
        at_nanosec = self.prim("u4", nanosec)
        self.string(frame_id)
        return at_sec, at_nanosec

    def payload(self) -> bytes:
        return b"\x00\x01\x00\x00" + bytes(self.body)


def _stamps(t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    sec = np.floor_divide(t_ns, NS_PER_S)
    if t_ns.size and (int(sec.min()) < -(2**31) or int(sec.max()) >= 2**31):
        raise UsageError("timestamps do not fit a ROS 2 builtin_interfaces/Time (int32 seconds)")
    return sec.astype("<i4"), (t_ns - sec * NS_PER_S).astype("<u4")


# --- registering ------------------------------------------------------------------------


def register_truth_channel(writer: McapWriter) -> int:
    """The ``/imufdi/truth`` channel (``imufdi_msgs/msg/FaultEvent``, CDR); its id."""
    schema_id = writer.register_schema(FAULT_EVENT_SCHEMA_NAME, "ros2msg", FAULT_EVENT_SCHEMA)
    return writer.register_channel(TRUTH_TOPIC, "cdr", schema_id)


def register_events_channel(writer: McapWriter) -> int:
    """The ``/imufdi/events`` channel (``imufdi_msgs/msg/FdiEvent``, CDR); its id."""
    schema_id = writer.register_schema(FDI_EVENT_SCHEMA_NAME, "ros2msg", FDI_EVENT_SCHEMA)
    return writer.register_channel(EVENTS_TOPIC, "cdr", schema_id)


# --- encoding ---------------------------------------------------------------------------


def encode_fault_events(channel_id: int, events: Sequence[dict[str, Any]]) -> MessageBatch:
    """FaultEvent messages (log time = ``t_ns``) from truth event dicts (module docstring)."""
    payloads = []
    for event in events:
        fault = event["fault"]
        until = fault.get("until_s")
        params = dict(fault.get("params", {}))
        cdr = _CdrBuilder()
        cdr.header(int(event["t_ns"]))
        cdr.string(str(event["event"]))
        cdr.prim("f8", float(event.get("t_s", math.nan)))
        cdr.string(str(event.get("fault_id", fault.get("id", ""))))
        cdr.string(str(fault["model"]))
        cdr.strings([str(s) for s in fault["sensors"]])
        cdr.prim("f8", float(fault["at_s"]))
        cdr.prim("f8", math.nan if until is None else float(until))
        cdr.strings([str(k) for k in params])
        cdr.f8_sequence([float(v) for v in params.values()])
        cdr.string(str(fault.get("spec", "")))
        payloads.append(cdr.payload())
    t_ns = np.array([int(e["t_ns"]) for e in events], np.int64)
    return MessageBatch.from_payloads(channel_id, t_ns, payloads)


def encode_fdi_events(
    channel_id: int,
    t_ns: np.ndarray,
    *,
    detector: str,
    sensor_type: str,
    sensor_ids: Sequence[str],
    alarm: np.ndarray,
    isolated: np.ndarray,
    amplitude: np.ndarray,
    statistic: np.ndarray,
) -> MessageBatch:
    """FdiEvent messages for K alarm changes of one detector and sensor type, in bulk.

    Parameters
    ----------
    t_ns : ndarray, shape (K,), int64
        Sample time of each change (also the log time).
    alarm : ndarray, shape (K,), bool
        True: the alarm starts at that sample; False: it ends.
    isolated : ndarray, shape (K,), int
        Index into ``sensor_ids``; -1 none, -2 not isolable.
    amplitude, statistic : ndarray, shape (K,), float64

    Messages sharing (start/end, isolated sensor) have the same byte layout: one template
    per such kind (cached across calls) holds the constant bytes; the K payloads are the
    templates joined in event order, and the stamps and numbers are written into all of
    them at once with numpy.
    """
    t_ns = np.asarray(t_ns, np.int64)
    k = t_ns.shape[0]
    if k == 0:
        return MessageBatch.empty()
    alarm = np.asarray(alarm, bool)
    isolated = np.asarray(isolated, np.int64)
    sec, nanosec = _stamps(t_ns)
    key = alarm.astype(np.int64) * (len(sensor_ids) + 3) + np.clip(isolated, -2, None) + 2
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    kinds = [
        _fdi_template(
            detector,
            sensor_type,
            bool(alarm[i]),
            sensor_ids[int(isolated[i])] if 0 <= int(isolated[i]) < len(sensor_ids) else "",
            int(isolated[i]) != -2,
        )
        for i in first.tolist()
    ]
    payloads = [kinds[g][0] for g in inverse.tolist()]
    data = np.frombuffer(b"".join(payloads), np.uint8).copy()
    fields = np.array([at for _, at in kinds], np.int64)[inverse]  # (K, 4) field offsets
    length = np.array([len(p) for p, _ in kinds], np.int64)[inverse]
    offset = np.zeros(k, np.int64)
    np.cumsum(length[:-1], out=offset[1:])
    columns = (
        (sec, 4),
        (nanosec, 4),
        (np.ascontiguousarray(amplitude, "<f8"), 8),
        (np.ascontiguousarray(statistic, "<f8"), 8),
    )
    for column, (values, size) in enumerate(columns):
        where = offset + fields[:, column]
        data[where[:, None] + np.arange(size)] = values.reshape(k, 1).view(np.uint8)
    return MessageBatch(
        channel_id=np.full(k, channel_id, np.uint16),
        sequence=np.zeros(k, np.uint32),
        log_time=t_ns.copy(),
        publish_time=t_ns.copy(),
        data=data,
        offset=offset,
        length=length,
    )


_TEMPLATES: dict[tuple[str, str, bool, str, bool], tuple[bytes, tuple[int, int, int, int]]] = {}


def _fdi_template(
    detector: str, sensor_type: str, start: bool, isolated: str, isolable: bool
) -> tuple[bytes, tuple[int, int, int, int]]:
    """FdiEvent payload with zero stamp and numbers, and the offsets of sec, nanosec,
    amplitude and statistic."""
    key = (detector, sensor_type, start, isolated, isolable)
    found = _TEMPLATES.get(key)
    if found is None:
        cdr = _CdrBuilder()
        at_sec, at_nanosec = cdr.header()
        cdr.string(detector)
        cdr.string(sensor_type)
        cdr.string("alarm_start" if start else "alarm_end")
        cdr.string(isolated)
        cdr.prim("u1", isolable)
        at_amplitude = cdr.prim("f8", 0.0)
        at_statistic = cdr.prim("f8", 0.0)
        _episode_fields(cdr, None)
        found = (cdr.payload(), (at_sec, at_nanosec, at_amplitude, at_statistic))
        if len(_TEMPLATES) > 4096:
            _TEMPLATES.clear()
        _TEMPLATES[key] = found
    return found


# --- decoding ---------------------------------------------------------------------------


def is_event_channel(channel: ChannelInfo) -> bool:
    """A FaultEvent/FdiEvent CDR channel, or a JSON event channel of an older imufdi."""
    if channel.schema is None:
        return False
    if channel.message_encoding == "cdr":
        return channel.schema.name in (FAULT_EVENT_SCHEMA_NAME, FDI_EVENT_SCHEMA_NAME)
    return channel.message_encoding == "json" and channel.topic in (TRUTH_TOPIC, EVENTS_TOPIC)


def is_current_fdi_channel(channel: ChannelInfo) -> bool:
    """A CDR FdiEvent channel with this version's schema: its payloads can be copied as
    they are onto a channel of :func:`register_events_channel` (those of an older schema,
    without ``start_ns``/``end_ns``, must be re-encoded: :func:`encode_fdi_event_dicts`)."""
    return (
        channel.message_encoding == "cdr"
        and channel.schema is not None
        and channel.schema.name == FDI_EVENT_SCHEMA_NAME
        and channel.schema.data == FDI_EVENT_SCHEMA
    )


def _stamp_ns(header: dict[str, Any]) -> int:
    stamp = header["stamp"]
    return int(stamp["sec"]) * NS_PER_S + int(stamp["nanosec"])


def _fault_event(msg: dict[str, Any]) -> dict[str, Any]:
    until = float(msg["until_s"])
    return {
        "event": msg["event"],
        "t_ns": _stamp_ns(msg["header"]),
        "t_s": float(msg["t_s"]),
        "fault_id": msg["fault_id"],
        "fault": {
            "id": msg["fault_id"],
            "model": msg["model"],
            "sensors": list(msg["sensors"]),
            "at_s": float(msg["at_s"]),
            "until_s": None if math.isnan(until) else until,
            "params": {k: float(v) for k, v in zip(msg["param_names"], msg["param_values"])},
            "spec": msg["spec"],
        },
    }


def _fdi_event(msg: dict[str, Any]) -> dict[str, Any]:
    amplitude = float(msg["amplitude"])
    event = {
        "detector": msg["detector"],
        "sensor_type": msg["sensor_type"],
        "event": msg["event"],
        "t_ns": _stamp_ns(msg["header"]),
        "isolated": msg["isolated"] or None,
        "isolable": bool(msg["isolable"]),
        "amplitude": None if math.isnan(amplitude) else amplitude,
        "statistic": float(msg["statistic"]),
    }
    detail = msg.get("detail")
    if detail:
        try:
            event["episode"] = loads(detail, "episode detail", McapInputError)
        except McapInputError as err:
            raise ValueError("malformed episode detail") from err
    return event


def decode_events(batch: MessageBatch, channel: ChannelInfo) -> list[dict[str, Any]]:
    """Event dicts (module docstring) of the messages of one event channel (CDR or JSON)."""
    if channel.message_encoding == "json":
        return decode_json_payloads(batch)
    if not is_event_channel(channel) or channel.schema is None:
        raise McapInputError(f"channel {channel.topic} is not an imufdi event channel")
    codec = codec_for(channel.schema.name, channel.schema.data)
    convert = _fault_event if channel.schema.name == FAULT_EVENT_SCHEMA_NAME else _fdi_event
    decode = codec.decoder()
    out = []
    for i in range(len(batch)):
        try:
            out.append(convert(decode(batch.payload(i))))
        except (KeyError, TypeError, ValueError) as err:
            raise McapInputError(f"{channel.topic}: malformed {codec.root} message") from err
    return out


def match_fields(
    episode: dict[str, Any],
) -> tuple[str, int, int, str | None, str | None, float | None, float | None]:
    """What matching reads of an explanation (``Episode.to_dict``): sensor type, first
    and last alarmed sample (ns), first isolated sensor, and the best fit's model, interval
    low and high (None when absent) -- the arguments of
    :meth:`imufdi_cli.episodes.scoring.EpisodeMatcher.match`, and the typed fields of an
    ``episode`` event."""
    sensors = episode.get("sensors") or []
    fits = episode.get("fits") or []
    best = fits[0] if fits else {}
    return (
        episode["sensor_type"],
        episode["start_ns"],
        episode["end_ns"],
        sensors[0] if sensors else None,
        best.get("model"),
        best.get("low"),
        best.get("high"),
    )


class EpisodeEvent:
    """An ``episode`` event as ``imufdi report`` reads it: what matching and counting need
    (detector, sensor type, first and last alarmed sample, first isolated sensor, the best
    fit's model and interval), with the explanation (:meth:`Episode.to_dict`) parsed from
    its JSON only when :meth:`explanation` is called.

    Attributes
    ----------
    detector, sensor_type : str
    start_ns, end_ns : int
        First and last alarmed sample, ns (log time).
    isolated : str or None
        First isolated sensor.
    fault_class : str or None
        Model of the best fit (None when unexplained).
    low, high : float or None
        Its interval (SI; None when none).
    """

    __slots__ = (
        "_detail",
        "_explanation",
        "detector",
        "end_ns",
        "fault_class",
        "high",
        "isolated",
        "low",
        "sensor_type",
        "start_ns",
    )

    def __init__(
        self,
        detector: str,
        sensor_type: str,
        start_ns: int,
        end_ns: int,
        isolated: str | None,
        fault_class: str | None,
        low: float | None,
        high: float | None,
        detail: bytes | None = None,
        explanation: dict[str, Any] | None = None,
    ) -> None:
        self.detector = detector
        self.sensor_type = sensor_type
        self.start_ns = start_ns
        self.end_ns = end_ns
        self.isolated = isolated
        self.fault_class = fault_class
        self.low = low
        self.high = high
        self._detail = detail
        self._explanation = explanation

    @classmethod
    def from_explanation(cls, episode: dict[str, Any]) -> EpisodeEvent:
        """From a decoded explanation (files without the typed ``start_ns``/``end_ns``
        fields, and the JSON event channels of older versions)."""
        return cls(episode["detector"], *match_fields(episode), explanation=episode)

    def match_fields(
        self,
    ) -> tuple[str, int, int, str | None, str | None, float | None, float | None]:
        """The arguments of :meth:`imufdi_cli.episodes.scoring.EpisodeMatcher.match`."""
        return (
            self.sensor_type,
            self.start_ns,
            self.end_ns,
            self.isolated,
            self.fault_class,
            self.low,
            self.high,
        )

    def explanation(self) -> dict[str, Any]:
        """The whole explanation (:meth:`imufdi_cli.episodes.Episode.to_dict`), parsed
        on first use; McapInputError when its JSON is malformed."""
        if self._explanation is None:
            text = (self._detail or b"").rstrip(b"\0").decode("utf-8", errors="replace")
            try:
                episode = loads(text, "episode detail", McapInputError)
            except McapInputError as err:
                raise McapInputError(f"{EVENTS_TOPIC}: malformed episode detail") from err
            if not isinstance(episode, dict):
                raise McapInputError(f"{EVENTS_TOPIC}: malformed episode detail")
            self._explanation = episode
            self._detail = None
        return self._explanation


def decode_episode_events(batch: MessageBatch, channel: ChannelInfo) -> list[EpisodeEvent]:
    """The ``episode`` events among the messages of one event channel, in order.

    Messages of the current FdiEvent schema (typed ``start_ns``/``end_ns``) are walked
    field by field without decoding the alarm starts and ends or parsing any episode's
    JSON detail; older schemas and JSON channels are decoded in full
    (:func:`decode_events`) and give the same fields.
    """
    if is_current_fdi_channel(channel):
        walked = _walk_episode_events(batch, channel.topic)
        if walked is not None:
            return walked
    out = []
    for event in decode_events(batch, channel):
        if not isinstance(event, dict) or event.get("event") != "episode":
            continue
        episode = event.get("episode")
        if episode is None:
            continue
        try:
            out.append(EpisodeEvent.from_explanation(episode))
        except (AttributeError, KeyError, TypeError) as err:
            raise McapInputError(f"{channel.topic}: malformed episode detail") from err
    return out


_EPISODE = b"episode"


class _Malformed(ValueError):
    """A message of the batch is cut short or its strings run past its end."""


def _gather(data: np.ndarray, at: np.ndarray, size: int) -> np.ndarray:
    """(K, size) bytes of ``data`` from each offset ``at`` (bounds checked by callers)."""
    return data[at[:, None] + np.arange(size)]


def _string_field(
    data: np.ndarray, base: np.ndarray, pos: np.ndarray, end: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The CDR string at ``pos`` of each message (positions relative to ``base``, the end
    of the encapsulation header, as CDR aligns): (first byte, byte count with the NUL,
    position after it), all (K,) int64."""
    pos = pos + (-pos) % 4
    at = base + pos
    if (at + 4 > end).any():
        raise _Malformed("string length past the end of the message")
    size = _gather(data, at, 4).view("<u4").reshape(-1).astype(np.int64)
    first = at + 4
    if (first + size > end).any():
        raise _Malformed("string past the end of the message")
    return first, size, pos + 4 + size


def _numbers(
    data: np.ndarray, base: np.ndarray, pos: np.ndarray, end: np.ndarray, dtype: str
) -> tuple[np.ndarray, np.ndarray]:
    """Two consecutive 8-byte numbers at ``pos`` (aligned to 8) of each message: (K, 2)
    values and the position after them."""
    pos = pos + (-pos) % 8
    if (base + pos + 16 > end).any():
        raise _Malformed("numbers past the end of the message")
    return _gather(data, base + pos, 16).view(dtype), pos + 16


#: episodes in a batch from which their fields are gathered with numpy, not one by one
_VECTOR_MIN = 24
_U32_AT = struct.Struct("<I").unpack_from
_F8X2_AT = struct.Struct("<2d").unpack_from
_I8X2_AT = struct.Struct("<2q").unpack_from


def _episode_tail(view: memoryview, base: int, pos: int, end: int) -> tuple[Any, ...]:
    """The fields after ``event`` of one episode message (``pos`` relative to ``base``,
    the end of its encapsulation header): isolated (first byte, size), fault_class
    (first, size), detail (first, size), (size_low, size_high), (start_ns, end_ns)."""

    def string(pos: int) -> tuple[int, int, int]:
        pos += (-pos) % 4
        at = base + pos
        if at + 4 > end:
            raise _Malformed("string length past the end of the message")
        (size,) = _U32_AT(view, at)
        if at + 4 + size > end:
            raise _Malformed("string past the end of the message")
        return at + 4, size, pos + 4 + size

    def numbers(pos: int, unpack: Any) -> tuple[tuple[Any, Any], int]:
        pos += (-pos) % 8
        if base + pos + 16 > end:
            raise _Malformed("numbers past the end of the message")
        return unpack(view, base + pos), pos + 16

    isolated, isolated_size, pos = string(pos)
    _, pos = numbers(pos + 1, _F8X2_AT)  # isolable; amplitude, statistic
    fault_class, fault_class_size, pos = string(pos)
    _, _, pos = string(pos)  # size_name
    interval, pos = numbers(pos + (-pos) % 8 + 8, _F8X2_AT)  # size; size_low, size_high
    detail, detail_size, pos = string(pos)
    times, _ = numbers(pos, _I8X2_AT)
    return (
        isolated,
        isolated_size,
        fault_class,
        fault_class_size,
        detail,
        detail_size,
        interval,
        times,
    )


def _walk_episode_events(batch: MessageBatch, topic: str) -> list[EpisodeEvent] | None:
    """:func:`decode_episode_events` for messages of the current FdiEvent schema (field
    order of ``FDI_EVENT_SCHEMA``: header, detector, sensor_type, event, isolated,
    isolable, amplitude, statistic, fault_class, size_name, size, size_low, size_high,
    detail, start_ns, end_ns), walked for all messages of the batch at once with numpy;
    only the episodes' fields become Python objects. Strings decode as
    :class:`~imufdi_cli.mcapio.cdr_message.MessageDecoder` decodes them. None when a message is
    big-endian (not written by imufdi): the caller decodes the batch in full."""
    if len(batch) == 0:
        return []
    data = np.ascontiguousarray(batch.data, np.uint8)
    start = np.asarray(batch.offset, np.int64)
    end = start + np.asarray(batch.length, np.int64)
    try:
        if (end - start < 4).any() or (end > data.size).any():
            raise _Malformed("message shorter than its CDR header")
        if (data[start] != 0).any() or (data[start + 1] > 1).any():
            raise _Malformed("unsupported or missing CDR encapsulation header")
        if (data[start + 1] == 0).any():
            return None
        base = start + 4  # CDR alignment is relative to the end of the header
        pos = np.full(start.size, 8, np.int64)  # header.stamp: sec, nanosec
        _, _, pos = _string_field(data, base, pos, end)  # header.frame_id
        detector, detector_size, pos = _string_field(data, base, pos, end)
        sensor_type, sensor_type_size, pos = _string_field(data, base, pos, end)
        event, event_size, pos = _string_field(data, base, pos, end)
        # "episode" and NULs only (as the decoder strips them); alarm events stop here
        maybe = np.flatnonzero(event_size >= len(_EPISODE))
        if maybe.size:
            head = _gather(data, event[maybe], len(_EPISODE))
            maybe = maybe[(head == np.frombuffer(_EPISODE, np.uint8)).all(axis=1)]
        # "episode" + NUL as imufdi writes it, else check that the rest is NULs
        exact = event_size[maybe] == len(_EPISODE) + 1
        exact &= data[event[maybe] + len(_EPISODE)] == 0
        longer = maybe[~exact & (event_size[maybe] > len(_EPISODE))]
        keep = np.sort(
            np.concatenate(
                [
                    maybe[exact],
                    [
                        i
                        for i in longer.tolist()
                        if not data[event[i] + len(_EPISODE) : event[i] + event_size[i]].any()
                    ],
                    maybe[event_size[maybe] == len(_EPISODE)],
                ]
            ).astype(np.int64)
        )
        if keep.size == 0:
            return []
        view = data.data  # a memoryview: slicing it is cheaper than slicing the array
        tails: Iterable[tuple[Any, ...]]
        if keep.size >= _VECTOR_MIN:  # the rest of the fields, for all episodes at once
            base, pos, end = base[keep], pos[keep], end[keep]
            isolated, isolated_size, pos = _string_field(data, base, pos, end)
            pos = pos + 1  # isolable
            _, pos = _numbers(data, base, pos, end, "<f8")  # amplitude, statistic
            fault_class, fault_class_size, pos = _string_field(data, base, pos, end)
            _, _, pos = _string_field(data, base, pos, end)  # size_name
            pos = pos + (-pos) % 8 + 8  # size
            interval, pos = _numbers(data, base, pos, end, "<f8")  # size_low, size_high
            detail, detail_size, pos = _string_field(data, base, pos, end)
            times, pos = _numbers(data, base, pos, end, "<i8")  # start_ns, end_ns
            tails = zip(
                isolated.tolist(),
                isolated_size.tolist(),
                fault_class.tolist(),
                fault_class_size.tolist(),
                detail.tolist(),
                detail_size.tolist(),
                interval.tolist(),
                times.tolist(),
            )
        else:  # a few: one by one (numpy's per-call cost would dominate)
            tails = [
                _episode_tail(view, b, p, e)
                for b, p, e in zip(base[keep].tolist(), pos[keep].tolist(), end[keep].tolist())
            ]
    except _Malformed as err:
        raise McapInputError(f"{topic}: malformed {FDI_EVENT_SCHEMA_NAME} message: {err}") from err

    texts: dict[bytes, str] = {}  # few distinct names per batch

    def text(first: int, size: int) -> str:
        raw = view[first : first + size].tobytes()
        found = texts.get(raw)
        if found is None:
            found = texts[raw] = raw.rstrip(b"\0").decode("utf-8", errors="replace")
        return found

    out = []
    bounds = zip(
        detector[keep].tolist(),
        detector_size[keep].tolist(),
        sensor_type[keep].tolist(),
        sensor_type_size[keep].tolist(),
        tails,
    )
    for d, dn, s, sn, (i, i_n, f, fn, j, jn, (low, high), (t0, t1)) in bounds:
        raw = view[j : j + jn].tobytes()
        if not raw.rstrip(b"\0"):
            continue  # no explanation: not an episode (as decode_events reads it)
        out.append(
            EpisodeEvent(
                text(d, dn),
                text(s, sn),
                t0,
                t1,
                text(i, i_n) or None,
                text(f, fn) or None,
                None if math.isnan(low) else low,
                None if math.isnan(high) else high,
                detail=raw,
            )
        )
    return out


def read_events(
    source: str | os.PathLike[str] | IO[bytes] | McapSource, topic: str
) -> list[tuple[int, dict[str, Any]]]:
    """All events on ``topic`` (``/imufdi/truth`` or ``/imufdi/events``, CDR or the JSON of
    older versions) as ``(log_time ns, event dict)``, in file order."""
    out: list[tuple[int, dict[str, Any]]] = []
    for channel, sub in iter_topic(source, topic):
        if not is_event_channel(channel):
            raise McapInputError(
                f"topic {topic} has type {channel.schema.name if channel.schema else '?'}"
                f" ({channel.message_encoding}), not an imufdi event type"
            )
        out.extend(zip(sub.log_time.tolist(), decode_events(sub, channel)))
    return out


def encode_fdi_event_dicts(
    channel_id: int, log_time: Sequence[int], events: Sequence[dict[str, Any]]
) -> MessageBatch:
    """FdiEvent messages from event dicts one by one (for re-encoding older JSON events)."""
    payloads = []
    for event in events:
        amplitude = event.get("amplitude")
        cdr = _CdrBuilder()
        cdr.header(int(event.get("t_ns", 0)))
        cdr.string(str(event.get("detector", "")))
        cdr.string(str(event.get("sensor_type", "")))
        cdr.string(str(event.get("event", "")))
        cdr.string(str(event.get("isolated") or ""))
        cdr.prim("u1", bool(event.get("isolable", True)))
        cdr.prim("f8", math.nan if amplitude is None else float(amplitude))
        cdr.prim("f8", float(event.get("statistic", math.nan)))
        _episode_fields(cdr, event.get("episode"))
        payloads.append(cdr.payload())
    return MessageBatch.from_payloads(channel_id, np.asarray(log_time, np.int64), payloads)


def _episode_fields(cdr: _CdrBuilder, episode: dict[str, Any] | None) -> None:
    """The episode fields of FdiEvent: the explanation of an ``episode`` event, or the
    empty/NaN defaults of an alarm start or end."""
    best = (episode or {}).get("fits") or [{}]
    fit = best[0]
    cdr.string(str(fit.get("model", "")))
    cdr.string(str(fit.get("size_name", "")))
    for key in ("size", "low", "high"):
        value = fit.get(key)
        cdr.prim("f8", math.nan if value is None else float(value))
    cdr.string("" if episode is None else _EPISODE_JSON.encode(episode))
    for key in ("start_ns", "end_ns"):
        cdr.prim("i8", 0 if episode is None else int(episode.get(key) or 0))


def encode_episode_events(channel_id: int, episodes: Sequence[dict[str, Any]]) -> MessageBatch:
    """``episode`` FdiEvent messages from :meth:`imufdi_cli.episodes.Episode.to_dict`
    dicts; stamped (and logged) at the decision time of each episode's last alarm."""
    events = []
    for episode in episodes:
        sensors = episode.get("sensors") or []
        events.append(
            {
                "t_ns": int(episode["decided_end_ns"]),
                "detector": episode["detector"],
                "sensor_type": episode["sensor_type"],
                "event": "episode",
                "isolated": sensors[0] if sensors else "",
                "isolable": True,
                "amplitude": None,
                # None when no alarm had a finite statistic/threshold (to_dict's JSON)
                "statistic": math.nan
                if episode.get("peak_ratio") is None
                else float(episode["peak_ratio"]),
                "episode": episode,
            }
        )
    return encode_fdi_event_dicts(channel_id, [e["t_ns"] for e in events], events)
