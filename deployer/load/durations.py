"""Durations as people write them: ``250ms``, ``30s``, ``5m``, ``1h`` (also ``1.5 s``, ``2min``).

One parser for every duration the tool reads (``apply --soak``, ``--pause``, pacing in profiles).
A bare number is in the caller's unit: seconds on the command line, milliseconds in a profile
(where ``wait`` has always been milliseconds).
"""

from __future__ import annotations

import math
import re

from ..limits import WEEK

_UNITS = {"ms": 0.001, "s": 1.0, "sec": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0}
_FORM = re.compile(r"\s*(\d+(?:\.\d*)?|\.\d+)\s*([a-z]*)\s*", re.IGNORECASE)
MAX_SECONDS = WEEK  # longer is a typo (and overflows asyncio's timers on some systems)


def parse_duration(text: str | float | int, *, bare: str = "s") -> float:
    """Seconds in ``text``; ValueError with a message that shows the accepted forms.

    ``bare``: the unit of a number without one ("s" or "ms").
    """
    if isinstance(text, bool):
        raise ValueError(f"{text!r} is not a duration (e.g. 250ms, 30s, 5m, 1h)")
    if isinstance(text, int | float):
        number, unit = float(text), bare
    else:
        m = _FORM.fullmatch(text)
        if m is None:
            raise ValueError(f"'{text}' is not a duration (e.g. 250ms, 30s, 5m, 1h)")
        number, unit = float(m.group(1)), (m.group(2).lower() or bare)
    if unit not in _UNITS:
        raise ValueError(f"'{text}': unknown unit '{unit}' (ms, s, m, h)")
    seconds = number * _UNITS[unit]
    if not math.isfinite(seconds) or seconds > MAX_SECONDS:
        raise ValueError(f"'{text}' is longer than a week")
    return seconds


def format_duration(seconds: float) -> str:
    """The shortest exact text for a duration: 0.25 -> '250ms', 90 -> '90s', 300 -> '5m', 3600 -> '1h'."""
    seconds = float(seconds)
    if seconds < 1 and (seconds * 1000).is_integer():
        return f"{int(seconds * 1000)}ms"
    for unit, size in (("h", 3600), ("m", 60)):
        if seconds >= size and (seconds / size).is_integer():
            return f"{int(seconds / size)}{unit}"
    return f"{seconds:g}s"
