"""Encode ImuBlocks as raw captures in a layout, optionally with deliberate corruption.

Used by ``imufdi simulate --capture`` and by the tests: because the encoder reports
exactly which frames it damaged, a test knows how many intact frames the parser must
recover and what every counter must read.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.capture.checksum import compute_checksums
from imufdi_cli.capture.layout import Layout
from imufdi_cli.errors import CaptureError, LayoutError
from imufdi_cli.log import ImuBlock


@dataclass(frozen=True)
class Corruption:
    """How many corrupted stretches to inject (each at a different frame).

    Attributes
    ----------
    garbage : int
        Stretches of random bytes inserted between frames. The bytes never include the
        first sync byte, so they can never be mistaken for a frame.
    garbage_size : tuple of int
        Inclusive (min, max) length of each stretch, bytes.
    flipped : int
        Frames with one bit flipped inside the IMU records (the checksum no longer matches).
    cut : int
        Frames cut short (sync and header kept, then part of the records), immediately
        followed by the next frame.
    dropped : int
        Frames left out entirely (a counter gap).
    duplicated : int
        Frames sent twice in a row.
    """

    garbage: int = 0
    garbage_size: tuple[int, int] = (1, 64)
    flipped: int = 0
    cut: int = 0
    dropped: int = 0
    duplicated: int = 0

    @property
    def events(self) -> int:
        return self.garbage + self.flipped + self.cut + self.dropped + self.duplicated


@dataclass
class EncodedCapture:
    """Bytes of an encoded capture and exactly what was corrupted.

    Attributes
    ----------
    data : bytes
        The capture.
    frame_size : int
        Bytes per frame.
    intact : ndarray, shape (N,), bool
        Samples of the input block whose frame arrives intact (once).
    garbage_bytes : int
        Total garbage bytes inserted.
    flipped, cut, dropped, duplicated : ndarray of int
        Sample indices of the frames damaged in each way.
    cut_bytes : int
        Bytes of the cut frames that were sent.
    """

    data: bytes
    frame_size: int
    intact: np.ndarray
    garbage_bytes: int = 0
    flipped: np.ndarray = field(default_factory=lambda: np.zeros(0, np.intp))
    cut: np.ndarray = field(default_factory=lambda: np.zeros(0, np.intp))
    dropped: np.ndarray = field(default_factory=lambda: np.zeros(0, np.intp))
    duplicated: np.ndarray = field(default_factory=lambda: np.zeros(0, np.intp))
    cut_bytes: int = 0

    def expected_stats(self, *, has_counter: bool = True) -> dict[str, int]:
        """The IngestStats counts a correct parser must report for this capture."""
        damaged = self.flipped.size + self.cut.size + self.dropped.size
        return {
            "bytes_total": len(self.data),
            "bytes_dropped": self.garbage_bytes
            + self.frame_size * (self.flipped.size + self.duplicated.size)
            + self.cut_bytes,
            "frames_ok": int(self.intact.sum()),
            "frames_bad_checksum": int(self.flipped.size),
            "frames_truncated": int(self.cut.size),
            "frames_lost": damaged if has_counter else 0,
            "duplicates": int(self.duplicated.size),
        }


def _write(frames: np.ndarray, offset: int, values: np.ndarray, dtype: np.dtype) -> None:
    """Write ``values`` (N,) or (N, m) as ``dtype`` at byte ``offset`` of each row."""
    raw = np.ascontiguousarray(values.astype(dtype)).view(np.uint8)
    frames[..., offset : offset + dtype.itemsize] = raw.reshape(*values.shape, dtype.itemsize)


def _to_raw(values: np.ndarray, scale: float, dtype: np.dtype, offset: float = 0.0) -> np.ndarray:
    scaled = (np.nan_to_num(values, nan=0.0) - offset) / scale
    if dtype.kind in "ui":
        info = np.iinfo(dtype)
        return np.clip(np.round(scaled), info.min, info.max)
    return scaled


def encode_frames(
    block: ImuBlock,
    layout: Layout,
    *,
    start_counter: int = 0,
    temperature_c: float = 25.0,
) -> np.ndarray:
    """Frames of a block, shape (N, frame_size) uint8, with valid checksums.

    Values are rounded to the nearest LSB and saturate at the field's range; missing
    sensor types are written as 0. Counter ``i`` of sample ``i`` is
    ``start_counter + i`` modulo its wrap; timestamps are ``t_ns / tick`` modulo theirs.
    """
    if layout.kind != "binary":
        raise LayoutError(f"layout {layout.name!r} is not a binary layout; cannot encode frames")
    n_samples = len(block)
    n_imus = block.n_imus if layout.n_imus is None else layout.n_imus
    if layout.n_imus is not None and block.n_imus not in (0, layout.n_imus):
        raise LayoutError(
            f"layout {layout.name!r} has {layout.n_imus} IMUs per frame, the block has "
            f"{block.n_imus}"
        )
    if not 1 <= n_imus <= layout.max_imus:
        raise LayoutError(f"layout {layout.name!r} takes 1..{layout.max_imus} IMUs, got {n_imus}")
    size = layout.frame_size(n_imus)
    frames = np.zeros((n_samples, size), dtype=np.uint8)
    frames[:, : len(layout.sync)] = np.frombuffer(layout.sync, dtype=np.uint8)
    index = np.arange(n_samples, dtype=np.int64)
    for item in layout.header:
        if item.type == "pad":
            continue
        if item.role == "counter":
            assert item.wrap_bits is not None
            values = (start_counter + index) % (1 << item.wrap_bits)
        elif item.role == "timestamp":
            assert item.tick_s is not None and item.wrap_bits is not None
            ticks = np.round(block.t_ns.astype(np.float64) / (item.tick_s * 1e9))
            values = ticks.astype(np.int64) % (1 << item.wrap_bits)
        elif item.role == "imu_count":
            values = np.full(n_samples, n_imus, dtype=np.int64)
        else:
            values = np.full(n_samples, item.expect or 0, dtype=np.int64)
        _write(frames, item.offset, values, item.dtype)
    records = np.zeros((n_samples, n_imus, layout.record_size), dtype=np.uint8)
    for record_field in layout.record:
        if record_field.type == "pad":
            continue
        if record_field.name == "temperature":
            raw = _to_raw(
                np.full((n_samples, n_imus), temperature_c),
                record_field.scale,
                record_field.dtype,
                record_field.value_offset,
            )
        else:
            sensor, axis = record_field.name.split("_")
            triads = block.get(sensor)
            if triads is None:
                continue
            raw = _to_raw(triads[:, :, "xyz".index(axis)], record_field.scale, record_field.dtype)
        _write(records, record_field.offset, raw, record_field.dtype)
    start = layout.header_end
    frames[:, start : start + n_imus * layout.record_size] = records.reshape(n_samples, -1)
    spec = layout.checksum
    if spec.kind != "none" and n_samples:
        cs_start, cs_end, at = spec.resolve(size)
        values = compute_checksums(spec.kind, frames[:, cs_start:cs_end], spec.model)
        shifts = np.arange(spec.size, dtype=np.uint64) * np.uint64(8)  # any size: CRC-24
        stored = ((values.astype(np.uint64)[:, None] >> shifts) & np.uint64(0xFF)).astype(np.uint8)
        frames[:, at : at + spec.size] = stored if spec.endian == "little" else stored[:, ::-1]
    return frames


def encode_capture(
    block: ImuBlock,
    layout: Layout,
    *,
    corrupt: Corruption | None = None,
    rng: np.random.Generator | None = None,
    start_counter: int = 0,
    temperature_c: float = 25.0,
) -> EncodedCapture:
    """The raw bytes of ``block`` in ``layout``, optionally deliberately corrupted.

    Parameters
    ----------
    block : ImuBlock
        N samples of m IMUs (SI units).
    layout : Layout
        A binary layout (CSV layouts are written with :func:`encode_csv`).
    corrupt : Corruption or None
        What to damage. Damaged frames are chosen among samples 1..N-2, at least three
        frames apart, so that every event is counted exactly once by the parser.
    rng : numpy.random.Generator
        Required when ``corrupt`` is given.
    start_counter : int
        Counter value of the first frame.
    temperature_c : float
        Temperature written in every record that has one, degC.

    Returns
    -------
    EncodedCapture
    """
    frames = encode_frames(block, layout, start_counter=start_counter, temperature_c=temperature_c)
    n_samples, frame_size = frames.shape
    intact = np.ones(n_samples, dtype=bool)
    if corrupt is None or corrupt.events == 0:
        return EncodedCapture(data=frames.tobytes(), frame_size=frame_size, intact=intact)
    if rng is None:
        raise CaptureError("encode_capture: corruption needs an explicit rng")
    if corrupt.flipped and layout.checksum.kind == "none":
        raise LayoutError(
            f"layout {layout.name!r} has no checksum: flipped bits would not be detectable"
        )
    chosen, (garbage_at, flipped, cut, dropped, duplicated) = _choose_damage(
        corrupt, n_samples, rng
    )
    intact[flipped] = False
    intact[cut] = False
    intact[dropped] = False
    data, garbage_total, cut_total = _damaged_bytes(
        frames, layout, corrupt, chosen, (garbage_at, flipped, cut, duplicated), rng
    )
    return EncodedCapture(
        data=data,
        frame_size=frame_size,
        intact=intact,
        garbage_bytes=garbage_total,
        flipped=flipped,
        cut=cut,
        dropped=dropped,
        duplicated=duplicated,
        cut_bytes=cut_total,
    )


def _choose_damage(
    corrupt: Corruption, n_samples: int, rng: np.random.Generator
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Frames to damage (samples 1..N-2, three apart) and, per kind (garbage, flipped,
    cut, dropped, duplicated), the sorted frame indices of that kind."""
    slots = np.arange(1, n_samples - 1, 3)
    if corrupt.events > slots.size:
        raise CaptureError(
            f"encode_capture: {corrupt.events} corruptions need at least "
            f"{3 * corrupt.events + 2} samples, the block has {n_samples}"
        )
    chosen = rng.choice(slots, size=corrupt.events, replace=False)
    kinds = np.repeat(
        np.arange(5),
        [corrupt.garbage, corrupt.flipped, corrupt.cut, corrupt.dropped, corrupt.duplicated],
    )
    return chosen, [np.sort(chosen[kinds == k]) for k in range(5)]


