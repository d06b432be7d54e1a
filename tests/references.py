"""Comparing computed floats with references stored in the repository, on any machine.

The last bits of a floating-point result depend on the machine as much as on the code:
numpy dispatches its loops (sums, transcendental functions) to the widest SIMD level the
CPU has (AVX-512, AVX2, SSE), OpenBLAS picks a matrix kernel per CPU model (SkylakeX,
Haswell, Sandybridge, ...), a BLAS thread count splits sums differently, and numpy and
scipy releases change algorithms. A stored float reference is therefore never compared bit
for bit: each test compares within a tolerance that it states and justifies next to the
comparison, wide enough for those differences and tight enough that a real change of the
computation fails it. Exact comparisons stay for bytes (MCAP framing, the writer's output
for fixed inputs) and for integers (counts, indices, alarm decisions: the decisions of the
stored cases lie far from their thresholds, and CI checks them on a second CPU
configuration, ``.ci/run``).

A long array is stored as a :func:`fingerprint` instead of its values (a few numbers in
place of kilobytes of noise-like digits); :func:`assert_fingerprint_close` compares two
with the bounds that a change of at most ``rtol`` of the array's scale in every element
implies.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def fingerprint(values: Any) -> list[float]:
    """(NaN count, sum, sum of squares, sum weighted by ``sin(0.37 k + 1)``, sum |x|) of the
    values in C order, NaN taken as 0 (and counted)."""
    raw = np.asarray(values, dtype=np.float64).ravel()
    x = np.where(np.isnan(raw), 0.0, raw)
    weights = np.sin(0.37 * np.arange(x.size) + 1.0)
    sums = [x.sum(), (x * x).sum(), (x * weights).sum(), np.abs(x).sum()]
    return [float(np.isnan(raw).sum()), *(float(v) for v in sums)]


def assert_fingerprint_close(got: list[float], want: list[float], rtol: float, where: str) -> None:
    """``got`` and ``want`` (:func:`fingerprint`) are those of arrays within ``rtol`` of each
    other: NaN count equal; the sum and the weighted sum within ``rtol`` times sum |x| (the
    most that moving each element by ``rtol |x|`` can change them), the sum of squares within
    ``2 rtol`` of itself, sum |x| within ``rtol``. A single element changed by more than
    ``rtol`` sum |x| shows in the sums; the sine weights catch values moved between
    positions."""
    assert len(got) == len(want) == 5, where
    assert got[0] == want[0], f"{where}: NaN count {got[0]:g} != {want[0]:g}"
    scale = max(want[4], math.ulp(0.0))
    bounds = (rtol * scale, 2.0 * rtol * abs(want[2]), rtol * scale, rtol * scale)
    for name, g, w, bound in zip(
        ("sum", "sum of squares", "weighted sum", "sum |x|"), got[1:], want[1:], bounds
    ):
        assert abs(g - w) <= bound, (
            f"{where}: {name} {g!r} != {w!r} (|diff| {abs(g - w):.3g} > {bound:.3g})"
        )


def _same_float(got: float, want: float, bound: float) -> bool:
    if math.isnan(want) or math.isinf(want):
        return (math.isnan(got) and math.isnan(want)) or got == want
    return abs(got - want) <= bound


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def assert_tree_close(got: Any, want: Any, rtol: float, where: str = "") -> None:
    """Two JSON-like trees (dicts, lists, numbers, strings, booleans, None) are equal but for
    float rounding: the same keys, lengths, types and non-float values; a float within
    ``rtol`` of its own magnitude, or, in a list of numbers (a vector), within ``rtol`` of
    the vector's largest magnitude (an entry near zero in a vector of larger ones carries
    the rounding of those: a relative bound would not hold for it). NaN matches NaN, an
    infinity itself; an integer matches only itself."""
    if isinstance(want, dict):
        assert isinstance(got, dict), f"{where}: {type(got).__name__}, not a mapping"
        assert sorted(got) == sorted(want), f"{where}: keys {sorted(got)} != {sorted(want)}"
        for key in want:
            assert_tree_close(got[key], want[key], rtol, f"{where}.{key}")
        return
    if isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want), f"{where}: length differs"
        if want and all(_is_number(v) for v in want) and any(isinstance(v, float) for v in want):
            bound = rtol * max((abs(v) for v in want if math.isfinite(v)), default=0.0)
            for i, (g, w) in enumerate(zip(got, want)):
                _assert_number(g, w, bound, f"{where}[{i}]")
            return
        for i, (g, w) in enumerate(zip(got, want)):
            assert_tree_close(g, w, rtol, f"{where}[{i}]")
        return
    if isinstance(want, float):
        _assert_number(got, want, rtol * abs(want) if math.isfinite(want) else 0.0, where)
        return
    assert type(got) is type(want) and got == want, f"{where}: {got!r} != {want!r}"


def _assert_number(got: Any, want: Any, bound: float, where: str) -> None:
    if isinstance(want, float):
        assert _is_number(got), f"{where}: {got!r} is not a number"
        ok = _same_float(float(got), want, bound)
        assert ok, (
            f"{where}: {got!r} != {want!r} (|diff| {abs(float(got) - want):.3g} > {bound:.3g})"
        )
    else:
        assert type(got) is type(want) and got == want, f"{where}: {got!r} != {want!r}"
