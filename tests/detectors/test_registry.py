"""The detector registry: lazy, complete, and consistent with each class."""

from __future__ import annotations

import subprocess
import sys

import pytest

from imufdi_cli.detectors import DETECTORS, Detector, detector_class, make_detector
from imufdi_cli.errors import DetectorConfigError


@pytest.mark.parametrize("name", sorted(DETECTORS))
def test_every_entry_imports_and_matches_its_name(name: str) -> None:
    cls = detector_class(name)
    assert cls.name == name  # type: ignore[attr-defined]
    assert isinstance(make_detector(name), Detector)


def test_unknown_name_lists_the_valid_ones() -> None:
    with pytest.raises(DetectorConfigError, match=r"unknown detector 'nope'; valid: .*glt"):
        make_detector("nope")


def test_cli_help_imports_no_detector_module_and_no_scipy() -> None:
    probe = (
        "import runpy, sys\n"
        "sys.argv = ['imufdi', '--help']\n"
        "try:\n    runpy.run_module('imufdi_cli', run_name='__main__')\n"
        "except SystemExit:\n    pass\n"
        "heavy = sorted(m for m in sys.modules if m.startswith('scipy')"
        " or (m.startswith('imufdi_cli.detectors.') and m != 'imufdi_cli.detectors.base'))\n"
        "print(heavy)\n"
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert done.stdout.strip().splitlines()[-1] == "[]"
