"""Measurement range of a layout's integer sensor fields (for the clipping flags).

An integer field of ``bits`` bits scaled by ``scale`` SI per LSB cannot report more than
``scale x 2^(bits-1)`` (signed) or ``scale x (2^bits - 1)`` (unsigned): that is the
sensor's full scale as the capture sees it (e.g. an MPU int16 gyro at 16.4 LSB per deg/s:
1998 deg/s). ``ingest`` records it as the ArrayConfig ``range`` when the array config
gives none, so ``detect`` can flag clipped samples (:mod:`imufdi_cli.validity`).
"""

from __future__ import annotations

from imufdi_cli.capture.layout import Layout


def layout_ranges(layout: Layout) -> dict[str, float]:
    """Per sensor type (gyro, accel, mag) the largest magnitude its integer fields can
    carry, SI; types with a float field (no hard limit) are left out."""
    ranges: dict[str, float] = {}
    floats: set[str] = set()
    for fld in layout.record:
        sensor = fld.name.split("_", 1)[0]
        if sensor not in ("gyro", "accel", "mag"):
            continue
        if not fld.is_integer:
            floats.add(sensor)
            continue
        bits = 8 * fld.size
        top = 2 ** (bits - 1) if fld.type.startswith("i") else 2**bits - 1
        ranges[sensor] = max(ranges.get(sensor, 0.0), abs(fld.scale) * top)
    return {k: v for k, v in ranges.items() if k not in floats and v > 0}
