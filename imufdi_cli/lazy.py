"""Re-exports imported on first use (PEP 562): a package's public names, each imported
from its submodule when first read, so that importing the package loads none of them
(start-up: a command pays only for the submodules it uses, docs/performance.md)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from importlib import import_module
from typing import Any


def lazy_exports(
    package: str, where: Mapping[str, str], namespace: dict[str, Any]
) -> Callable[[str], Any]:
    """A module ``__getattr__`` for ``package``: the name's value from the submodule
    ``where[name]``, stored in ``namespace`` (the package's ``globals()``) so that the next
    access is an ordinary lookup; ``AttributeError`` for a name ``where`` does not hold.

    Parameters
    ----------
    package : str
        The package's ``__name__`` (for the error message).
    where : mapping
        Public name -> the dotted name of the submodule defining it.
    namespace : dict
        The package's ``globals()``.
    """

    def __getattr__(name: str) -> Any:
        try:
            module = where[name]
        except KeyError:
            raise AttributeError(f"module {package!r} has no attribute {name!r}") from None
        value = getattr(import_module(module), name)
        namespace[name] = value
        return value

    return __getattr__


__all__ = ["lazy_exports"]
