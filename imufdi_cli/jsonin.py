"""JSON read from files: bounded nesting, and a small schema check with one-line errors.

Everything imufdi decodes from a log or a user's file (metadata records, episode details,
JSON messages, channel metadata, tuned parameters) goes through :func:`loads`, which
refuses nesting deeper than :data:`MAX_DEPTH` *before* the recursive decoder runs: a
document nested 100,000 levels deep is one clear error, never a ``RecursionError`` in
the decoder or in whatever walks the result later (``info --json`` writing it back, a
schema check).

:func:`check` validates a decoded document against a schema built from a few node types
(:class:`Int`, :class:`Number`, :class:`Str`, :class:`Bool`, :class:`Null`,
:class:`Anything`, :class:`OneOf`, :class:`ListOf`, :class:`MapOf`, :class:`Obj`) and
raises the caller's error class naming the document, the path of the first bad value
(``faults[0].at_s``), what was expected and what was found.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imufdi_cli.errors import ImufdiError, InputDataError

#: Deepest nesting of arrays and objects accepted. imufdi's own records nest at most
#: 5 levels (an array record's rotation matrices, a detect record's validity runs).
MAX_DEPTH = 64

#: A JSON string (no escapes or escaped characters): removed before brackets are counted.
_STRING = re.compile(r'"(?:[^"\\]|\\.)*"', re.DOTALL)
_OPEN = np.frombuffer(b"[{", np.uint8)
_CLOSE = np.frombuffer(b"]}", np.uint8)


def nesting_depth(text: str | bytes) -> int:
    """Deepest nesting of ``[``/``{`` in a JSON text, brackets inside strings left out;
    linear time, no recursion. A text with at most :data:`MAX_DEPTH` brackets in all
    gives their count (an upper bound: it cannot nest deeper). Malformed text gives some
    depth; the decoder then rejects it."""
    if isinstance(text, (bytes, bytearray, memoryview)):
        text = bytes(text).decode("utf-8", "replace")
    opened = text.count("[") + text.count("{")
    if opened <= MAX_DEPTH:
        return opened  # cannot be deeper than the brackets it has
    if '"' in text:
        text = _STRING.sub('""', text)
    codes = np.frombuffer(text.encode("utf-8", "replace"), np.uint8)
    step = np.isin(codes, _OPEN).astype(np.int32) - np.isin(codes, _CLOSE).astype(np.int32)
    return int(np.cumsum(step).max(initial=0))


def loads(text: str | bytes, where: str, error: type[ImufdiError] = InputDataError) -> Any:
    """Decode JSON from a file or log.

    Parameters
    ----------
    text : str or bytes
        The JSON text (bytes are decoded as UTF-8).
    where : str
        What it is, for the message (``imufdi.faults metadata``).
    error : ImufdiError subclass
        Raised for invalid JSON, invalid UTF-8, or nesting deeper than :data:`MAX_DEPTH`.
    """
    try:
        depth = nesting_depth(text)
        if depth > MAX_DEPTH:
            raise error(
                f"{where}: JSON nested {depth} levels deep; at most {MAX_DEPTH} are accepted"
            )
        return json.loads(text)
    except (ValueError, TypeError) as err:  # JSONDecodeError and UnicodeDecodeError
        raise error(f"{where}: not valid JSON ({err})") from err
    except RecursionError as err:  # pragma: no cover - the depth check comes first
        raise error(f"{where}: JSON nested too deeply") from err


# --- schema ------------------------------------------------------------------------------


def kind(value: Any) -> str:
    """The JSON type of a decoded value, for messages (``a string``, ``null``...)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int):
        return f"the integer {value}"
    if isinstance(value, float):
        return f"the number {value!r}"
    if isinstance(value, str):
        shown = value if len(value) <= 40 else value[:37] + "..."
        return f"the string {shown!r}"
    if isinstance(value, list):
        return f"a list of {len(value)}"
    if isinstance(value, dict):
        return "an object"
    return type(value).__name__


class Node:
    """A schema node: :meth:`problem` says what is wrong with a value (None: nothing)."""

    expected = "a value"

    def problem(self, value: Any, path: str) -> tuple[str, str] | None:
        """(path, message) of the first problem in ``value``, or None."""
        return (
            None if self.accepts(value) else (path, f"expected {self.expected}, got {kind(value)}")
        )

    def accepts(self, value: Any) -> bool:  # pragma: no cover - overridden
        return True


class Anything(Node):
    expected = "any value"


class Int(Node):
    """An integer (not a boolean), optionally within ``[low, high]``."""

    def __init__(self, low: int | None = None, high: int | None = None) -> None:
        self.low, self.high = low, high
        bounds = [
            f">= {low}" if low is not None else "",
            f"<= {high}" if high is not None else "",
        ]
        limits = " and ".join(b for b in bounds if b)
        self.expected = "an integer" + (f" {limits}" if limits else "")

    def accepts(self, value: Any) -> bool:
        return (
            isinstance(value, int)
            and not isinstance(value, bool)
            and (self.low is None or value >= self.low)
            and (self.high is None or value <= self.high)
        )


class Number(Node):
    """A finite number (integer or float, not a boolean), optionally of magnitude at most
    ``limit`` (times and sizes a computation can hold: 1e300 seconds is no time)."""

    def __init__(self, limit: float | None = None) -> None:
        self.limit = limit
        self.expected = "a finite number" + (f" of magnitude <= {limit:g}" if limit else "")

    def accepts(self, value: Any) -> bool:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        try:
            number = float(value)
        except OverflowError:  # an integer beyond any float
            return False
        return math.isfinite(number) and (self.limit is None or abs(number) <= self.limit)


#: an integer nanosecond time or count numpy's int64 holds
def Int64() -> Int:
    node = Int(low=-(1 << 63), high=(1 << 63) - 1)
    node.expected = "a 64-bit integer"
    return node


class Str(Node):
    expected = "a string"

    def accepts(self, value: Any) -> bool:
        return isinstance(value, str)


class Bool(Node):
    expected = "true or false"

    def accepts(self, value: Any) -> bool:
        return isinstance(value, bool)


class Null(Node):
    expected = "null"

    def accepts(self, value: Any) -> bool:
        return value is None


class OneOf(Node):
    """Any of several nodes (the first that accepts the value)."""

    def __init__(self, *options: Node) -> None:
        self.options = options
        self.expected = " or ".join(o.expected for o in options)

    def problem(self, value: Any, path: str) -> tuple[str, str] | None:
        found = [o.problem(value, path) for o in self.options]
        if any(f is None for f in found):
            return None
        # a container of the right type with a bad item: say which item
        deeper = [f for f in found if f is not None and f[0] != path]
        return deeper[0] if deeper else (path, f"expected {self.expected}, got {kind(value)}")


def Optional(node: Node) -> Node:
    """``node`` or null."""
    return OneOf(node, Null())


@dataclass
class ListOf(Node):
    """A list of ``item``; ``length``: exactly that many."""

    item: Node
    length: int | None = None

    def __post_init__(self) -> None:
        self.expected = "a list" if self.length is None else f"a list of {self.length}"

    def problem(self, value: Any, path: str) -> tuple[str, str] | None:
        if not isinstance(value, list) or (self.length is not None and len(value) != self.length):
            return path, f"expected {self.expected}, got {kind(value)}"
        for i, item in enumerate(value):
            found = self.item.problem(item, f"{path}[{i}]")
            if found is not None:
                return found
        return None


@dataclass
class MapOf(Node):
    """An object whose every value is ``value`` (keys are free)."""

    value: Node
    expected: str = "an object"

    def problem(self, value: Any, path: str) -> tuple[str, str] | None:
        if not isinstance(value, dict):
            return path, f"expected {self.expected}, got {kind(value)}"
        for key, item in value.items():
            found = self.value.problem(item, f"{path}.{key}" if path else str(key))
            if found is not None:
                return found
        return None


@dataclass
class Obj(Node):
    """An object with ``required`` and ``optional`` keys; other keys are accepted (newer
    writers may add some) unless ``closed``."""

    required: Mapping[str, Node] = field(default_factory=dict)
    optional: Mapping[str, Node] = field(default_factory=dict)
    closed: bool = False
    expected: str = "an object"

    def problem(self, value: Any, path: str) -> tuple[str, str] | None:
        if not isinstance(value, dict):
            return path, f"expected {self.expected}, got {kind(value)}"
        for key in self.required:
            if key not in value:
                return path, f"missing key {key!r}"
        for key, item in value.items():
            node = self.required.get(key) or self.optional.get(key)
            where = f"{path}.{key}" if path else key
            if node is None:
                if self.closed:
                    valid = ", ".join(sorted({*self.required, *self.optional}))
                    return where, f"unknown key; valid: {valid}"
                continue
            found = node.problem(item, where)
            if found is not None:
                return found
        return None


def check(value: Any, schema: Node, where: str, error: type[ImufdiError] = InputDataError) -> Any:
    """``value`` when it matches ``schema``; else raise ``error`` naming ``where``, the
    path of the first bad value and what was expected there."""
    found = schema.problem(value, "")
    if found is not None:
        path, message = found
        raise error(f"{where}: {path + ': ' if path else ''}{message}")
    return value
