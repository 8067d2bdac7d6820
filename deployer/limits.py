"""The bounds of every number a caller gives a run: defined once, used by the command line, the Python
API and the Ansible modules alike (``deployer.LIMITS``).

Each bound checks a value and names the argument in its UsageError ("parallel must be from 1 to 1024,
got 0"); a command line option says it as ``--parallel``, a Python keyword as ``parallel``.

This module imports only ``deployer.errors``, so every layer can use it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .errors import UsageError

__all__ = ["BATCH_BY", "LIMITS", "WEEK", "Bound", "Limits"]

WEEK = 7 * 24 * 3600.0  # the longest duration the tool takes: longer is a typo (asyncio's timers overflow)
BATCH_BY = ("profile", "group")  # what one batch of a staged rollout takes a share of (--batch-by, batch_by)


@dataclass(frozen=True)
class Bound:
    """An allowed range: ``low`` to ``high`` (``low`` itself excluded when ``low_open``), whole numbers
    only when ``integer``; ``unit`` ("seconds") is said in messages."""

    low: float
    high: float
    integer: bool = False
    low_open: bool = False
    unit: str = ""

    def text(self) -> str:
        """'from 1 to 1024', 'more than 0 and at most 600 seconds'."""
        unit = f" {self.unit}" if self.unit else ""
        high = "a week" if self.unit == "seconds" and self.high == WEEK else f"{self.high:g}{unit}"
        if self.low_open:
            return f"more than {self.low:g} and at most {high}"
        return f"from {self.low:g}{unit if high == 'a week' else ''} to {high}"

    def problem(self, value: object, what: str) -> str | None:
        """Why ``value`` is not allowed for the argument ``what`` (None: it is)."""
        kind = "a whole number" if self.integer else "a number"
        if isinstance(value, bool) or not isinstance(value, int | float) or (self.integer and isinstance(value, float)):
            shown = repr(value) if len(repr(value)) <= 40 else repr(value)[:39] + "..."
            return f"{what} must be {kind} {self.text()}, got {type(value).__name__} {shown}"
        if not math.isfinite(value) or value > self.high or value < self.low or (self.low_open and value == self.low):
            return (
                f"{what} must be {self.text()}, got {value:g}"
                if isinstance(value, float)
                else f"{what} must be {self.text()}, got {value}"
            )
        return None

    def check(self, value: object, what: str) -> float:
        """``value`` when it is allowed, else a UsageError naming ``what``."""
        why = self.problem(value, what)
        if why is not None:
            raise UsageError(why)
        assert isinstance(value, int | float)
        return value


@dataclass(frozen=True)
class Limits:
    """The bounds of a run's numbers, one for each argument (``deployer.LIMITS.parallel.high`` is 1024).

    ``parallel``: devices at once; ``timeout``: seconds per request attempt; ``retries``: retries after a
    timeout or busy answer; ``soak`` and ``confirm_within``: the safe-change windows; ``health_interval``:
    the time between two rounds of health checks (at least 100 ms: a soak reads the device, it must not
    flood it); ``pause``: between batches; ``lock_timeout``: the wait for a device another run holds;
    ``workers``: worker processes running a fleet's devices (0: none, all in the run's own process).
    """

    parallel: Bound = Bound(1, 1024, integer=True)
    timeout: Bound = Bound(0, 600, low_open=True, unit="seconds")
    retries: Bound = Bound(0, 20, integer=True)
    soak: Bound = Bound(0, WEEK, low_open=True, unit="seconds")
    confirm_within: Bound = Bound(0, WEEK, low_open=True, unit="seconds")
    health_interval: Bound = Bound(0.1, 3600, unit="seconds")
    pause: Bound = Bound(0, WEEK, unit="seconds")
    lock_timeout: Bound = Bound(0, WEEK, unit="seconds")
    workers: Bound = Bound(0, 64, integer=True)


LIMITS = Limits()
