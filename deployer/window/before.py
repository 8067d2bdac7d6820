"""Reading the health checks: which of them fail now (a soak's rounds; the plan's ``health`` steps before a safe
change are the executor's, ``execute/executor.py``).

A soak or a confirmation window judges the change by the profile's health checks. A device already in alarm
before the first write would fail its first check at once, and the change would be rolled back and blamed for
the old alarm ("health check failed after 0.0 s"): a safe change's plan reads them before the snapshot, and a
failing one leaves the device unwritten (``failed``), unless the operator allows it
(``ApplyOptions.allow_unhealthy``, ``--allow-unhealthy``); then the checks that were failing before are named and
not held against the change during its window (``DeviceResult.unhealthy_before``).
"""

from __future__ import annotations

from collections.abc import Sequence

from ..execute.session import Session
from ..profile import HealthCheck, Profile

Failing = list[tuple[int, HealthCheck, list[int]]]  # a check's index in the profile, the check, the words read


async def failing_checks(session: Session, prof: Profile, skip: Sequence[int] = (), *, first: bool = False) -> Failing:
    """The health checks of ``prof`` that fail now (``first``: the first one only, the rest not read);
    ``skip``: indices not read. Raises DeviceGone, ExceptionResponse."""
    out: Failing = []
    for i, c in enumerate(prof.health):
        if i in skip:
            continue
        words = await session.read(c.address, c.count, c.function)
        if not c.holds(words):
            out.append((i, c, words))
            if first:
                break
    return out
