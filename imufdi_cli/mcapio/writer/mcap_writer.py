"""The bulk MCAP writer's class: :class:`McapWriter` (its output in
:mod:`~imufdi_cli.mcapio.writer.output`, messages and chunks in
:mod:`~imufdi_cli.mcapio.writer.messages`, index and summary records in
:mod:`~imufdi_cli.mcapio.writer.index`); here the Header, the Schema, Channel and Metadata
records, and the end of the file."""

from __future__ import annotations

import os
import struct
from collections import deque
from typing import IO, Any

from imufdi_cli.errors import UsageError
from imufdi_cli.mcapio.records import (
    COMPRESSIONS,
    MAGIC,
    OP_DATA_END,
    OP_HEADER,
    OP_METADATA,
    ChannelInfo,
    SchemaInfo,
    _record,
    _string,
    _string_map,
    channel_record,
    schema_record,
)
from imufdi_cli.mcapio.writer.index import _statistics_record, summary_section
from imufdi_cli.mcapio.writer.messages import _ChunkQueue


class McapWriter(_ChunkQueue):
    """Bulk MCAP writer (a context manager).

    Parameters
    ----------
    output : str, Path or binary stream
        ``"-"`` writes straight to stdout. A path is written to a temporary file in the same
        directory and renamed into place by :meth:`close`; if the ``with`` block raises,
        the temporary file is removed and nothing is left behind.
    compression : {"zstd", "lz4", "none"}
    chunk_size : int
        Uncompressed bytes of message records per chunk (approximate).
    profile : str
        The Header profile (``"ros2"`` for ROS 2 CDR messages).
    """

    def __init__(
        self,
        output: str | os.PathLike[str] | IO[bytes],
        *,
        compression: str = "zstd",
        chunk_size: int = 1 << 20,
        profile: str = "ros2",
    ) -> None:
        if compression not in COMPRESSIONS:
            raise UsageError(
                f"unknown MCAP compression {compression!r}; valid: {', '.join(COMPRESSIONS)}"
            )
        if chunk_size < 1:
            raise UsageError(f"chunk_size must be >= 1 byte, got {chunk_size}")
        self.compression = "" if compression == "none" else compression
        self.chunk_size = int(chunk_size)
        self._open_output(output)
        self._data_crc = 0
        self._closed = False
        self.schemas = {}
        self.channels = {}
        self._channel_schema = {}
        self._metadata_index = []
        self._chunk_index = []
        self._pending = []
        self._pending_ids = []
        self._pending_bytes = 0
        self._in_flight = deque()
        self._executor = None
        self._message_count = 0
        self._channel_counts = {}
        self._start_time = None
        self._end_time = None
        self._write(MAGIC)
        self._write(_record(OP_HEADER, _string(profile) + _string("imufdi")))

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    # --- schemas, channels, metadata --------------------------------------------------

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        """Write a Schema record (or reuse an identical one); returns its id (>= 1)."""
        for schema in self.schemas.values():
            if (schema.name, schema.encoding, schema.data) == (name, encoding, bytes(data)):
                return schema.id
        schema_id = max(self.schemas, default=0) + 1
        self._add_schema(SchemaInfo(schema_id, name, encoding, bytes(data)))
        return schema_id

    def _add_schema(self, schema: SchemaInfo) -> None:
        self.schemas[schema.id] = schema
        self._write(schema_record(schema))

    def register_channel(
        self,
        topic: str,
        message_encoding: str,
        schema_id: int,
        metadata: dict[str, str] | None = None,
    ) -> int:
        """Write a Channel record; returns its id."""
        if schema_id != 0 and schema_id not in self.schemas:
            raise UsageError(f"schema id {schema_id} is not registered")
        channel_id = max(self.channels, default=-1) + 1
        self._add_channel(channel_id, topic, message_encoding, schema_id, metadata or {})
        return channel_id

    def _add_channel(
        self, channel_id: int, topic: str, encoding: str, schema_id: int, meta: dict[str, str]
    ) -> None:
        self.channels[channel_id] = ChannelInfo(
            channel_id, topic, encoding, dict(meta), self.schemas.get(schema_id)
        )
        self._channel_schema[channel_id] = schema_id
        self._write(channel_record(channel_id, schema_id, topic, encoding, meta))

    def copy_channels(self, channels: dict[int, ChannelInfo]) -> None:
        """Register channels (and their schemas) with the SAME ids, for raw pass-through."""
        for channel_id in sorted(channels):
            info = channels[channel_id]
            if channel_id in self.channels:
                raise UsageError(f"channel id {channel_id} ({info.topic}) is already registered")
            schema_id = 0
            if info.schema is not None:
                schema_id = info.schema.id
                existing = self.schemas.get(schema_id)
                if existing is None:
                    self._add_schema(info.schema)
                elif existing != info.schema:
                    raise UsageError(f"schema id {schema_id} is already used by another schema")
            self._add_channel(
                channel_id, info.topic, info.message_encoding, schema_id, dict(info.metadata)
            )

    def register_json_channel(self, topic: str, schema_name: str) -> int:
        """A JSON channel (``message_encoding="json"``) with a permissive jsonschema."""
        schema_id = self.register_schema(schema_name, "jsonschema", b'{"type": "object"}')
        return self.register_channel(topic, "json", schema_id)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Write a Metadata record (values must be strings)."""
        for key, value in data.items():
            if not isinstance(key, str) or not isinstance(value, str):
                raise UsageError(f"metadata {name!r}: keys and values must be strings")
        record = _record(OP_METADATA, _string(name) + _string_map(data))
        # Chunks still compressing on worker threads are written first: the index entry
        # must hold the position the record actually lands at.
        self._drain(0)
        self._metadata_index.append((self._position, len(record), name))
        self._write_now(record)

    # --- finishing ---------------------------------------------------------------------

    def close(self) -> None:
        """Write the remaining chunk, DataEnd, summary and footer; rename into place."""
        if self._closed:
            return
        try:
            self._finish()
            self._commit_output()
        except BaseException:
            self.abort()
            raise
        finally:
            self._shutdown_executor()
        self._closed = True

    def abort(self) -> None:
        """Stop writing and remove the temporary file (nothing is left behind)."""
        if self._closed:
            return
        self._closed = True
        self._shutdown_executor()
        self._discard_output()

    def _finish(self) -> None:
        self._flush_chunk()
        self._drain(0)
        self._write(_record(OP_DATA_END, struct.pack("<I", self._data_crc)))
        statistics = _statistics_record(
            message_count=self._message_count,
            schema_count=len(self.schemas),
            channel_count=len(self.channels),
            metadata_count=len(self._metadata_index),
            chunk_count=len(self._chunk_index),
            start_time=self._start_time,
            end_time=self._end_time,
            channel_counts=self._channel_counts,
        )
        summary, footer = summary_section(
            self._position,
            schemas=self.schemas,
            channels=self.channels,
            channel_schema=self._channel_schema,
            chunk_index=self._chunk_index,
            metadata_index=self._metadata_index,
            statistics=statistics,
        )
        self._write(summary)
        self._write(footer)
        self._write(MAGIC)
