"""The one JSON writer of imufdi's machine-readable summaries and reports.

Every ``--json`` output goes through :func:`dumps`, so that all commands write numbers
the same way: floats rounded to :data:`SIGNIFICANT_DIGITS` significant digits (binary
float noise such as ``0.6519999999999999`` becomes ``0.652``; twelve digits are far more
than any figure imufdi computes is accurate to, and fewer than the 15-17 where the noise
lives), NaN and infinities as ``null`` (JSON has no such numbers), numpy scalars and
arrays as plain numbers and lists, tuples as lists.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

#: significant digits kept in JSON floats
SIGNIFICANT_DIGITS = 12


def round_float(value: float, digits: int = SIGNIFICANT_DIGITS) -> float | None:
    """``value`` rounded to ``digits`` significant digits; None for NaN and infinities.

    Examples
    --------
    >>> round_float(0.6519999999999999)
    0.652
    >>> round_float(1e-300)
    1e-300
    """
    if not math.isfinite(value):
        return None
    return float(f"{value:.{digits}g}")


def clean(value: Any, digits: int = SIGNIFICANT_DIGITS) -> Any:
    """A copy of ``value`` made of plain JSON types with rounded floats (see module doc)."""
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        return round_float(value, digits)
    if isinstance(value, Mapping):
        return {str(k): clean(v, digits) for k, v in value.items()}
    if isinstance(value, (list, tuple, set, frozenset)):
        items = sorted(value) if isinstance(value, (set, frozenset)) else value
        return [clean(v, digits) for v in items]
    tolist = getattr(value, "tolist", None)  # numpy scalars and arrays
    if callable(tolist):
        return clean(tolist(), digits)
    to_dict = getattr(value, "to_dict", None)
    if callable(to_dict):
        return clean(to_dict(), digits)
    raise TypeError(f"cannot write {type(value).__name__} as JSON")


def dumps(value: Any, *, indent: int | None = 2) -> str:
    """``value`` as JSON text ending in a newline (floats rounded, see :func:`clean`)."""
    return json.dumps(clean(value), indent=indent, allow_nan=False) + "\n"
