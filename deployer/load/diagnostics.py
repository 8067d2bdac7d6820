"""Errors in user input, reported as ``FILE:LINE:COL: error: message``.

Every loader collects all problems of a file before raising, so users fix them in one pass.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

# Exit codes: a public interface (DESIGN.md, "Exit codes"); scripts rely on them.
EXIT_OK = 0
EXIT_INVALID = 1
EXIT_CHANGES = 2
EXIT_UNREACHABLE = 3
EXIT_FAILED = 4


@dataclass(frozen=True, order=True)
class Diagnostic:
    """One problem in one file. ``line`` and ``col`` are 1-based (0 when unknown)."""

    path: str
    line: int
    col: int
    message: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}:{self.col}: error: {self.message}"


class InputError(Exception):
    """Invalid input (files, options): nothing may be sent to any device. Exit code 1."""

    def __init__(self, diagnostics: Iterable[Diagnostic]) -> None:
        self.diagnostics = sorted(set(diagnostics))
        super().__init__("\n".join(str(d) for d in self.diagnostics))


class UsageError(Exception):
    """A bad option or combination of options (not tied to a file position). Exit code 1."""
