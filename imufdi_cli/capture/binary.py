"""Streaming, vectorised parser of fixed-layout binary frames.

Each round appends a chunk to the carried-over tail and, with numpy only:

1. finds every occurrence of the sync bytes (one comparison per sync byte over the buffer);
2. reads the header of every candidate at once, drops candidates whose ``expect`` fields
   or IMU count are impossible, and computes each candidate's frame length;
3. verifies the checksums of all candidates that fit in the buffer at once
   (:mod:`imufdi_cli.capture.checksum`);
4. keeps valid frames that do not overlap (fast path: no overlap at all; otherwise a walk
   along the chain "next valid frame starting at or after my end");
5. classifies the remaining plausible candidates that do not start inside a kept frame:
   bad checksum (complete, ends before the next kept frame) or truncated (overlaps the
   next kept frame, or runs past the end of the capture);
6. decodes the kept frames, unwraps counter and timestamp with the state carried from the
   previous round, drops duplicates and counts counter gaps.

Anything that may belong to a frame not yet complete is carried over to the next round,
so memory stays bounded by the chunk size plus one frame.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from imufdi_cli.capture.checksum import compute_checksums
from imufdi_cli.capture.layout import HeaderField, Layout, RecordField
from imufdi_cli.capture.stats import IngestStats
from imufdi_cli.errors import CaptureError
from imufdi_cli.log import ImuBlock


def _field_values(rows: np.ndarray, offset: int, size: int, dtype: np.dtype) -> np.ndarray:
    """Values of one field at byte ``offset`` of every row of ``rows`` (..., W) uint8 ->
    (...,): a strided view (no copy) when the rows' bytes are contiguous."""
    raw = rows[..., offset : offset + size]
    if raw.strides[-1] != 1:
        raw = np.ascontiguousarray(raw)
    return raw.view(dtype)[..., 0]


def find_sync(data: np.ndarray, sync: bytes) -> np.ndarray:
    """Start offsets of every occurrence of ``sync`` in ``data`` (uint8), shape (K,) intp."""
    n = data.shape[0] - len(sync) + 1
    if n <= 0:
        return np.zeros(0, dtype=np.intp)
    mask = data[:n] == sync[0]
    for k in range(1, len(sync)):
        mask &= data[k : k + n] == sync[k]
    return np.flatnonzero(mask)


def _stored_checksum(frames: np.ndarray, at: int, size: int, endian: str) -> np.ndarray:
    """The stored checksums (F,), uint32 (uint64 for more than 4 bytes: CRC-64)."""
    dtype = np.dtype(np.uint32 if size <= 4 else np.uint64)
    raw = frames[:, at : at + size].astype(dtype)
    order = range(size) if endian == "big" else range(size - 1, -1, -1)
    value = np.zeros(frames.shape[0], dtype=dtype)
    eight = np.array(8, dtype=dtype)
    for k in order:
        value = np.left_shift(value, eight) | raw[:, k]
    return value


def checksums_ok(layout: Layout, frames: np.ndarray) -> np.ndarray:
    """Whether each frame (F, L) carries a valid checksum, shape (F,) bool."""
    spec = layout.checksum
    if spec.kind == "none":
        return np.ones(frames.shape[0], dtype=bool)
    start, end, at = spec.resolve(frames.shape[1])
    computed = compute_checksums(spec.kind, frames[:, start:end], spec.model)
    return computed == _stored_checksum(frames, at, spec.size, spec.endian)


@dataclass
class _Round:
    """What one scan of the buffer decided."""

    starts: np.ndarray  # kept frame starts (K,)
    frame_size: int
    consumed: int  # bytes of the buffer resolved this round
    bad_checksum: int
    truncated: int


