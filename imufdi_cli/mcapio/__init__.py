"""Fast MCAP I/O for IMU arrays (DESIGN.md §4).

Low level: :class:`McapSource` (streaming reader, :class:`MessageBatch` of whole chunks, about 4 MiB each) and
:class:`McapWriter` (bulk writer, atomic rename). IMU arrays: :class:`ImuArrayReader`,
:class:`ImuArrayWriter`, :func:`read_array`, :func:`write_array`; per-channel codecs
:func:`decode_imu`, :func:`patch_imu`, :func:`decode_mag`, :func:`patch_mag`. Detector
status channels: :func:`register_status_channel`, :func:`encode_status`, :func:`read_status`.
Ground truth and alarm events (CDR ``FaultEvent``/``FdiEvent``): :func:`read_events`,
:func:`encode_fault_events`, :func:`encode_fdi_events`.
"""

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
