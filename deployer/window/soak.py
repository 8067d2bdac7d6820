"""Keeping only changes that proved themselves: the soak.

After a verified write the profile's ``health`` checks are read every ``health_interval`` for
``soak`` seconds; the first failed check rolls that device back from its snapshot at once (a
verified rollback, without the profile's ``commit``), and the device ends ``rolled-back``. The
``commit`` steps (a store to non-volatile memory) of the devices that passed are sent only
afterwards (``finish.send_commit``), or only once the run is confirmed (``confirm``).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable, Sequence
from typing import Any

from ..errors import DeviceGone, ExceptionResponse, Unreachable, UsageError
from ..execute.connect import opened
from ..execute.session import ApplyOptions, Session
from ..load.durations import format_duration
from ..profile import HealthCheck, Profile
from ..state import durable, journal
from ..transport import clients as tp
from .before import failing_checks
from .finish import roll_back
from .held import Written, needs_soak
from .held import record as _journal


def check_soak_profiles(profiles: Sequence[Profile]) -> None:
    """``--soak`` watches the profile's health checks: a profile without any is refused up front."""
    bare = sorted({p.id for p in profiles if not p.health})
    if bare:
        raise UsageError(
            f"--soak watches the profile's health checks, and profile {', '.join(bare)} declares none "
            "(health: in the profile, e.g. - {register: 48, equals: 0, description: drive fault code "
            "is zero}); use --confirm-within to hold the commit without checks"
        )


async def read_health(
    session: Session, prof: Profile, skip: Sequence[int] = ()
) -> tuple[HealthCheck, list[int]] | None:
    """The first failed check and the words read, or None when the device is healthy. ``skip``: the indices of
    checks not read (those failing before a change written anyway: ``DeviceResult.unhealthy_before``)."""
    failing = await failing_checks(session, prof, skip, first=True)
    return (failing[0][1], failing[0][2]) if failing else None