class BinaryFrameParser:
    """Incremental parser: feed chunks, get ImuBlocks; counts go to ``stats``."""

    def __init__(
        self,
        layout: Layout,
        stats: IngestStats,
        *,
        rate_hz: float | None = None,
        strict: bool = False,
    ) -> None:
        if layout.kind != "binary":
            raise CaptureError(f"layout {layout.name!r} is not a binary frame layout")
        self.layout = layout
        self.stats = stats
        self.strict = strict
        self.n_imus: int | None = layout.n_imus
        self._counter = layout.role("counter")
        self._timestamp = layout.role("timestamp")
        self._count_field = layout.role("imu_count")
        rate = rate_hz if rate_hz is not None else layout.rate_hz
        if self._timestamp is None and rate is None:
            raise CaptureError(
                f"layout {layout.name!r} has no timestamp field: give the sample rate (rate_hz)"
            )
        self._period_ns = None if rate is None else 1e9 / rate
        self._buffer = b""
        self._offset = 0  # stream offset of the buffer's first byte
        self._last_counter: int | None = None
        self._last_time: int | None = None
        self._counter_unwrapped = 0
        self._time_unwrapped = 0
        self._frames_seen = 0

    # --- public ---------------------------------------------------------------------

    def feed(self, chunk: bytes, *, final: bool = False) -> ImuBlock | None:
        """Add ``chunk``; return the samples of the frames resolved so far (or None)."""
        self.stats.bytes_total += len(chunk)
        buffer = self._buffer + chunk if self._buffer else bytes(chunk)
        data = np.frombuffer(buffer, dtype=np.uint8)
        result = self._scan(data, final)
        dropped = result.consumed - result.starts.size * result.frame_size
        self.stats.frames_bad_checksum += result.bad_checksum
        self.stats.frames_truncated += result.truncated
        block = None
        if result.starts.size:
            block, duplicates = self._decode(data, result.starts, result.frame_size)
            dropped += duplicates * result.frame_size
        self.stats.bytes_dropped += dropped
        if self.strict and dropped:
            raise CaptureError(
                f"strict: {dropped} bytes dropped between stream offsets {self._offset} and "
                f"{self._offset + result.consumed} (garbage, bad checksum, truncated or "
                f"duplicated frames)"
            )
        self._offset += result.consumed
        self._buffer = buffer[result.consumed :]
        return block

    # --- scanning -------------------------------------------------------------------

    def _scan(self, data: np.ndarray, final: bool) -> _Round:
        layout = self.layout
        size = data.shape[0]
        header_end = layout.header_end
        candidates = find_sync(data, layout.sync)
        # candidates whose header is complete, and whose header values are possible
        has_header = candidates + header_end <= size
        full = candidates[has_header]
        plausible = np.ones(full.size, dtype=bool)
        counts = np.full(full.size, self.n_imus or 0, dtype=np.int64)
        if full.size:
            headers = sliding_window_view(data, header_end)[full]
            for item in layout.header:
                if item.expect is None and item.role != "imu_count":
                    continue
                values = _field_values(headers, item.offset, item.size, item.dtype)
                if item.expect is not None:
                    plausible &= values == item.expect
                if item.role == "imu_count":
                    counts = values.astype(np.int64)
                    plausible &= (counts >= 1) & (counts <= layout.max_imus)
                    if self.n_imus is not None:
                        plausible &= counts == self.n_imus
        lengths = layout.frame_size(0) + counts * layout.record_size
        fits = full + lengths <= size
        valid = np.zeros(full.size, dtype=bool)
        check = np.flatnonzero(plausible & fits)
        checked = lengths[check]
        one_length = checked.size == 0 or int(checked.min()) == int(checked.max())
        for length in checked[:1] if one_length else np.unique(checked):
            group = check if one_length else check[checked == length]
            frames = sliding_window_view(data, int(length))[full[group]]
            valid[group] = checksums_ok(layout, frames)
        if self.n_imus is None and valid.any():
            # the first valid frame fixes the IMU count of the capture
            self.n_imus = int(counts[np.argmax(valid)])
            self.stats.n_imus = self.n_imus
            same = counts == self.n_imus
            plausible &= same
            valid &= same
        elif self.n_imus is not None:
            self.stats.n_imus = self.n_imus
        frame_size = layout.frame_size(self.n_imus or 0)

        kept = _non_overlapping(full[valid], frame_size)
        kept_ends = kept + frame_size

        # plausible candidates that are not valid and do not start inside a kept frame,
        # plus candidates whose header is not complete yet (end of buffer)
        other_starts = np.concatenate([full[plausible & ~valid], candidates[~has_header]])
        other_lengths = np.concatenate(
            [lengths[plausible & ~valid], np.full((~has_header).sum(), -1, dtype=np.int64)]
        )
        order = np.argsort(other_starts, kind="stable")
        other_starts = other_starts[order]
        other_lengths = other_lengths[order]
        if other_starts.size and kept.size:
            before = np.searchsorted(kept, other_starts, side="right") - 1
            inside = (before >= 0) & (other_starts < kept_ends[np.maximum(before, 0)])
            other_starts = other_starts[~inside]
            other_lengths = other_lengths[~inside]

        # resolution boundary: everything before it is decided this round
        boundary = size if final else size - (len(layout.sync) - 1)
        bad = 0
        truncated = 0
        if not final:
            pending = (other_lengths < 0) | (other_starts + other_lengths > size)
            if pending.any():
                boundary = min(boundary, int(other_starts[np.argmax(pending)]))
        previous_end = 0
        for start, length in zip(other_starts.tolist(), other_lengths.tolist()):
            if start >= boundary:
                break
            if start < previous_end:
                continue
            end = start + length if length >= 0 else size + 1
            if not final and end > boundary:
                boundary = start  # its fate depends on bytes not read yet
                break
            next_kept = int(np.searchsorted(kept, start, side="right"))
            next_start = int(kept[next_kept]) if next_kept < kept.size else None
            if end > size or (next_start is not None and next_start < end):
                truncated += 1
                previous_end = min(end, next_start) if next_start is not None else end
            else:
                bad += 1
                previous_end = end
        selected = kept[kept < boundary] if not final else kept
        consumed = boundary
        if selected.size:
            consumed = max(consumed, int(selected[-1]) + frame_size)
        return _Round(
            starts=selected,
            frame_size=frame_size,
            consumed=int(consumed),
            bad_checksum=bad,
            truncated=truncated,
        )

    # --- decoding -------------------------------------------------------------------

    def _decode(
        self, data: np.ndarray, starts: np.ndarray, frame_size: int
    ) -> tuple[ImuBlock, int]:
        layout = self.layout
        n_imus = self.n_imus or 0
        frames = sliding_window_view(data, frame_size)[starts]
        n_frames = frames.shape[0]
        keep = np.ones(n_frames, dtype=bool)

        counter_raw = time_raw = None
        if self._counter is not None:
            counter_raw = _field_values(
                frames, self._counter.offset, self._counter.size, self._counter.dtype
            ).astype(np.int64)
        if self._timestamp is not None:
            time_raw = _field_values(
                frames, self._timestamp.offset, self._timestamp.size, self._timestamp.dtype
            ).astype(np.int64)

        # duplicates: same counter and timestamp as the previous frame
        same = np.zeros(n_frames, dtype=bool)
        if counter_raw is not None or time_raw is not None:
            same[:] = True
            for raw, last in ((counter_raw, self._last_counter), (time_raw, self._last_time)):
                if raw is None:
                    continue
                previous = np.concatenate([[raw[0] - 1 if last is None else last], raw[:-1]])
                same &= raw == previous
            keep &= ~same
        duplicates = int(same.sum())
        self.stats.duplicates += duplicates

        t_ns: np.ndarray
        if counter_raw is not None:
            assert self._counter is not None
            counter_unwrapped, steps = self._unwrap(counter_raw[keep], self._counter, "counter")
            gaps = steps - 1
            self.stats.frames_lost += int(gaps[gaps > 0].sum())
        if time_raw is not None:
            assert self._timestamp is not None and self._timestamp.tick_s is not None
            ticks, _ = self._unwrap(time_raw[keep], self._timestamp, "timestamp")
            tick_ns = self._timestamp.tick_s * 1e9
            if abs(tick_ns - round(tick_ns)) < 1e-9 and tick_ns >= 1:
                t_ns = ticks * round(tick_ns)
            else:
                t_ns = np.round(ticks * tick_ns).astype(np.int64)
        elif counter_raw is not None:
            assert self._period_ns is not None
            t_ns = np.round(counter_unwrapped * self._period_ns).astype(np.int64)
        else:
            assert self._period_ns is not None
            index = self._frames_seen + np.arange(int(keep.sum()), dtype=np.int64)
            t_ns = np.round(index * self._period_ns).astype(np.int64)
        self._frames_seen += int(keep.sum())
        self.stats.frames_ok += int(keep.sum())

        if duplicates:
            frames = frames[keep]
        triads = _decode_triads(layout, frames, n_imus)
        return ImuBlock(t_ns=t_ns, **triads), duplicates

    def _unwrap(
        self, raw: np.ndarray, item: HeaderField, what: str
    ) -> tuple[np.ndarray, np.ndarray]:
        """Unwrapped values (K,) int64 and the step from the previous frame (K,)."""
        assert item.wrap_bits is not None
        modulus = 1 << item.wrap_bits
        half = modulus >> 1
        raw = raw & (modulus - 1)
        last = self._last_counter if what == "counter" else self._last_time
        if raw.size == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        previous = np.concatenate([[raw[0] - 1 if last is None else last], raw[:-1]])
        steps = (raw - previous) % modulus
        backwards = steps >= max(half, 1)
        wraps = (raw < previous) & ~backwards
        steps = np.where(backwards, steps - modulus, steps)
        if last is None:
            steps[0] = 0
        base = (
            int(raw[0])
            if last is None
            else (self._counter_unwrapped if what == "counter" else self._time_unwrapped)
        )
        unwrapped = base + np.cumsum(steps)
        if last is None:
            steps[0] = 1
        if what == "counter":
            self.stats.counter_wraps += int(wraps.sum())
            self.stats.counter_jumps += int(backwards.sum())
            self._last_counter = int(raw[-1])
            self._counter_unwrapped = int(unwrapped[-1])
        else:
            self.stats.timestamp_wraps += int(wraps.sum())
            self.stats.timestamp_jumps += int(backwards.sum())
            self._last_time = int(raw[-1])
            self._time_unwrapped = int(unwrapped[-1])
        return unwrapped, steps


