"""Wording of input errors: values echoed cut to a readable length, the closest known name."""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterable

MAX_ECHO = 60  # characters of a value echoed in a message; longer ones are cut with an ellipsis


def clip(text: str, limit: int = MAX_ECHO) -> str:
    """``text`` cut to about ``limit`` characters with an ellipsis (values echoed in errors)."""
    if len(text) <= limit:
        return text
    return f"{text[: limit - 10]}…{text[-8:]} ({len(text)} characters)"


def clipped_repr(value: object, limit: int = MAX_ECHO) -> str:
    return clip(repr(value), limit)


_LONG_WORD = re.compile(r"\S{121,}")  # longer than any path or name a message means to show whole


def clip_message(message: str) -> str:
    """A message with every overlong word (an echoed value) cut, and at most about 1,000 characters."""
    if len(message) <= 120:
        return message
    message = _LONG_WORD.sub(lambda m: clip(m.group()), message)
    if len(message) > 1000:
        message = f"{message[:600]} … {message[-300:]}"
    return message


def label_list(labels: Iterable[str]) -> str:
    """Labels for a message, one after another: quoted when one of them holds a comma or a space at
    an end (``'on, delayed', 'off'``), so the reader sees where each ends."""
    items = list(labels)
    if any("," in t or t != t.strip() or not t for t in items):
        return ", ".join(repr(t) for t in items)
    return ", ".join(items)


def closest(name: str, choices: Iterable[str]) -> str | None:
    hits = difflib.get_close_matches(name, list(choices), n=1, cutoff=0.6)
    return hits[0] if hits else None


# Characters a terminal acts on instead of showing, or that reorder or hide what follows: controls
# (C0, DEL, C1: escape sequences, carriage return, backspace, new lines), format characters (bidi
# overrides and isolates such as U+202E, zero-width ones), line and paragraph separators, and lone
# surrogates (file names that are not UTF-8). Unicode categories Cc, Cf, Zl, Zp and Cs, as of
# Unicode 15 (tests/test_hostile_output.py checks the class against the running Python's tables).
_UNSAFE = re.compile(
    "[\x00-\x1f\x7f-\x9f\xad\u0600-\u0605\u061c\u06dd\u070f\u0890-\u0891\u08e2\u180e"
    "\u200b-\u200f\u2028-\u202e\u2060-\u2064\u2066-\u206f\ud800-\udfff\ufeff\ufff9-\ufffb"
    "\U000110bd\U000110cd\U00013430-\U0001343f\U0001bca0-\U0001bca3\U0001d173-\U0001d17a"
    "\U000e0001\U000e0020-\U000e007f]"
)
_UNSAFE_BUT_NEWLINE = re.compile(_UNSAFE.pattern.replace("\x00-\x1f", "\x00-\x09\x0b-\x1f"))
_NAMED = {"\n": "\\n", "\t": "\\t", "\r": "\\r", "\x1b": "\\e"}


def _escaped(m: re.Match[str]) -> str:
    c = m.group()
    if c in _NAMED:
        return _NAMED[c]
    n = ord(c)
    return f"\\x{n:02x}" if n < 0x100 else f"\\u{n:04x}" if n < 0x10000 else f"\\U{n:08x}"


def printable(text: str, *, newlines: bool = False) -> str:
    """``text`` safe to show on a terminal: every character a terminal would act on (an escape
    sequence, a carriage return, a bidi override) as a visible escape (``\\e``, ``\\r``, ``\\u202e``).

    The one escaping function for text that reaches a terminal (names, labels, values, file names,
    messages that quote them). ``newlines``: keep line breaks (a text of several lines the program
    made itself); else a new line in a name is shown as ``\\n`` too, so no name can start a line.
    """
    return (_UNSAFE_BUT_NEWLINE if newlines else _UNSAFE).sub(_escaped, text)
