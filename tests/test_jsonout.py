"""The one JSON writer: float noise rounded away, exact values kept, NaN as null."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from imufdi_cli.jsonout import SIGNIFICANT_DIGITS, clean, dumps, round_float


def test_float_noise_is_rounded_away():
    assert 0.1 * 3 == 0.30000000000000004  # the noise this writer exists for
    assert dumps(0.1 * 3) == "0.3\n"
    assert dumps(0.6519999999999999) == "0.652\n"
    assert json.loads(dumps({"far": 0.6519999999999999}))["far"] == 0.652


@pytest.mark.parametrize("value", [1e-300, 123456789.0123, -2.5e17, 0.0, 1 / 3, math.pi])
def test_rounding_keeps_twelve_significant_digits(value):
    rounded = round_float(value)
    assert rounded is not None
    if value == 0.0:
        assert rounded == 0.0
    else:  # relative error below half a unit in the 12th digit
        assert abs(rounded - value) <= 0.5 * 10 ** (1 - SIGNIFICANT_DIGITS) * abs(value)


def test_integers_booleans_and_strings_are_untouched():
    big = 2**62 + 1  # not representable as a float: must stay exact
    assert json.loads(dumps({"n": big, "ok": True, "s": "0.6519999999999999"})) == {
        "n": big,
        "ok": True,
        "s": "0.6519999999999999",
    }


def test_numpy_values_nan_and_containers():
    data = {
        "a": np.float64(0.1) * 3,
        "b": np.arange(3, dtype=np.int32),
        "c": (np.nan, np.inf, -np.inf),
        "d": {1: np.bool_(True)},
        "e": {"z", "y"},
    }
    assert clean(data) == {
        "a": 0.3,
        "b": [0, 1, 2],
        "c": [None, None, None],
        "d": {"1": True},
        "e": ["y", "z"],
    }


def test_unknown_objects_are_refused():
    with pytest.raises(TypeError, match="object"):
        dumps(object())
