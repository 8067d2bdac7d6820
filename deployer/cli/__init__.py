"""Command line: thin over the library API. Each command returns its exit code.

``base`` holds the click group, the entry point and the shared helpers; importing each command module
registers its commands on the group.
"""

from __future__ import annotations

from . import apply, field, files, plan, profiles, read, simulate  # noqa: F401  (registers the commands)
from .apply import print_report
from .base import cli, main
from .files import validate_file
from .plan import _line_of, print_plan

__all__ = ["_line_of", "cli", "main", "print_plan", "print_report", "validate_file"]