def _damaged_bytes(
    frames: np.ndarray,
    layout: Layout,
    corrupt: Corruption,
    chosen: np.ndarray,
    kinds: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    rng: np.random.Generator,
) -> tuple[bytes, int, int]:
    """The frames (F, L) as bytes with the chosen ones damaged: garbage before, a flipped
    bit in the records, cut short, duplicated, or (any other) dropped. Returns (bytes,
    garbage bytes, bytes of cut frames)."""
    garbage_at, flipped, cut, duplicated = kinds
    frame_size = frames.shape[1]
    records_start = layout.header_end
    records_end = (
        frame_size
        - layout.trailer_size
        - (layout.checksum.size if layout.checksum.at is None else 0)
    )
    sync0 = layout.sync[0]
    pieces: list[bytes] = []
    garbage_total = 0
    cut_total = 0
    previous = 0
    for index in np.sort(chosen).tolist():
        pieces.append(frames[previous:index].tobytes())
        frame = frames[index].copy()
        if index in garbage_at:
            low, high = corrupt.garbage_size
            length = int(rng.integers(max(low, 1), max(high, low, 1) + 1))
            junk = rng.integers(0, 255, size=length)
            junk[junk >= sync0] += 1
            pieces.append(junk.astype(np.uint8).tobytes())
            garbage_total += length
            pieces.append(frame.tobytes())
        elif index in flipped:
            position = int(rng.integers(records_start, records_end))
            frame[position] ^= np.uint8(1 << int(rng.integers(0, 8)))
            pieces.append(frame.tobytes())
        elif index in cut:
            keep = int(rng.integers(records_start + 1, frame_size))
            pieces.append(frame[:keep].tobytes())
            cut_total += keep
        elif index in duplicated:
            pieces.append(frame.tobytes() * 2)
        # dropped: nothing
        previous = index + 1
    pieces.append(frames[previous:].tobytes())
    return b"".join(pieces), garbage_total, cut_total


