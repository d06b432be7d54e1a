"""One colour per detector for every figure (report plots and campaign plots).

A registered detector has a fixed colour; any other name gets one from :data:`PALETTE` by
the CRC-32 of its name, so it too keeps its colour across panels, figures and runs.
"""

from __future__ import annotations

import zlib

#: fixed colour per registered detector
DETECTOR_COLOURS = {
    "glt": "#1f77b4",
    "woa-mvmd-glt": "#ff7f0e",
    "pca-parity": "#2ca02c",
    "bank": "#9467bd",
    "noise-glr": "#8c564b",
    "cnn-map": "#17becf",
    "px4-selector": "#e377c2",
    "ap-consistency": "#7f7f7f",
}
#: colours for detectors not in DETECTOR_COLOURS (and, in report plots, suspect sensors)
PALETTE = ("#393b79", "#637939", "#8c6d31", "#843c39", "#7b4173", "#3182bd", "#31a354")


def detector_colour(name: str) -> str:
    """The colour of detector ``name`` (a hex string such as ``"#1f77b4"``)."""
    if name in DETECTOR_COLOURS:
        return DETECTOR_COLOURS[name]
    return PALETTE[zlib.crc32(name.encode()) % len(PALETTE)]
