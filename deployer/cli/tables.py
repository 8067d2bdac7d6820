"""Tables on the terminal: rich (colours) for a screenful, plain aligned text otherwise.

rich lays a table out cell by cell, about 0.4 ms a row: a 5,000-row plan took 2 s to print.
Plain text has the same columns and spacing (two spaces between columns), costs microseconds
a row, and is what scripts and pipes want anyway. Rich is used only on a terminal and for at
most ``RICH_ROWS`` rows; ``--verbose`` is not needed to see every row.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from ..load.messages import printable

if TYPE_CHECKING:
    from rich.console import Console

RICH_ROWS = 200

Cell = str | tuple[str, str]  # text, or (text, rich style) for a coloured cell


def plain(headers: Sequence[str], rows: Sequence[Sequence[Cell]]) -> str:
    """The table as aligned text, one line per row (header first), trailing spaces removed; what the
    cells hold is escaped (``printable``): a cell is one line, whatever a name or value holds."""
    texts = [list(headers), *([printable(c if isinstance(c, str) else c[0]) for c in row] for row in rows)]
    widths = [max(map(len, column)) for column in zip(*texts, strict=True)]
    line = " " + "  ".join(f"{{:<{w}}}" for w in widths)  # one format string: the padding happens in C
    return "".join(line.format(*r).rstrip() + "\n" for r in texts)


def show(out: Console, headers: Sequence[str], rows: Sequence[Sequence[Cell]]) -> None:
    """Print a table (nothing when there are no rows)."""
    if not rows:
        return
    if out.is_terminal and len(rows) <= RICH_ROWS:
        from rich.table import Table
        from rich.text import Text

        table = Table(*headers, box=None)
        for row in rows:  # Text, not markup: a parameter named 'preset[0].speed' stays as it is
            table.add_row(
                *(Text(printable(c)) if isinstance(c, str) else Text(printable(c[0]), style=c[1]) for c in row)
            )
        out.print(table)
        return
    out.file.write(plain(headers, rows))
    out.file.flush()
