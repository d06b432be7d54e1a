"""Detectors and their registry.

``DETECTORS`` is a plain dict from the CLI name to where the detector class lives
(``"module:Class"``); every class follows :class:`imufdi_cli.detectors.base.Detector`. A
detector's module (and the scipy parts it needs) is imported only when that detector is
used, so ``imufdi --help``, ``info`` and every stage of a shell pipeline start fast. The CLI
uses ``click.Choice(sorted(DETECTORS))`` so names cannot drift; a test checks that every
entry imports and that the class's ``name`` matches its key.

Every class inherits :class:`imufdi_cli.detectors.base.DetectorBase`, so every detector is
built the same way: ``make_detector(name, raw)`` is ``detector_class(name).from_params(raw)``.

Adding a detector is one module (or subpackage) in this package plus one line here
(docs/writing-a-detector.md).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Mapping, Sequence
from importlib import import_module
from typing import Any

from imufdi_cli.detectors.base import (
    DetectionBlock,
    Detector,
    DetectorBase,
    Param,
    ParameterRenamedWarning,
    parse_params,
)
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
    "health": "imufdi_cli.detectors.health:HealthDetector",
}


def detector_class(name: str) -> type[DetectorBase]:
    """The class registered as ``name`` (its module is imported on first use)."""
    try:
        location = DETECTORS[name]
    except KeyError:
        raise DetectorConfigError(
            f"unknown detector {name!r}; valid: {', '.join(sorted(DETECTORS))}"
        ) from None
    module_name, _, class_name = location.partition(":")
    cls: type[DetectorBase] = getattr(import_module(module_name), class_name)
    return cls


def check_selection(names: Sequence[str]) -> None:
    """Raise DetectorConfigError unless ``names`` selects at least one registered detector,
    each once (the message names the valid ones)."""
    valid = ", ".join(sorted(DETECTORS))
    if not names:
        raise DetectorConfigError(f"no detector selected; use -d NAME (valid: {valid})")
    seen: set[str] = set()
    for name in names:
        if name not in DETECTORS:
            raise DetectorConfigError(f"unknown detector {name!r}; valid: {valid}")
        if name in seen:
            raise DetectorConfigError(f"detector {name!r} selected twice")
        seen.add(name)


def make_detector(name: str, raw_params: Mapping[str, Any] | None = None) -> Detector:
    """The registered detector ``name`` built from raw parameters (strings or values).

    Raises
    ------
    DetectorConfigError
        Unknown detector or parameter, or a bad value (see ``DetectorBase.from_params``).
    """
    detector: Detector = detector_class(name).from_params(raw_params)  # type: ignore[assignment]
    return detector


def make_detectors(
    specs: Iterable[tuple[str, Mapping[str, Any]]],
) -> tuple[list[Detector], list[str]]:
    """Build several detectors; renamed-parameter notes are returned, not emitted.

    Returns
    -------
    detectors : list of Detector
        In the order of ``specs`` (name, raw parameters).
    notes : list of str
        One line per :class:`ParameterRenamedWarning` (for a command's ``warning:`` lines).
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ParameterRenamedWarning)
        detectors = [make_detector(name, params) for name, params in specs]
    notes = []
    for item in caught:
        if issubclass(item.category, ParameterRenamedWarning):
            notes.append(str(item.message))
        else:  # not ours: pass it on unchanged
            warnings.warn_explicit(item.message, item.category, item.filename, item.lineno)
    return detectors, notes


__all__ = [
    "DETECTORS",
    "DetectionBlock",
    "Detector",
    "DetectorBase",
    "Param",
    "ParameterRenamedWarning",
    "check_selection",
    "detector_class",
    "make_detector",
    "make_detectors",
    "parse_params",
]
