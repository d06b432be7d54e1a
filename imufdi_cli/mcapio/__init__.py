"""Fast MCAP I/O for IMU arrays (docs/formats.md, docs/performance.md).

Low level: :class:`McapSource` (streaming reader, :class:`MessageBatch` of whole chunks, about 4 MiB each) and
:class:`McapWriter` (bulk writer, atomic rename). IMU arrays: :class:`ImuArrayReader`,
:class:`ImuArrayWriter`, :func:`read_array`, :func:`write_array`; per-channel codecs
:func:`decode_imu`, :func:`patch_imu`, :func:`decode_mag`, :func:`patch_mag`. Detector
status channels: :func:`register_status_channel`, :func:`encode_status`, :func:`read_status`.
Ground truth and alarm events (CDR ``FaultEvent``/``FdiEvent``): :func:`read_events`,
:func:`encode_fault_events`, :func:`encode_fdi_events`.

Each name is imported from its submodule on first use (PEP 562 ``__getattr__``), so that a
command pays only for the parts it uses (start-up time, docs/performance.md).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from imufdi_cli.lazy import lazy_exports

if TYPE_CHECKING:
    from imufdi_cli.mcapio.events import (
        EVENTS_TOPIC,
        TRUTH_TOPIC,
        decode_events,
        encode_episode_events,
        encode_fault_events,
        encode_fdi_events,
        read_events,
        register_events_channel,
        register_truth_channel,
    )
    from imufdi_cli.mcapio.imu import (
        ARRAY_METADATA,
        AlignmentStats,
        ImuArrayReader,
        ImuArrayWriter,
        ImuFields,
        decode_imu,
        decode_mag,
        encode_messages,
        is_imu_channel,
        is_mag_channel,
        natural_key,
        patch_imu,
        patch_mag,
        read_array,
        write_array,
    )
    from imufdi_cli.mcapio.records import ChannelInfo, MessageBatch, SchemaInfo
    from imufdi_cli.mcapio.source import McapSource
    from imufdi_cli.mcapio.status import (
        STATUS_FRAME_ID,
        StatusArrays,
        encode_status,
        iter_status,
        read_json_topic,
        read_status,
        register_status_channel,
    )
    from imufdi_cli.mcapio.summary import LogSummary, TopicSummary, summarize
    from imufdi_cli.mcapio.writer import McapWriter

#: public name -> the submodule defining it (imported on first use, for start-up time)
_WHERE: dict[str, str] = {
    "ARRAY_METADATA": "imufdi_cli.mcapio.imu",
    "AlignmentStats": "imufdi_cli.mcapio.imu",
    "ChannelInfo": "imufdi_cli.mcapio.records",
    "EVENTS_TOPIC": "imufdi_cli.mcapio.events",
    "ImuArrayReader": "imufdi_cli.mcapio.imu",
    "ImuArrayWriter": "imufdi_cli.mcapio.imu",
    "ImuFields": "imufdi_cli.mcapio.imu",
    "LogSummary": "imufdi_cli.mcapio.summary",
    "McapSource": "imufdi_cli.mcapio.source",
    "McapWriter": "imufdi_cli.mcapio.writer",
    "MessageBatch": "imufdi_cli.mcapio.records",
    "STATUS_FRAME_ID": "imufdi_cli.mcapio.status",
    "SchemaInfo": "imufdi_cli.mcapio.records",
    "StatusArrays": "imufdi_cli.mcapio.status",
    "TRUTH_TOPIC": "imufdi_cli.mcapio.events",
    "TopicSummary": "imufdi_cli.mcapio.summary",
    "decode_events": "imufdi_cli.mcapio.events",
    "decode_imu": "imufdi_cli.mcapio.imu",
    "decode_mag": "imufdi_cli.mcapio.imu",
    "encode_episode_events": "imufdi_cli.mcapio.events",
    "encode_fault_events": "imufdi_cli.mcapio.events",
    "encode_fdi_events": "imufdi_cli.mcapio.events",
    "encode_messages": "imufdi_cli.mcapio.imu",
    "encode_status": "imufdi_cli.mcapio.status",
    "is_imu_channel": "imufdi_cli.mcapio.imu",
    "is_mag_channel": "imufdi_cli.mcapio.imu",
    "iter_status": "imufdi_cli.mcapio.status",
    "natural_key": "imufdi_cli.mcapio.imu",
    "patch_imu": "imufdi_cli.mcapio.imu",
    "patch_mag": "imufdi_cli.mcapio.imu",
    "read_array": "imufdi_cli.mcapio.imu",
    "read_events": "imufdi_cli.mcapio.events",
    "read_json_topic": "imufdi_cli.mcapio.status",
    "read_status": "imufdi_cli.mcapio.status",
    "register_events_channel": "imufdi_cli.mcapio.events",
    "register_status_channel": "imufdi_cli.mcapio.status",
    "register_truth_channel": "imufdi_cli.mcapio.events",
    "summarize": "imufdi_cli.mcapio.summary",
    "write_array": "imufdi_cli.mcapio.imu",
}


__getattr__ = lazy_exports(__name__, _WHERE, globals())


__all__ = [
    "ARRAY_METADATA",
    "EVENTS_TOPIC",
    "STATUS_FRAME_ID",
    "TRUTH_TOPIC",
    "AlignmentStats",
    "ChannelInfo",
    "ImuArrayReader",
    "ImuArrayWriter",
    "ImuFields",
    "LogSummary",
    "McapSource",
    "McapWriter",
    "MessageBatch",
    "SchemaInfo",
    "StatusArrays",
    "TopicSummary",
    "decode_events",
    "decode_imu",
    "decode_mag",
    "encode_episode_events",
    "encode_fault_events",
    "encode_fdi_events",
    "encode_messages",
    "encode_status",
    "is_imu_channel",
    "is_mag_channel",
    "iter_status",
    "natural_key",
    "patch_imu",
    "patch_mag",
    "read_array",
    "read_events",
    "read_json_topic",
    "read_status",
    "register_events_channel",
    "register_status_channel",
    "register_truth_channel",
    "summarize",
    "write_array",
]
