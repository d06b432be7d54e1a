"""Plain-text rendering of simple tables without importing rich (start-up time).

When a command's output is not a terminal (a pipe, a file, ``NO_COLOR``-free or not), rich
renders without styles at width 160 (:func:`imufdi_cli.cli.ui.make_console`). For the
simple tables ``imufdi info`` prints, that rendering is plain padding and box characters;
:class:`PlainTable` reproduces it byte for byte so that ``imufdi info LOG | ...`` does not
pay rich's import (about 40 ms of the 2x-numpy start-up budget, docs/performance.md). Any
content it cannot render exactly as rich would (non-ASCII or control characters, markup
brackets, leading or trailing blanks in a cell, a table wider than the console) makes
:meth:`PlainTable.render` return None and the caller falls back to rich;
``tests/cli/test_plain.py`` compares both renderings.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

#: width of a console that is not a terminal (see ``ui.make_console``)
PLAIN_WIDTH = 160


def plain_safe(text: str) -> bool:
    """True when rich would print ``text`` (as escaped markup) exactly as it is: printable
    ASCII only, no tab or control character."""
    return text.isascii() and text.isprintable()


def _cell_safe(text: str) -> bool:
    # unescaped cell text is parsed as markup by rich; blanks at the ends may be wrapped
    return plain_safe(text) and "[" not in text and "]" not in text and text == text.strip()


class PlainTable:
    """A table with the two looks ``imufdi info`` uses.

    Parameters
    ----------
    columns : sequence of str
        Column headers (shown when ``boxed``).
    boxed : bool
        rich's default look (heavy head box, header row, ``title`` above); otherwise
        ``box=None`` and no header, as the key/value table of ``info``.
    title : str or None
        Title line above a boxed table.
    bold_first : bool
        First column in bold (rich rendering only).
    """

    def __init__(
        self,
        columns: Sequence[str],
        boxed: bool = True,
        title: str | None = None,
        bold_first: bool = False,
    ) -> None:
        self.columns = tuple(columns)
        self.boxed = boxed
        self.title = title
        self.bold_first = bold_first
        self.rows: list[tuple[str, ...]] = []

    def add_row(self, *cells: str) -> None:
        self.rows.append(tuple(cells))

    def to_rich(self) -> Any:
        """The same table as a ``rich.table.Table`` (cells escaped)."""
        from rich.markup import escape
        from rich.table import Table

        if self.boxed:
            table = Table(title=self.title)
        else:
            table = Table(show_header=False, box=None)
        for i, name in enumerate(self.columns):
            if self.bold_first and i == 0:
                table.add_column(name, style="bold")
            else:
                table.add_column(name)
        for row in self.rows:
            table.add_row(*(escape(cell) for cell in row))
        return table

    def render(self, width: int = PLAIN_WIDTH) -> str | None:
        """The table as rich prints it on a plain console of ``width`` columns (lines
        ending in ``\\n``), or None when that cannot be guaranteed (see the module)."""
        cells = [*self.rows, tuple(self.columns)] if self.boxed else list(self.rows)
        if not self.rows or any(len(r) != len(self.columns) for r in self.rows):
            return None
        if not all(_cell_safe(c) for row in cells for c in row):
            return None
        if self.title is not None and not _cell_safe(self.title):
            return None
        widths = [max(len(row[i]) for row in cells) for i in range(len(self.columns))]
        if any(w == 0 for w in widths):
            return None
        total = sum(w + 2 for w in widths) + (len(widths) + 1 if self.boxed else 0)
        if total > width:
            return None

        def line(row: Sequence[str], bar: str = "") -> str:
            inner = bar.join(f" {cell.ljust(w)} " for cell, w in zip(row, widths, strict=True))
            return f"{bar}{inner}{bar}\n"

        if not self.boxed:
            return "".join(line(row) for row in self.rows)

        def rule(left: str, fill: str, joint: str, right: str) -> str:
            return left + joint.join(fill * (w + 2) for w in widths) + right + "\n"

        out = [f"{self.title}\n"] if self.title else []
        out.append(rule("┏", "━", "┳", "┓"))
        out.append(line(self.columns, "┃"))
        out.append(rule("┡", "━", "╇", "┩"))
        out.extend(line(row, "│") for row in self.rows)
        out.append(rule("└", "─", "┴", "┘"))
        return "".join(out)
