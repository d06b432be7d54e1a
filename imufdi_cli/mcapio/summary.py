"""``summarize``: what ``imufdi info`` shows about an MCAP log."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import IO, Any

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.mcapio.imu import (
    AlignmentStats,
    ImuArrayReader,
    NoImuChannelError,
    is_imu_channel,
    natural_key,
)
from imufdi_cli.mcapio.source import McapSource


@dataclass
class TopicSummary:
    topic: str
    schema: str
    message_encoding: str
    message_count: int


@dataclass
class LogSummary:
    """Summary of an MCAP log.

    Attributes
    ----------
    topics : list of TopicSummary
        Every channel, sorted naturally by topic.
    imu_topics : list of str
        Imu topics read as the array, in array order (empty if there are none).
    n_imus : int
    n_samples : int
        Aligned array samples.
    rate_hz : float or None
        Measured rate of the aligned samples ((N - 1) / duration).
    start_ns, end_ns : int or None
        First and last aligned stamp.
    duration_s : float or None
    stats : AlignmentStats or None
        Gaps, duplicates, misalignment found while aligning.
    array : ArrayConfig or None
        From ``imufdi.array`` metadata or inferred.
    array_from_metadata : bool
    metadata : dict
        All metadata records (name -> string map).
    warnings : list of str
    """

    source: str
    topics: list[TopicSummary] = field(default_factory=list)
    imu_topics: list[str] = field(default_factory=list)
    n_imus: int = 0
    n_samples: int = 0
    rate_hz: float | None = None
    start_ns: int | None = None
    end_ns: int | None = None
    duration_s: float | None = None
    stats: AlignmentStats | None = None
    array: ArrayConfig | None = None
    array_from_metadata: bool = False
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    @property
    def metadata_names(self) -> list[str]:
        return sorted(self.metadata)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "source": self.source,
            "topics": [asdict(t) for t in self.topics],
            "imu_topics": list(self.imu_topics),
            "n_imus": self.n_imus,
            "n_samples": self.n_samples,
            "rate_hz": self.rate_hz,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "duration_s": self.duration_s,
            "alignment": asdict(self.stats) if self.stats is not None else None,
            "array": self.array.to_dict() if self.array is not None else None,
            "array_from_metadata": self.array_from_metadata,
            "metadata_names": self.metadata_names,
            "warnings": list(self.warnings),
        }


def summarize(
    source: str | os.PathLike[str] | IO[bytes],
    *,
    topics: Sequence[str] | None = None,
    strict: bool = False,
) -> LogSummary:
    """Topics, message counts, array, rate, duration, gaps/duplicates and metadata of a log.

    The whole log is streamed once (IMU messages are decoded and aligned to count gaps);
    message counts come from the summary section when the file has one.
    """
    src = McapSource(source, strict=strict)
    with src:
        summary = LogSummary(source=src.name)
        counts: dict[int, int] = {}
        reader: ImuArrayReader | None = None
        try:
            reader = ImuArrayReader(src, topics=topics, strict=strict)
        except NoImuChannelError:
            if topics is not None or any(is_imu_channel(c) for c in src.channels.values()):
                raise
        first: int | None = None
        last: int | None = None
        n_samples = 0
        if reader is not None:
            for batch, block in reader.stream():
                _count(batch.channel_id, counts)
                if len(block):
                    first = int(block.t_ns[0]) if first is None else first
                    last = int(block.t_ns[-1])
                    n_samples += len(block)
            summary.imu_topics = list(reader.imu_topics)
            summary.n_imus = len(reader.imu_topics)
            summary.stats = reader.stats
            summary.array = reader.array
            summary.array_from_metadata = "imufdi.array" in src.metadata and not any(
                "imufdi.array" in w for w in reader.warnings
            )
        else:
            for batch in src.batches():
                _count(batch.channel_id, counts)
        if src.summary_channel_counts is not None and not src.warnings:
            counts = dict(src.summary_channel_counts)
        summary.topics = sorted(
            (
                TopicSummary(
                    c.topic,
                    c.schema.name if c.schema is not None else "",
                    c.message_encoding,
                    int(counts.get(c.id, 0)),
                )
                for c in src.channels.values()
            ),
            key=lambda t: natural_key(t.topic),
        )
        summary.n_samples = n_samples
        if first is not None and last is not None:
            summary.start_ns, summary.end_ns = first, last
            summary.duration_s = (last - first) * 1e-9
            if n_samples > 1 and last > first:
                summary.rate_hz = (n_samples - 1) / summary.duration_s
        summary.metadata = dict(src.metadata)
        summary.warnings = list(src.warnings)
    return summary


def _count(channel_ids: np.ndarray, counts: dict[int, int]) -> None:
    if channel_ids.size == 0:
        return
    ids, n = np.unique(channel_ids, return_counts=True)
    for cid, c in zip(ids.tolist(), n.tolist()):
        counts[cid] = counts.get(cid, 0) + c
