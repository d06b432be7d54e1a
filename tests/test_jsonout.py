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


def _random_value(rng: np.random.Generator, depth: int = 0):
    """A random nested value of every kind :func:`clean` accepts."""
    kind = int(rng.integers(0, 16 if depth < 4 else 10))
    if kind == 0:
        return None
    if kind == 1:
        return bool(rng.random() < 0.5)
    if kind == 2:
        return int(rng.integers(-(2**62), 2**62)) * int(rng.choice([1, 2**40]))
    if kind == 3:  # float noise, tiny, huge, zero, non-finite
        return float(rng.choice([0.1 * 3, 1e-300, -2.5e17, 0.0, -0.0, math.nan, math.inf]))
    if kind == 4:
        return float(rng.standard_normal() * 10.0 ** int(rng.integers(-20, 20)))
    if kind == 5:  # ASCII, escapes, non-ASCII, astral plane
        return "".join(rng.choice(list('ab "\\/\n\t\x01é→😀'), int(rng.integers(0, 6))))
    if kind == 6:
        return np.float64(rng.standard_normal())
    if kind == 7:
        return np.int32(rng.integers(-100, 100))
    if kind == 8:
        return np.bool_(rng.random() < 0.5)
    if kind == 9:
        return rng.standard_normal(int(rng.integers(0, 4))) if rng.random() < 0.5 else np.nan
    size = int(rng.integers(0, 4))
    items = [_random_value(rng, depth + 1) for _ in range(size)]
    if kind in (10, 11):
        return items
    if kind == 12:
        return tuple(items)
    if kind == 13:
        return set(int(v) for v in rng.integers(0, 50, size)) or frozenset()
    if kind == 14:  # keys of several types; 1 and "1" become one key, as in clean
        keys = [rng.choice(["a", "1", "é", ""]), int(rng.integers(0, 3)), True, None, 2.5]
        return {keys[int(rng.integers(0, len(keys)))]: v for v in items}
    return {f"k{i}": v for i, v in enumerate(items)}


def test_dumps_writes_what_json_dumps_of_the_cleaned_value_writes():
    """The one-pass writer against the standard library on the cleaned copy, byte for byte:
    400 random nested values (every type clean accepts, empty containers, keys that clean
    merges, escapes and non-ASCII text, NaN and infinities), and a report-shaped record."""
    rng = np.random.default_rng(3)
    values = [_random_value(rng) for _ in range(400)]
    values.append(
        {
            "results": [{"far": 0.6519999999999999, "roc": np.linspace(0, 1, 7), "n": 3}],
            "notes": [],
            "episodes": [{"sensors": ["imu0.gyro.x"], "fits": {}, "peak": np.inf}],
        }
    )
    kinds = {type(value).__name__ for value in values}
    assert {"dict", "list", "tuple", "set", "str", "float", "int", "ndarray"} <= kinds
    for indent in (2, 0, None):
        for value in values:
            want = json.dumps(clean(value), indent=indent, allow_nan=False) + "\n"
            assert dumps(value, indent=indent) == want, (indent, value)