def _sensor_fields(layout: Layout) -> dict[str, list[RecordField]]:
    """The x, y, z record fields of each sensor type of the layout."""
    by_name = {f.name: f for f in layout.record}
    return {s: [by_name[f"{s}_{a}"] for a in "xyz"] for s in layout.sensor_types}


def _decode_triads(layout: Layout, frames: np.ndarray, n_imus: int) -> dict[str, np.ndarray]:
    """Sensor triads (F, m, 3) float64 in SI of frames (F, frame size) uint8.

    ``value = raw * scale`` per field. When every sensor field is an integer of one type
    and the record size is a multiple of it, each triad's integers are gathered from the
    record region with one ``np.take``, converted to float64 in one cast (byte order
    included) and scaled in one product; otherwise each field is read through a strided
    view. The values are the same either way.
    """
    n_frames = frames.shape[0]
    fields = _sensor_fields(layout)
    start = layout.header_end
    stop = start + n_imus * layout.record_size
    items = [f for triad in fields.values() for f in triad]
    dtype = items[0].dtype if items else None
    size = items[0].size if items else 1
    uniform = (
        dtype is not None
        and all(f.is_integer and f.dtype == dtype and f.offset % size == 0 for f in items)
        and layout.record_size % size == 0
        and frames.strides[-1] == 1
    )
    triads: dict[str, np.ndarray] = {}
    if uniform:
        assert dtype is not None
        columns = (
            frames[:, start:stop].view(dtype).reshape(n_frames, n_imus, layout.record_size // size)
        )
        for sensor, triad in fields.items():
            # the triad's integers gathered first, then one cast (byte order included):
            # no float64 copy of the fields no triad uses
            raw = np.take(columns, [item.offset // size for item in triad], axis=2)
            if triad[0].scale == triad[1].scale == triad[2].scale:
                # cast and product in one pass: float64(raw) * scale, as cast-then-scale
                values = np.multiply(raw, triad[0].scale, dtype=np.float64)
            else:
                values = raw.astype(np.float64)
                for axis, item in enumerate(triad):
                    values[..., axis] *= item.scale
            triads[sensor] = values
        return triads
    # (F, m, record size) view of the IMU records: every field is a strided view
    records = np.lib.stride_tricks.as_strided(
        frames[:, start:],
        shape=(n_frames, n_imus, layout.record_size),
        strides=(frames.strides[0], layout.record_size, frames.strides[1]),
        writeable=False,
    )
    for sensor, triad in fields.items():
        values = np.empty((n_frames, n_imus, 3), dtype=np.float64)
        for axis, item in enumerate(triad):
            raw = _field_values(records, item.offset, item.size, item.dtype)
            # float fields carry whatever bits the board sent (NaN, huge): no warnings
            with np.errstate(all="ignore"):
                values[:, :, axis] = raw * item.scale
        triads[sensor] = values
    return triads


def _non_overlapping(starts: np.ndarray, frame_size: int) -> np.ndarray:
    """Greedy choice of non-overlapping frames among sorted valid ``starts``."""
    if starts.size < 2 or np.all(np.diff(starts) >= frame_size):
        return starts
    following = np.searchsorted(starts, starts + frame_size, side="left")
    chosen = []
    index = 0
    count = starts.size
    following_list = following.tolist()
    while index < count:
        chosen.append(index)
        index = following_list[index]
    return starts[np.asarray(chosen, dtype=np.intp)]


def iter_binary_blocks(
    chunks: Iterator[bytes],
    layout: Layout,
    stats: IngestStats,
    *,
    rate_hz: float | None = None,
    strict: bool = False,
) -> Iterator[ImuBlock]:
    """ImuBlocks of the frames in a stream of byte chunks (one block per chunk at most)."""
    parser = BinaryFrameParser(layout, stats, rate_hz=rate_hz, strict=strict)
    pending: bytes | None = None
    for chunk in chunks:
        if pending is not None:
            block = parser.feed(pending)
            if block is not None and len(block):
                yield block
        pending = chunk
    block = parser.feed(pending or b"", final=True)
    if block is not None and len(block):
        yield block
    stats.complete = True
