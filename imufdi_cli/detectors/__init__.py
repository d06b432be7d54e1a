"""Detectors and their registry.

``DETECTORS`` is a plain dict from the CLI name to where the detector class lives
(``"module:Class"``); every class follows :class:`imufdi_cli.detectors.base.Detector`. A
detector's module (and the scipy parts it needs) is imported only when that detector is
used, so ``imufdi --help``, ``info`` and every stage of a shell pipeline start fast. The CLI
uses ``click.Choice(sorted(DETECTORS))`` so names cannot drift; a test checks that every
entry imports and that the class's ``name`` matches its key.

Adding a detector is one module in this package plus one line here.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

from imufdi_cli.detectors.base import DetectionBlock, Detector, Param, parse_params
from imufdi_cli.errors import DetectorConfigError

DETECTORS: dict[str, str] = {
    "glt": "imufdi_cli.detectors.glt:GltDetector",
    "pca-parity": "imufdi_cli.detectors.pca_parity:PcaParityDetector",
    "noise-glr": "imufdi_cli.detectors.noise_glr:NoiseGlrDetector",
    "woa-mvmd-glt": "imufdi_cli.detectors.woa_mvmd_glt:WoaMvmdGltDetector",
    "bank": "imufdi_cli.detectors.bank:BankDetector",
    "cnn-map": "imufdi_cli.detectors.cnn_map:CnnMapDetector",
    "px4-selector": "imufdi_cli.detectors.px4_selector:Px4SelectorDetector",
    "ap-consistency": "imufdi_cli.detectors.ap_consistency:ApConsistencyDetector",
}


def detector_class(name: str) -> type:
    """The class registered as ``name`` (its module is imported on first use)."""
    try:
        location = DETECTORS[name]
    except KeyError:
        raise DetectorConfigError(
            f"unknown detector {name!r}; valid: {', '.join(sorted(DETECTORS))}"
        ) from None
    module_name, _, class_name = location.partition(":")
    cls: type = getattr(import_module(module_name), class_name)
    return cls


def make_detector(name: str, raw_params: dict[str, Any] | None = None) -> Detector:
    """Instantiate a registered detector with parameters parsed from strings or values."""
    cls = detector_class(name)
    params = parse_params(cls.PARAMS, raw_params or {}, name)  # type: ignore[attr-defined]
    return cls(**params)  # type: ignore[no-any-return]


__all__ = [
    "DETECTORS",
    "DetectionBlock",
    "Detector",
    "Param",
    "detector_class",
    "make_detector",
    "parse_params",
]
