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
from json.encoder import encode_basestring_ascii
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


def _leaf(value: Any, digits: int) -> str | None:
    """The JSON text of a str, int, float, bool or None of exactly that type (None for
    anything else: :func:`_encode` handles it)."""
    kind = type(value)
    if kind is str:
        return encode_basestring_ascii(value)
    if kind is float:
        if not math.isfinite(value):
            return "null"
        return float.__repr__(float(f"{value:.{digits}g}"))
    if kind is int:
        return int.__repr__(value)
    if value is None:
        return "null"
    if kind is bool:
        return "true" if value else "false"
    return None


def _encode(value: Any, digits: int, indent: str, step: str, parts: list[str]) -> None:
    """Append the JSON text of ``clean(value, digits)`` to ``parts``, laid out as
    ``json.dumps(..., indent=len(step))`` lays it out (``indent``: the current line's
    indentation, after its newline). One pass, without the cleaned copy."""
    if isinstance(value, str):
        parts.append(encode_basestring_ascii(value))
    elif value is None:
        parts.append("null")
    elif value is True:
        parts.append("true")
    elif value is False:
        parts.append("false")
    elif isinstance(value, int):
        parts.append(int.__repr__(value))
    elif isinstance(value, float):
        rounded = round_float(value, digits)
        parts.append("null" if rounded is None else float.__repr__(rounded))
    elif isinstance(value, Mapping):
        items = {str(k): v for k, v in value.items()}  # clean's keys (the last value wins)
        entries = [(encode_basestring_ascii(key) + ": ", item) for key, item in items.items()]
        _encode_container("{", "}", entries, digits, indent, step, parts)
    elif isinstance(value, (list, tuple, set, frozenset)):
        seq = sorted(value) if isinstance(value, (set, frozenset)) else value
        _encode_container("[", "]", [("", item) for item in seq], digits, indent, step, parts)
    else:
        tolist = getattr(value, "tolist", None)  # numpy scalars and arrays
        if callable(tolist):
            _encode(tolist(), digits, indent, step, parts)
            return
        to_dict = getattr(value, "to_dict", None)
        if callable(to_dict):
            _encode(to_dict(), digits, indent, step, parts)
            return
        raise TypeError(f"cannot write {type(value).__name__} as JSON")


def _encode_container(
    opening: str,
    closing: str,
    entries: list[tuple[str, Any]],
    digits: int,
    indent: str,
    step: str,
    parts: list[str],
) -> None:
    """Append an object's or array's JSON text to ``parts``: each entry is the text before
    its value (``"key": `` in an object, nothing in an array) and the value, one per line
    at ``indent + step``, as ``json.dumps(..., indent=len(step))`` lays them out."""
    if not entries:
        parts.append(opening + closing)
        return
    inner = indent + step
    separator = "," + inner
    parts.append(opening + inner)
    for number, (prefix, item) in enumerate(entries):
        if number:
            parts.append(separator)
        text = _leaf(item, digits)
        if text is None:
            parts.append(prefix)
            _encode(item, digits, inner, step, parts)
        else:
            parts.append(prefix + text)
    parts.append(indent + closing)


def dumps(value: Any, *, indent: int | None = 2) -> str:
    """``value`` as JSON text ending in a newline (floats rounded, see :func:`clean`).

    The same text as ``json.dumps(clean(value), indent=indent, allow_nan=False)``: with an
    indent, the standard library encodes in Python (its C encoder only writes one line),
    so :func:`_encode` does it in one pass over ``value``, numbers and strings written
    directly, instead of cleaning a copy and walking that (half the CPU on a report of
    250 episodes, 15 -> 8 ms; tests/test_jsonout.py compares the two byte for byte)."""
    if indent is None:
        return json.dumps(clean(value), allow_nan=False) + "\n"
    parts: list[str] = []
    _encode(value, SIGNIFICANT_DIGITS, "\n", " " * indent, parts)
    return "".join(parts) + "\n"
