"""click choices whose values come from a registry imported only when they are needed
(``--help`` of that command, validation, shell completion), not at start-up."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import click


class LazyChoice(click.Choice):
    """A :class:`click.Choice` whose choices a loader returns on first use."""

    def __init__(self, loader: Callable[[], Sequence[str]], case_sensitive: bool = True):
        self._loader = loader
        self._loaded: Sequence[str] | None = None
        super().__init__([], case_sensitive=case_sensitive)

    @property  # type: ignore[override]
    def choices(self) -> Sequence[str]:
        if self._loaded is None:
            self._loaded = tuple(self._loader())
        return self._loaded

    @choices.setter
    def choices(self, value: Any) -> None:  # click.Choice.__init__ assigns []
        pass


def presets() -> list[str]:
    from imufdi_cli.simulate import PRESETS

    return sorted(PRESETS)


def motions() -> list[str]:
    from imufdi_cli.simulate import MOTIONS

    return sorted(MOTIONS)


def detectors() -> list[str]:
    from imufdi_cli.detectors import DETECTORS

    return sorted(DETECTORS)
