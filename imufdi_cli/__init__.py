"""imufdi: fault detection and isolation for redundant MEMS IMU arrays, on MCAP logs.

The Python API is :mod:`imufdi_cli.api` (docs/python-api.md)::

    import imufdi_cli.api as imufdi

    imufdi.simulate("base.mcap", preset="paper-table4", seed=1)

Its result and configuration types are importable from here too (``from imufdi_cli import
DetectResult``); they are imported on first access, so ``import imufdi_cli`` stays as cheap
as the CLI's start-up needs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from imufdi_cli._version import __version__

if TYPE_CHECKING:
    from imufdi_cli import api
    from imufdi_cli.array import ArrayConfig
    from imufdi_cli.calibrate import CalibrationResult
    from imufdi_cli.campaign import CampaignResult, CampaignSpec
    from imufdi_cli.capture.stats import IngestStats
    from imufdi_cli.detect import DetectResult
    from imufdi_cli.errors import ImufdiError
    from imufdi_cli.faults import InjectResult
    from imufdi_cli.pipeline import SimulateResult
    from imufdi_cli.report import Report

#: name -> module of the lazily re-exported names
_LAZY = {
    "api": "imufdi_cli.api",
    "ArrayConfig": "imufdi_cli.array",
    "CalibrationResult": "imufdi_cli.calibrate",
    "CampaignResult": "imufdi_cli.campaign",
    "CampaignSpec": "imufdi_cli.campaign",
    "DetectResult": "imufdi_cli.detect",
    "ImufdiError": "imufdi_cli.errors",
    "IngestStats": "imufdi_cli.capture.stats",
    "InjectResult": "imufdi_cli.faults",
    "Report": "imufdi_cli.report",
    "SimulateResult": "imufdi_cli.pipeline",
}

__all__ = [
    "ArrayConfig",
    "CalibrationResult",
    "CampaignResult",
    "CampaignSpec",
    "DetectResult",
    "ImufdiError",
    "IngestStats",
    "InjectResult",
    "Report",
    "SimulateResult",
    "__version__",
    "api",
]


def __getattr__(name: str) -> Any:
    """Import a re-exported name on first access (PEP 562)."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'imufdi_cli' has no attribute {name!r}")
    from importlib import import_module

    imported = import_module(module)
    value = imported if name == "api" else getattr(imported, name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})
