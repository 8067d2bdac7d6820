"""Durations as people write them: ``250ms``, ``1s``, ``1.5 s``; a bare number is milliseconds."""

from __future__ import annotations

import re

_DURATION = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*(ms|s)?\s*$")
PATTERN = r"^\s*\d+(\.\d+)?\s*(ms|s)?\s*$"  # the same, for the JSON Schemas
MAX_MS = 600_000  # ten minutes: longer pauses are a typing mistake, not a device's need


def parse_ms(value: object) -> float:
    """Milliseconds of a duration (``250ms``, ``1s``, ``250``). Raises ValueError with what is accepted."""
    if isinstance(value, bool):
        raise ValueError(f"not a duration: {value!r} (e.g. 250ms, 1s; a bare number is milliseconds)")
    if isinstance(value, int | float):
        ms = float(value)
    else:
        m = _DURATION.match(str(value))
        if m is None:
            raise ValueError(f"not a duration: {value!r} (e.g. 250ms, 1s; a bare number is milliseconds)")
        ms = float(m.group(1)) * (1000 if m.group(2) == "s" else 1)
    if not 0 <= ms <= MAX_MS:
        raise ValueError(f"duration {value!r} is out of range (0 to 600s)")
    return ms


def show_ms(ms: float) -> str:
    """'250ms', '1s', '1.5s': the shortest way to write a duration back."""
    if ms >= 1000 and ms % 100 == 0:
        return f"{ms / 1000:g}s"
    return f"{ms:g}ms"
