"""Command line: thin over the library API. Each command returns its exit code.

``base`` holds the click group, the entry point and the shared helpers; the group imports a
command's module (``apply``, ``field``, ``files``, ``plan``, ``profiles``, ``read``,
``simulate``) only when that
command runs (``LazyGroup``).
"""

from __future__ import annotations

from .base import cli, main

__all__ = ["cli", "main"]
