"""User text inside a page, its bidi controls balanced."""

from __future__ import annotations

import html

# bidi embeddings and overrides (closed by U+202C), isolates (closed by U+2069)
_OPENS = {
    **{chr(c): "\u202c" for c in (0x202A, 0x202B, 0x202D, 0x202E)},
    **{chr(c): "\u2069" for c in (0x2066, 0x2067, 0x2068)},
}


def isolated(value: object) -> str:
    """User text as HTML inside ``<bdi>``, its bidi controls balanced (an unmatched closer dropped, what
    is left open closed at its end): a U+202E in a name cannot reorder the page's text after it (as
    the script's txt())."""
    opened: list[str] = []
    out = []
    for c in str(value):
        if c in _OPENS:
            opened.append(_OPENS[c])
        elif c == "\u202c":
            if not opened or opened[-1] != c:
                continue
            opened.pop()
        elif c == "\u2069":
            if c not in opened:
                continue
            del opened[len(opened) - 1 - opened[::-1].index(c) :]
        out.append(c)
    return f"<bdi>{html.escape(''.join(out) + ''.join(reversed(opened)))}</bdi>"
