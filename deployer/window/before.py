"""Health before the change: a safe change does not write a device that is already failing a health check.

A soak or a confirmation window judges the change by the profile's health checks. A device already in
alarm before the first write would fail its first check at once, and the change would be rolled back and
blamed for the old alarm ("health check failed after 0.0 s"). So the checks are read with the other
reads, before the snapshot: a failing one leaves the device unwritten (``failed``), unless the operator
allows it (``ApplyOptions.allow_unhealthy``, ``--allow-unhealthy``); then the checks that were failing
before are named and not held against the change during its window (``DeviceResult.unhealthy_before``).
"""

from __future__ import annotations

from collections.abc import Sequence

from ..errors import DeviceGone, ExceptionResponse
from ..execute.session import ApplyOptions, Session
from ..profile import HealthCheck, Profile
from ..report import DeviceResult

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


async def unhealthy_before(session: Session, prof: Profile, opts: ApplyOptions, res: DeviceResult) -> str | None:
    """Why a safe change must not write this device (its health checks fail already); None to go on.

    Only for a soak or a confirmation (``opts.soak``, ``opts.confirm_within``) and a profile with health
    checks; the reads are in ``res.requests`` like every other."""
    if (opts.soak is None and opts.confirm_within is None) or not prof.health:
        return None
    try:
        failing = await failing_checks(session, prof)
    except (DeviceGone, ExceptionResponse) as e:
        return f"the health checks could not be read before the change: {e}"
    if not failing:
        return None
    said = "; ".join(c.failure(words) for _, c, words in failing)
    if not opts.allow_unhealthy:
        return (f"health check already failing before the change: {said} (the change is not to blame for it; "
                "to write it anyway: --allow-unhealthy)")
    res.unhealthy_before = tuple(i for i, _, _ in failing)
    res.notices.append(f"health check already failing before the change, written anyway (--allow-unhealthy): "
                       f"{said}; its window does not hold that check against the change")
    return None
