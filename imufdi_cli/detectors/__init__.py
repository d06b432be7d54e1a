"""Detectors and their registry.

``DETECTORS`` is a plain dict from the CLI name to the detector class; every class follows
:class:`imufdi_cli.detectors.base.Detector`. The CLI uses ``click.Choice(sorted(DETECTORS))``
so names cannot drift.
"""

from __future__ import annotations

from typing import Any

from imufdi_cli.detectors.ap_consistency import ApConsistencyDetector
from imufdi_cli.detectors.bank import BankDetector
from imufdi_cli.detectors.base import DetectionBlock, Detector, Param, parse_params
from imufdi_cli.detectors.cnn_map import CnnMapDetector
from imufdi_cli.detectors.glt import GltDetector
from imufdi_cli.detectors.noise_glr import NoiseGlrDetector
from imufdi_cli.detectors.pca_parity import PcaParityDetector
from imufdi_cli.detectors.px4_selector import Px4SelectorDetector
from imufdi_cli.detectors.woa_mvmd_glt import WoaMvmdGltDetector
from imufdi_cli.errors import DetectorConfigError

DETECTORS: dict[str, type] = {
    GltDetector.name: GltDetector,
    PcaParityDetector.name: PcaParityDetector,
    NoiseGlrDetector.name: NoiseGlrDetector,
    WoaMvmdGltDetector.name: WoaMvmdGltDetector,
    BankDetector.name: BankDetector,
    CnnMapDetector.name: CnnMapDetector,
    Px4SelectorDetector.name: Px4SelectorDetector,
    ApConsistencyDetector.name: ApConsistencyDetector,
}


def make_detector(name: str, raw_params: dict[str, Any] | None = None) -> Detector:
    """Instantiate a registered detector with parameters parsed from strings or values."""
    try:
        cls = DETECTORS[name]
    except KeyError:
        raise DetectorConfigError(
            f"unknown detector {name!r}; valid: {', '.join(sorted(DETECTORS))}"
        ) from None
    params = parse_params(cls.PARAMS, raw_params or {}, name)  # type: ignore[attr-defined]
    return cls(**params)  # type: ignore[no-any-return]


__all__ = ["DETECTORS", "DetectionBlock", "Detector", "Param", "make_detector", "parse_params"]