async def soak(
    devices: Sequence[Written],
    options: ApplyOptions,
    *,
    on_failed: Callable[[Written], None] | None = None,
    report: str | None = None,
    until: asyncio.Event | None = None,
    during: str | None = None,
) -> list[Written]:
    """Watch ``devices`` together for ``options.soak`` seconds; roll back each one whose health fails.

    ``until``: the watch also ends (the devices still healthy pass) once this is set: ``confirm`` watches
    the health while it waits for the confirmation; ``during`` names that wait in messages ("the
    confirmation wait"; default "the 5m soak").

    ``report``: a report of the run so far (its snapshots), named in the journal's ``soak-started`` line so
    that ``deployer status`` can point a rollback at it should the process die during the soak.

    Returns the devices that passed. Health reads are counted in each device's notices, not logged
    request by request (a 5-minute soak at 1 s would add 300 reads per device to the report).
    """
    assert options.soak is not None
    todo = [w for w in devices if needs_soak(w.result)]
    if not todo:
        return []
    run = options.run_id
    await durable.settled()  # as before a confirmation wait: the snapshots fsync'ed, their log closed
    start = time.monotonic()
    deadline = start + options.soak
    # a health watch inside the confirmation window (``until``) is part of that window: the journal says
    # "confirm", not "soak" (status would say the run died during a soak)
    journaled = run if until is None else None
    for w in todo if until is None else ():  # a run refused meanwhile says whose soak holds it, until when
        for h in w.locks:  # (a confirmation wait that watches the health says so itself)
            h.in_window("soak", time.time() + options.soak)
    if journaled is not None:
        _journal(
            options,
            {
                "event": "soak-started",
                "run": run,
                "time": journal._now(),
                "seconds": options.soak,
                "interval": options.health_interval,
                "devices": [w.name for w in todo],
                "report": report,
                **journal.deadline(options.soak),
            },
            *(w.result for w in todo),
        )
    passed: list[Written] = []
    failed: list[Written] = []

    # one connection per bus, one request at a time on it: a gateway allows few connections, and the
    # devices behind it share one line anyway
    lines: dict[str, tuple[tp.Transport, asyncio.Lock, asyncio.Future[str | None]]] = {}

    async def connect(transport: tp.Transport) -> str | None:
        try:
            await transport.connect()
        except Unreachable as e:
            return f"the device could not be reached: {e}"
        return None

    async def watch(w: Written) -> None:
        if w.url.bus not in lines:
            transport = opened(w.url, w.recipe.profile)  # paced as the profile says, as every command is
            lines[w.url.bus] = (transport, asyncio.Lock(), asyncio.ensure_future(connect(transport)))
        transport, one_at_a_time, connected = lines[w.url.bus]
        records: list[Any] = []
        session = Session(transport, w.unit, retries=w.url.retries, backoff=options.backoff, records=records)
        reads = rounds = 0
        why: str | None = await asyncio.shield(connected)
        while why is None:
            rounds += 1
            try:
                async with one_at_a_time:
                    bad = await read_health(session, w.recipe.profile, w.result.unhealthy_before)
                reads += len(w.recipe.profile.health) - len(w.result.unhealthy_before)
            except (DeviceGone, ExceptionResponse) as e:
                why = f"could not be read: {e}"
                break
            if bad is not None:
                check, word = bad
                why = check.failure(word)
                break
            left = deadline - time.monotonic()
            if left <= 0 or (until is not None and until.is_set()):
                break
            await _pause(min(options.health_interval, left), until)
        seen = time.monotonic() - start
        if why is None:
            w.result.notices.append(
                f"{during or 'soak'} passed: {reads} health reads over "
                f"{format_duration(seen if during else options.soak or 0)}"
            )
            passed.append(w)
            return
        window = during or f"the {format_duration(options.soak or 0)} soak"
        # "after 0.0 s" alone read like a clock gone wrong: a device that trips on the write fails its first check
        first = " (its first check after the write)" if rounds == 1 else ""
        why = f"health check failed after {seen:.1f} s of {window}{first}: {why}"
        if run is not None:
            _journal(
                options,
                {
                    "event": "health-failed",
                    "run": run,
                    "time": journal._now(),
                    "name": w.name,
                    "url": w.result.url,
                    "unit": w.unit,
                    "reason": why,
                },
                w.result,
            )
        failed.append(w)
        if on_failed is not None:
            on_failed(w)
        rollbacks.append(asyncio.ensure_future(off_line(w, why)))
        await asyncio.shield(rollbacks[-1])  # an interrupt must not cut a rollback short

    rolling: dict[str, asyncio.Lock] = {}

    async def off_line(w: Written, why: str) -> None:
        """Roll ``w`` back with the watch's connection to its bus closed meanwhile: the rollback connects on its
        own, and a gateway or device may serve one connection only (it would never answer a second one). The
        watch of the other devices on that bus waits, and connects again after."""
        async with rolling.setdefault(w.url.bus, asyncio.Lock()):  # rollbacks on one bus: one after another
            line = lines.get(w.url.bus)
            if line is None:
                await roll_back(w, why, options)
                return
            transport, one_at_a_time, _ = line
            async with one_at_a_time:
                await transport.close()
                try:
                    await roll_back(w, why, options)
                finally:
                    if any(v.url.bus == w.url.bus and v not in passed and v not in failed for v in todo):
                        await connect(transport)  # unreachable now: the next health read says so

    rollbacks: list[asyncio.Future[None]] = []
    interrupted = False
    try:
        await asyncio.gather(*(watch(w) for w in todo))
    except asyncio.CancelledError:  # Ctrl-C: a change that has not proven itself is undone, not left behind
        interrupted = True
        for w in todo:
            if w not in passed and w not in failed:
                failed.append(w)
                rollbacks.append(asyncio.ensure_future(off_line(w, "interrupted during the soak")))
        await asyncio.gather(*rollbacks, return_exceptions=True)
        raise
    finally:
        for transport, _, _ in lines.values():
            await transport.close()
        if journaled is not None:
            _journal(
                options,
                {
                    "event": "soak-finished",
                    "run": run,
                    "time": journal._now(),
                    "passed": [w.name for w in passed],
                    "rolled_back": [w.name for w in failed if w.result.status == "rolled-back"],
                    "failed": [w.name for w in failed if w.result.status != "rolled-back"],
                    **({"interrupted": True} if interrupted else {}),
                },
                *(w.result for w in todo),
            )
    return [w for w in todo if w in passed]


async def _pause(seconds: float, until: asyncio.Event | None) -> None:
    """Sleep, or less when ``until`` is set meanwhile."""
    if until is None:
        await asyncio.sleep(seconds)
        return
    with contextlib.suppress(asyncio.TimeoutError):
        await asyncio.wait_for(until.wait(), seconds)
