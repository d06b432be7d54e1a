"""Plain-text rendering of simple tables without rich's renderer (time).

When a command's output is not a terminal (a pipe, a file, ``NO_COLOR``-free or not), rich
renders without styles at width 160 (:func:`imufdi_cli.cli.ui.make_console`). For the
simple tables the commands print (``info``'s description, ``report``'s figures and
episodes, the summaries of ``detect``, ``calibrate``, ``tune``, ``ingest`` and ``demo``),
that rendering is plain padding and box characters; :class:`PlainTable` reproduces it byte
for byte, so a command in a pipe pays neither rich's table layout (about 40 ms of CPU for
``report``'s three tables on a six-row report, 0.4 ms as plain text) nor, where nothing
else it prints needs rich (``info``, ``report``, ``detect``, ``ingest``), rich's import
(about 40 ms; for ``info`` part of the 2x-numpy start-up budget, docs/performance.md).
Any content it cannot render exactly as rich would (non-ASCII or control characters,
backslashes, which rich's markup escaping does not round-trip, leading or trailing blanks
in a cell, a table wider than the console, an empty column) makes
:meth:`PlainTable.render` return None and the caller falls back to rich
(:meth:`imufdi_cli.cli.ui.UI.print_table`); ``tests/cli/test_plain.py`` compares both
renderings.

Every text of a table (title, headers, cells) is plain text, never markup:
:meth:`PlainTable.to_rich` escapes it, so ``[bold]`` or ``[0.88, 0.94]`` in a cell reads
as it is in both renderings.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

#: width of a console that is not a terminal (see ``ui.make_console``)
PLAIN_WIDTH = 160


def plain_safe(text: str) -> bool:
    """True when rich would print ``text`` (as escaped markup) exactly as it is: printable
    ASCII only, no tab or control character, no backslash (``rich.markup.escape``
    round-trips every bracket but not a backslash before a bracket or at the end)."""
    return text.isascii() and text.isprintable() and "\\" not in text


def _cell_safe(text: str) -> bool:
    # blanks at the ends of a cell may be wrapped or trimmed
    return plain_safe(text) and text == text.strip()


class PlainTable:
    """A table in one of the two looks the commands use, rendered as rich would.

    Parameters
    ----------
    columns : sequence of str
        Column headers (shown when ``boxed``).
    boxed : bool
        rich's default look (heavy head box, header row, ``title`` above); otherwise
        ``box=None`` and no header, as the key/value table of ``info``.
    title : str or None
        Title line above the table (rich prints it unpadded on a console that soft-wraps).
    bold_first : bool
        First column in bold (a style: seen on a terminal only).
    justify : sequence of {"left", "right"}
        Per column, header included; columns past its end are left-justified.
    """

    def __init__(
        self,
        columns: Sequence[str],
        boxed: bool = True,
        title: str | None = None,
        bold_first: bool = False,
        justify: Sequence[str] = (),
    ) -> None:
        if len(justify) > len(columns) or any(j not in ("left", "right") for j in justify):
            raise ValueError(f"justify {tuple(justify)!r} for {len(columns)} columns")
        self.columns = tuple(columns)
        self.boxed = boxed
        self.title = title
        self.bold_first = bold_first
        self.justify = tuple(justify) + ("left",) * (len(self.columns) - len(justify))
        self.rows: list[tuple[str, ...]] = []

    def add_row(self, *cells: str) -> None:
        self.rows.append(tuple(cells))

    def to_rich(self) -> Any:
        """The same table as a ``rich.table.Table`` (title, headers and cells escaped)."""
        from rich.markup import escape
        from rich.table import Table

        title = None if self.title is None else escape(self.title)
        if self.boxed:
            table = Table(title=title)
        else:
            table = Table(title=title, show_header=False, box=None)
        for i, (name, justify) in enumerate(zip(self.columns, self.justify, strict=True)):
            style = "bold" if self.bold_first and i == 0 else None
            table.add_column(
                escape(name), style=style, justify="right" if justify == "right" else "left"
            )
        for row in self.rows:
            table.add_row(*(escape(cell) for cell in row))
        return table

    def render(self, width: int = PLAIN_WIDTH) -> str | None:
        """The table as rich prints it on a plain console of ``width`` columns (lines
        ending in ``\\n``), or None when that cannot be guaranteed (see the module)."""
        cells = [*self.rows, self.columns] if self.boxed else list(self.rows)
        if not cells or any(len(r) != len(self.columns) for r in self.rows):
            return None  # rich prints an unboxed table without rows as nothing or a title
        if not all(_cell_safe(c) for row in cells for c in row):
            return None
        if self.title is not None and not _cell_safe(self.title):
            return None
        widths = [max(len(row[i]) for row in cells) for i in range(len(self.columns))]
        if not widths or any(w == 0 for w in widths):
            return None
        total = sum(w + 2 for w in widths) + (len(widths) + 1 if self.boxed else 0)
        if total > width:
            return None

        def line(row: Sequence[str], bar: str = "") -> str:
            inner = bar.join(
                f" {cell.rjust(w) if j == 'right' else cell.ljust(w)} "
                for cell, w, j in zip(row, widths, self.justify, strict=True)
            )
            return f"{bar}{inner}{bar}\n"

        out = [f"{self.title}\n"] if self.title else []
        if not self.boxed:
            out.extend(line(row) for row in self.rows)
            return "".join(out)

        def rule(left: str, fill: str, joint: str, right: str) -> str:
            return left + joint.join(fill * (w + 2) for w in widths) + right + "\n"

        out.append(rule("┏", "━", "┳", "┓"))
        out.append(line(self.columns, "┃"))
        out.append(rule("┡", "━", "╇", "┩"))
        out.extend(line(row, "│") for row in self.rows)
        out.append(rule("└", "─", "┴", "┘"))
        return "".join(out)
