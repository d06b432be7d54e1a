"""What a capture parse kept, dropped and repaired."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any


@dataclass
class IngestStats:
    """Counts of a capture parse; complete when the block iterator is exhausted.

    Attributes
    ----------
    bytes_total : int
        Bytes read from the capture.
    bytes_dropped : int
        Bytes not part of a kept frame (garbage, bad-checksum and truncated frames,
        duplicates). For binary layouts ``bytes_total - bytes_dropped`` is
        ``frames_ok`` times the frame size.
    frames_ok : int
        Frames (CSV: rows) kept and returned as samples.
    frames_bad_checksum : int
        Complete frames whose checksum did not match (dropped).
    frames_truncated : int
        Frames cut short, by the next frame's sync or by the end of the capture (dropped).
    frames_lost : int
        Counter values missing between consecutive kept frames: frames never received or
        dropped above. 0 when the layout has no counter.
    duplicates : int
        Frames repeating the previous frame's counter and timestamp (dropped).
    counter_wraps, timestamp_wraps : int
        Wrap-arounds of the counter and timestamp fields (unwrapped).
    counter_jumps, timestamp_jumps : int
        Steps backwards (more than half the field range forward): resets or reordering;
        not counted as lost frames.
    rows_malformed : int
        CSV rows with a wrong number of fields or values that are not numbers (dropped).
    n_imus : int
        IMUs per frame (0 until the first frame is kept).
    """

    bytes_total: int = 0
    bytes_dropped: int = 0
    frames_ok: int = 0
    frames_bad_checksum: int = 0
    frames_truncated: int = 0
    frames_lost: int = 0
    duplicates: int = 0
    counter_wraps: int = 0
    timestamp_wraps: int = 0
    counter_jumps: int = 0
    timestamp_jumps: int = 0
    rows_malformed: int = 0
    n_imus: int = 0
    complete: bool = False

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def as_rows(self) -> list[tuple[str, int]]:
        """(name, count) pairs for a table, without the ``complete`` flag."""
        return [(k.replace("_", " "), v) for k, v in asdict(self).items() if k != "complete"]
