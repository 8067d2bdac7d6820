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
