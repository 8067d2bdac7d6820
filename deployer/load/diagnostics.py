"""Errors in user input, reported as ``FILE:LINE:COL: error: message``.

Every loader collects all problems of a file before raising, so users fix them in one pass.
"""

from __future__ import annotations

from dataclasses import dataclass

# the errors and exit codes live in deployer.errors; loaders import them from here too
from ..errors import EXIT_CHANGES, EXIT_FAILED, EXIT_INVALID, EXIT_OK, EXIT_UNREACHABLE, InputError, UsageError

__all__ = ["EXIT_CHANGES", "EXIT_FAILED", "EXIT_INVALID", "EXIT_OK", "EXIT_UNREACHABLE", "Diagnostic", "InputError",
           "UsageError"]


@dataclass(frozen=True, order=True)
class Diagnostic:
    """One problem in one file. ``line`` and ``col`` are 1-based (0 when unknown)."""

    path: str
    line: int
    col: int
    message: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}:{self.col}: error: {self.message}"
