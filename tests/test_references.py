"""tests/references.py: the comparisons of stored float references pass rounding and fail
a real change."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.references import assert_fingerprint_close, assert_tree_close, fingerprint


def test_fingerprints_pass_rounding_and_fail_a_changed_element() -> None:
    rng = np.random.default_rng(5)
    x = rng.normal(size=(400, 6))
    x[3, 2] = np.nan
    want = fingerprint(x)
    assert want[0] == 1.0
    # every element moved by up to 1e-12 of itself, as another kernel's rounding would
    assert_fingerprint_close(
        fingerprint(x * (1 + 1e-12 * rng.uniform(-1, 1, x.shape))), want, 1e-9, "x"
    )
    # one element moved by 2e-9 of the sum |x| fails the sums; two swapped values the weights
    changed = x.copy()
    changed[10, 1] += 2e-9 * want[4]
    with pytest.raises(AssertionError, match="sum"):
        assert_fingerprint_close(fingerprint(changed), want, 1e-9, "x")
    swapped = x.copy()
    swapped[[0, 1], 0] = swapped[[1, 0], 0]
    with pytest.raises(AssertionError, match="weighted sum"):
        assert_fingerprint_close(fingerprint(swapped), want, 1e-9, "x")
    lost = x.copy()
    lost[0, 0] = np.nan
    with pytest.raises(AssertionError, match="NaN count"):
        assert_fingerprint_close(fingerprint(lost), want, 1e-9, "x")


def test_trees_compare_floats_to_their_scale_and_the_rest_exactly() -> None:
    want = {
        "bic": -8343.47038810875,
        "vector": [0.004, -1.5e-17, 2.0],  # an entry near zero carries the vector's rounding
        "count": 3,
        "name": "step",
        "none": None,
        "flags": [True, False],
        "inf": math.inf,
        "nan": math.nan,
    }
    near = {**want, "bic": want["bic"] * (1 + 1e-12), "vector": [0.004, 3e-16, 2.0]}
    assert_tree_close(near, want, 1e-9)
    for key, value in [
        ("bic", want["bic"] * (1 + 1e-8)),
        ("vector", [0.004, 3e-9, 2.0]),
        ("count", 4),
        ("count", 3.0),
        ("name", "drift"),
        ("flags", [True, True]),
        ("inf", 1e308),
        ("nan", 0.0),
        ("none", 0.0),
    ]:
        with pytest.raises(AssertionError):
            assert_tree_close({**want, key: value}, want, 1e-9)
    with pytest.raises(AssertionError, match="keys"):
        assert_tree_close({k: v for k, v in want.items() if k != "name"}, want, 1e-9)
    with pytest.raises(AssertionError, match="length"):
        assert_tree_close({**want, "vector": [0.004, 2.0]}, want, 1e-9)
