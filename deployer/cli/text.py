"""Text on the terminal that nobody can spoof: never parsed as markup, control characters escaped.

Names, labels, values, descriptions and file names come from files, inventories and devices. None
of them is ever rich markup (a recipe named ``[/red]`` is a name, not a closing tag) and none
reaches the terminal raw (an escape sequence in a name would move the cursor and fake a line):
everything printed goes through ``load.messages.printable``.
"""

from __future__ import annotations

from typing import Any

from rich.console import Console
from rich.text import Text

from ..load.messages import printable


class SafeConsole(Console):
    """A console without markup, emoji codes or highlighting, that escapes what it is given as text.

    Lines the program makes itself may span several lines; the user text inside them is escaped
    with ``safe`` (base.py) where it is put in, so a new line in a name is shown as ``\\n``.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(markup=False, emoji=False, highlight=False, **kwargs)

    def print(self, *objects: Any, **kwargs: Any) -> None:
        kwargs.update(markup=False, emoji=False)
        super().print(*(printable(o, newlines=True) if isinstance(o, str) else o for o in objects), **kwargs)


def styled(*parts: str | tuple[str, str]) -> Text:
    """One line from parts: plain text, or ``(text, style)``; every part escaped (``printable``)."""
    return Text.assemble(*(printable(p) if isinstance(p, str) else (printable(p[0]), p[1]) for p in parts))
