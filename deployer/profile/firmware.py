"""Firmware-aware profiles: which firmware revisions a profile (or one of its parameters) applies to.

A revision is compared as dotted numbers (``2.1.0`` < ``2.10``); a range is one or more comparisons
separated by commas (``>=1.2, <2``); a bare revision means that one or later (``2.1``: ``>=2.1``), as
wb-mqtt-serial's ``fw`` does.
"""

from __future__ import annotations

import operator
import re
from collections.abc import Callable
from dataclasses import dataclass

_TERM = re.compile(r"^\s*(>=|<=|==|=|>|<)?\s*v?(\d+(?:\.\d+)*)\s*$")
_OPS: dict[str, Callable[[tuple[int, ...], tuple[int, ...]], bool]] = {
    ">=": operator.ge,
    "<=": operator.le,
    "==": operator.eq,
    "=": operator.eq,
    ">": operator.gt,
    "<": operator.lt,
}


def numbers(revision: str) -> tuple[int, ...] | None:
    """'V2.1.0', '2.10 build 7' -> (2, 1, 0), (2, 10, 7); None when the text holds no number."""
    found = re.findall(r"\d+", revision)
    return tuple(int(n) for n in found[:8]) if found else None


def _padded(a: tuple[int, ...], b: tuple[int, ...]) -> tuple[tuple[int, ...], tuple[int, ...]]:
    n = max(len(a), len(b))
    return a + (0,) * (n - len(a)), b + (0,) * (n - len(b))


def check_range(text: str) -> str | None:
    """Why ``text`` is not a revision range, or None."""
    for term in str(text).split(","):
        if not _TERM.match(term):
            return f"'{term.strip()}' is not a revision or a comparison with one (e.g. '2.1', '>=1.2, <2', '==3.0.4')"
    return None


def matches(text: str, revision: str) -> bool:
    """Whether ``revision`` (as the device said it) lies in the range ``text``."""
    have = numbers(revision)
    if have is None:
        return False
    for term in str(text).split(","):
        m = _TERM.match(term)
        assert m is not None, term  # checked when the profile loaded
        op = m[1] or ">="
        a, b = _padded(have, tuple(int(x) for x in m[2].split(".")))
        if not _OPS[op](a, b):
            return False
    return True


@dataclass(frozen=True)
class FirmwareSource:
    """Where the device says its firmware revision: a Function 43 object, or registers (a number or text)."""

    object_id: int | None = 2  # Function 43 / 14 object (2: MajorMinorRevision)
    address: int | None = None
    count: int = 1
    register_type: str = "holding"
    text: bool = False  # the registers hold text (two characters each), else one unsigned number
    applies: str | None = None  # the revisions the whole profile applies to

    def describe(self) -> str:
        if self.address is None:
            return "Function 43 revision" if self.object_id == 2 else f"Function 43 object 0x{self.object_id:02X}"
        return f"{'input register' if self.register_type == 'input' else 'register'} 0x{self.address:04X}"

    def revision_of(self, registers: list[int]) -> str:
        if self.text:
            raw = b"".join(w.to_bytes(2, "big") for w in registers)
            return raw.decode("latin-1").strip(" \x00")
        value = 0
        for w in registers:
            value = value << 16 | w
        return str(value)