#: corruption injected per block by ``CaptureEncoder(corrupt=True)``
DEFAULT_CORRUPTION = Corruption(garbage=1, flipped=1, cut=1, dropped=1, duplicated=1)


class CaptureEncoder:
    """Streaming encoder: consecutive ImuBlocks to one continuous capture.

    The counter runs on across blocks. With ``corrupt``, each block long enough for it
    gets the given :class:`Corruption` (``True``: :data:`DEFAULT_CORRUPTION`); the
    running totals of what a correct parser must report are in :attr:`expected`.

    Parameters
    ----------
    array : ArrayConfig or None
        When given, blocks must have its IMU count.
    layout : Layout or None
        Default: the built-in ``mpu6500-array`` (500 dps, 4 g).
    corrupt : bool or Corruption
    seed : int or None
        Seed of the generator that places corruptions (ignored when ``rng`` is given).
    rng : numpy.random.Generator or None
    """

    def __init__(
        self,
        array: ArrayConfig | None = None,
        *,
        layout: Layout | None = None,
        corrupt: bool | Corruption = False,
        seed: int | None = 0,
        rng: np.random.Generator | None = None,
    ) -> None:
        from imufdi_cli.capture.layouts import mpu6500_array

        self.array = array
        self.layout = layout if layout is not None else mpu6500_array()
        if corrupt is True:
            self.corruption: Corruption | None = DEFAULT_CORRUPTION
        elif corrupt is False:
            self.corruption = None
        else:
            self.corruption = corrupt
        self.rng = rng if rng is not None else np.random.default_rng(seed)
        self.counter = 0
        self.expected: dict[str, int] = {}

    def encode(self, block: ImuBlock) -> bytes:
        """Bytes of the next block of the capture."""
        if self.array is not None and len(block) and block.n_imus != self.array.n_imus:
            raise LayoutError(
                f"block has {block.n_imus} IMUs, the array config {self.array.n_imus}"
            )
        if len(block) == 0:
            return b""
        corruption = self.corruption
        if corruption is not None and 3 * corruption.events + 2 > len(block):
            corruption = None
        encoded = encode_capture(
            block, self.layout, corrupt=corruption, rng=self.rng, start_counter=self.counter
        )
        self.counter += len(block)
        for key, value in encoded.expected_stats(
            has_counter=self.layout.role("counter") is not None
        ).items():
            self.expected[key] = self.expected.get(key, 0) + value
        return encoded.data

    def finish(self) -> bytes:
        """Bytes closing the capture (none for fixed-frame layouts)."""
        return b""
