"""Copying an input log's records into an output as they are: the channels (ids kept where
free, renumbered where the writer already uses them) and the alarm events of the detectors
a new run does not replace (``imufdi detect`` on an annotated log)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import replace

import numpy as np

from imufdi_cli.errors import McapInputError
from imufdi_cli.mcapio.events import decode_events, encode_fdi_event_dicts, is_current_fdi_channel
from imufdi_cli.mcapio.records import ChannelInfo, MessageBatch
from imufdi_cli.mcapio.writer import McapWriter


class ChannelCopier:
    """Copy input channels into a writer for raw pass-through, keeping their ids where
    free and renumbering (channel and schema ids) where the writer already uses them."""

    def __init__(self, writer: McapWriter) -> None:
        self.writer = writer
        self.mapping: dict[int, int] = {}
        self._lut: np.ndarray | None = None
        self._identity: bool | None = None

    @property
    def known(self) -> set[int]:
        return set(self.mapping)

    def ensure(self, channels: Mapping[int, ChannelInfo], ids: Iterable[int]) -> None:
        for cid in sorted(ids):
            if cid in self.mapping:
                continue
            info = channels[cid]
            schema = info.schema
            if schema is not None:
                existing = self.writer.schemas.get(schema.id)
                if existing is not None and existing != schema:
                    new_id = self.writer.register_schema(schema.name, schema.encoding, schema.data)
                    schema = replace(schema, id=new_id)
            out_id = cid if cid not in self.writer.channels else max(self.writer.channels) + 1
            self.writer.copy_channels({out_id: replace(info, id=out_id, schema=schema)})
            self.mapping[cid] = out_id
            self._lut = None
            self._identity = None

    @property
    def identity(self) -> bool:
        """Every input channel keeps its id (messages can be copied as they are)."""
        if self._identity is None:
            self._identity = all(k == v for k, v in self.mapping.items())
        return self._identity

    def remap(self, batch: MessageBatch) -> MessageBatch:
        if self.identity:
            return batch
        if self._lut is None:
            self._lut = np.arange(65536, dtype=np.uint16)
            for k, v in self.mapping.items():
                self._lut[k] = v
        return replace(batch, channel_id=self._lut[batch.channel_id])


def keep_fdi_events(
    writer: McapWriter,
    channel_id: int,
    batch: MessageBatch,
    channel: ChannelInfo,
    rerun: set[str],
) -> None:
    """Copy the input's alarm events of detectors not run again onto ``channel_id``
    (CDR events of this schema as raw bytes; older FdiEvent schemas and the JSON events
    of an older imufdi re-encoded as FdiEvent)."""
    sub = batch.select(batch.channel_id == channel.id)
    try:
        events = decode_events(sub, channel)
    except McapInputError:
        return  # not readable as events: dropped like the rest of the old channel
    keep = np.array(
        [isinstance(e, dict) and e.get("detector") not in rerun for e in events], dtype=bool
    )
    if not keep.any():
        return
    if is_current_fdi_channel(channel):  # older FdiEvent schemas lack fields: re-encoded
        kept = sub.select(keep)
        writer.add_batch(replace(kept, channel_id=np.full(len(kept), channel_id, np.uint16)))
    else:
        log_time = sub.log_time[keep].tolist()
        writer.add_batch(
            encode_fdi_event_dicts(channel_id, log_time, [e for e, k in zip(events, keep) if k])
        )
