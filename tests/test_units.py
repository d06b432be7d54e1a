"""units: quantities typed by users to SI floats."""

from __future__ import annotations

import math

import pytest

from imufdi_cli.errors import UnitError
from imufdi_cli.units import parse_quantity


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("1/h", 1 / 3600),
        ("0.1/h", 0.1 / 3600),
        ("5/min", 5 / 60),
        ("2/s", 2.0),
        ("1 /h", 1 / 3600),
        ("100Hz", 100.0),
        ("3e-4", 3e-4),
    ],
)
def test_a_count_per_unit_of_time_is_a_frequency(text: str, expected: float) -> None:
    # exact up to the one division of the unit's factor (1 ulp)
    assert math.isclose(parse_quantity(text, "frequency"), expected, rel_tol=1e-15)


@pytest.mark.parametrize("text", ["1/m", "1/deg", "/h", "1//h"])
def test_what_is_not_a_rate_is_refused_with_examples(text: str) -> None:
    with pytest.raises(UnitError, match=r"frequency|malformed|cannot read"):
        parse_quantity(text, "frequency")
