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
        The sample rate measured from the aligned stamps: (samples + missing - 1) /
        duration, where missing samples are those of the gaps (``rate_method`` says so).
    rate_method : str
        How ``rate_hz`` was measured, in words.
    start_ns, end_ns : int or None
        First and last aligned stamp.
    duration_s : float or None
    gaps : dict
        Where every topic misses samples: ``count`` (intervals longer than 1.5 sample
        periods), ``missing_samples`` (sum of round(interval / period) - 1),
        ``expected_samples`` (present + missing), ``longest_s``, ``period_s``; the period
        is the median interval of the first 256 aligned stamps.
    stats : AlignmentStats or None
        Gaps of single topics, duplicates, misalignment found while aligning.
    time_source : str or None
        ``header`` or ``log_time``: the stamps read.
    imu_fields : dict
        Imu topic -> path of the Imu inside its message type (``""``: the message is Imu).
    ingest : dict or None
        The counts of ``imufdi ingest`` (bad checksums, lost frames, dropped bytes, ...)
        from the ``imufdi.ingest`` metadata.
    ingest_record : dict or None
        The whole ``imufdi.ingest`` record, checked against its schema (None when absent
        or malformed: then a warning says so).
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
    rate_method: str = ""
    start_ns: int | None = None
    end_ns: int | None = None
    duration_s: float | None = None
    gaps: dict[str, Any] = field(default_factory=dict)
    stats: AlignmentStats | None = None
    time_source: str | None = None
    imu_fields: dict[str, str] = field(default_factory=dict)
    ingest: dict[str, Any] | None = None
    ingest_record: dict[str, Any] | None = None
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
            "rate_method": self.rate_method,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "start_utc": _utc_or_none(self.start_ns),
            "end_utc": _utc_or_none(self.end_ns),
            "duration_s": self.duration_s,
            "time_source": self.time_source,
            "imu_fields": dict(self.imu_fields),
            "gaps": dict(self.gaps),
            "ingest": self.ingest,
            "alignment": asdict(self.stats) if self.stats is not None else None,
            "array": self.array.to_dict() if self.array is not None else None,
            "array_from_metadata": self.array_from_metadata,
            "metadata_names": self.metadata_names,
            "warnings": list(self.warnings),
        }


def _utc_or_none(t_ns: int | None) -> str | None:
    """ISO 8601 UTC of a stamp, or None when it is not a calendar time (stamps counted from
    boot: before 2001-09-09, :data:`~imufdi_cli.units.UNIX_TIME_MIN_S`)."""
    from imufdi_cli.units import UNIX_TIME_MIN_S, utc_iso

    if t_ns is None or t_ns < UNIX_TIME_MIN_S * 1e9:
        return None
    return utc_iso(t_ns)


def summarize(
    source: str | os.PathLike[str] | IO[bytes],
    *,
    topics: Sequence[str] | None = None,
    strict: bool = False,
    time_source: str = "auto",
    validate_crcs: bool = True,
) -> LogSummary:
    """Topics, message counts, array, rate, duration, gaps/duplicates and metadata of a log.

    The whole log is streamed once (IMU messages are decoded and aligned to count gaps);
    message counts come from the summary section when the file has one. ``validate_crcs``
    as in :class:`McapSource` (chunk CRC-32 checks; on by default).
    """
    src = McapSource(source, strict=strict, validate_crcs=validate_crcs)
    with src:
        summary = LogSummary(source=src.name)
        counts: dict[int, int] = {}
        reader: ImuArrayReader | None = None
        try:
            reader = ImuArrayReader(src, topics=topics, strict=strict, time_source=time_source)
        except NoImuChannelError:
            if topics is not None or any(is_imu_channel(c) for c in src.channels.values()):
                raise
        first: int | None = None
        last: int | None = None
        n_samples = 0
        gaps = _GapCounter()
        if reader is not None:
            for batch, block in reader.stream():
                _count(batch.channel_id, counts)
                if len(block):
                    first = int(block.t_ns[0]) if first is None else first
                    last = int(block.t_ns[-1])
                    n_samples += len(block)
                    gaps.add(block.t_ns)
            summary.imu_topics = list(reader.imu_topics)
            summary.imu_fields = dict(reader.imu_fields)
            summary.time_source = reader.time_source
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
        summary.gaps = gaps.result(n_samples)
        if first is not None and last is not None:
            summary.start_ns, summary.end_ns = first, last
            summary.duration_s = (last - first) * 1e-9
            if n_samples > 1 and last > first:
                missing = summary.gaps["missing_samples"]
                summary.rate_hz = (n_samples + missing - 1) / summary.duration_s
                stamps = "header stamps" if summary.time_source == "header" else "log times"
                summary.rate_method = (
                    f"({n_samples} aligned samples + {missing} missing - 1) /"
                    f" {summary.duration_s:.6g} s, from the {stamps}"
                )
        summary.metadata = dict(src.metadata)
        summary.warnings = list(src.warnings)
        from imufdi_cli.metadata import ingest_record

        summary.ingest_record = ingest_record(summary.metadata, summary.warnings)
        summary.ingest = _ingest_counts(summary.ingest_record)
    return summary


class _GapCounter:
    """Intervals between aligned samples longer than 1.5 periods, streamed block by block.

    The period is the median interval of the first ``HEAD`` samples (all of them for a
    shorter log); those are held until it is known."""

    HEAD = 256

    def __init__(self) -> None:
        self.period_ns: float | None = None
        self.head: list[np.ndarray] = []
        self.last: int | None = None
        self.count = 0
        self.missing = 0
        self.longest_ns = 0

    def add(self, t_ns: np.ndarray) -> None:
        if self.period_ns is None:
            self.head.append(np.asarray(t_ns, np.int64))
            if sum(h.shape[0] for h in self.head) >= self.HEAD:
                self._start()
            return
        self._scan(np.asarray(t_ns, np.int64))

    def _start(self) -> None:
        t = np.concatenate(self.head) if self.head else np.zeros(0, np.int64)
        self.head = []
        steps = np.diff(t)
        positive = steps[steps > 0]
        if positive.size == 0:
            return
        self.period_ns = float(np.median(positive))
        self._scan(t)

    def _scan(self, t: np.ndarray) -> None:
        if t.shape[0] == 0:
            return
        if self.last is not None:
            t = np.concatenate([[self.last], t])
        self.last = int(t[-1])
        assert self.period_ns is not None
        steps = np.diff(t)
        long = steps[steps > 1.5 * self.period_ns]
        if long.size:
            self.count += int(long.size)
            self.missing += int(np.sum(np.round(long / self.period_ns).astype(np.int64) - 1))
            self.longest_ns = max(self.longest_ns, int(long.max()))

    def result(self, n_samples: int) -> dict[str, Any]:
        if self.period_ns is None:
            self._start()
        return {
            "count": self.count,
            "missing_samples": self.missing,
            "expected_samples": n_samples + self.missing,
            "longest_s": self.longest_ns * 1e-9,
            "period_s": None if self.period_ns is None else self.period_ns * 1e-9,
        }


def _ingest_counts(record: dict[str, Any] | None) -> dict[str, Any] | None:
    """The ``stats`` of the checked ``imufdi.ingest`` record (None when absent)."""
    stats = None if record is None else record.get("stats")
    return dict(stats) if isinstance(stats, dict) else None


def _count(channel_ids: np.ndarray, counts: dict[int, int]) -> None:
    if channel_ids.size == 0:
        return
    ids, n = np.unique(channel_ids, return_counts=True)
    for cid, c in zip(ids.tolist(), n.tolist()):
        counts[cid] = counts.get(cid, 0) + c
