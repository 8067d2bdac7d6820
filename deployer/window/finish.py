"""The end of a window: the held commit sent, or the change rolled back from its snapshot.

Both first read the run's parameters again (``recheck``), under the device's lock: a value changed
during the window (by hand, by another tool) is never committed and never overwritten by the rollback.
The commit is then not sent; the parameters that still hold what the run wrote are rolled back, the
changed ones are left as found, and the device ends ``failed`` naming each of them.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import replace

from ..errors import DeviceGone, ExceptionResponse, InputError, Locked, Unreachable, UsageError
from ..execute.connect import connected
from ..execute.device import apply_job
from ..execute.executor import Execution
from ..execute.job import Job
from ..execute.session import ApplyOptions, Session
from ..execute.verify import values_of
from ..planning.model import Target
from ..planning.planner import plan_reads
from ..planning.steps import Planner, pacing_for
from ..profile import Profile, profile_ref
from ..recipe.loader import Desired, load_recipe
from ..report import DeviceResult, ParameterResult, RequestRecord, show_registers
from ..state import journal, learned, lock, snapshot
from .held import Written, record

Changed = list[tuple[ParameterResult, tuple[int, ...]]]  # a parameter the run wrote, and what it holds now


async def per_line(devices: Iterable[Written], step: Callable[[Written], Awaitable[None]]) -> None:
    """``step`` for each device: the devices on one bus (a gateway, a serial line) one after another, each bus in
    parallel. Each step opens a connection of its own, and a gateway may serve only one at a time."""
    buses: dict[str, list[Written]] = {}
    for w in devices:
        buses.setdefault(w.url.bus, []).append(w)

    async def along(line: list[Written]) -> None:
        for w in line:
            await step(w)

    await asyncio.gather(*(along(line) for line in buses.values()))


def release(w: Written) -> None:
    """The window of ``w`` is over: its device's lock goes (a run waiting for it may start)."""
    for h in reversed(w.locks):
        h.release()
    w.locks.clear()


async def _locks(w: Written, options: ApplyOptions) -> str | None:
    """Make sure ``w`` holds its device's lock (a window keeps it from the write; a rollback after the window
    takes it again); why not, when another run holds it."""
    if w.locks:
        return None
    try:
        w.locks.extend(
            await lock.acquire_device(
                w.url.lock_keys,
                w.unit,
                timeout=options.lock_timeout,
                command=lock.command_line(),
                directory=options.lock_dir,
                run=options.run_id,
            )
        )
    except Locked as e:
        return str(e)
    return None


async def recheck(session: Session, w: Written) -> Changed:
    """The run's parameters (those it wrote and verified) that no longer hold what it read back."""
    prof = w.recipe.profile
    ours = [p for p in w.result.parameters if p.status == "ok" and p.after_raw is not None]
    params = [prof.parameter(p.name) for p in ours]
    if not params:
        return []
    now = values_of(params, await session.read_blocks(plan_reads(prof, [p.name for p in params if p.readable]), prof))
    out: Changed = []
    for p in ours:
        found = now.get(p.name)
        if found is not None and p.after_raw is not None and not prof.parameter(p.name).same_value(found, p.after_raw):
            out.append((p, found))
    return out


def changed_text(w: Written, changed: Changed) -> str:
    """``F07 holds 9.99 s, the run wrote 3 s; ...``: each changed parameter, found and written."""
    prof = w.recipe.profile
    return "; ".join(
        f"{p.name} holds {show_registers(prof.parameter(p.name), found)}, the run wrote "
        f"{show_registers(prof.parameter(p.name), p.after_raw)}"
        for p, found in changed
    )


async def _read_again(w: Written, options: ApplyOptions, records: list[RequestRecord]) -> Changed | str:
    """``recheck`` on a connection of its own; why it could not be read instead."""
    try:
        async with connected(w.url, w.unit, w.recipe.profile, records=records, backoff=options.backoff) as session:
            return await recheck(session, w)
    except (Unreachable, DeviceGone, ExceptionResponse) as e:
        return str(e)


async def roll_back(w: Written, why: str, options: ApplyOptions) -> None:
    """Restore ``w`` from its snapshot now (verified, no commit unless its commit was sent), then end its window.

    Only the parameters that still hold what the run wrote are restored; one changed since is left as found
    and named, and the device ends ``failed``. Otherwise it ends ``rolled-back``, or ``failed`` with both
    reasons when the rollback itself did not verify."""
    try:
        await _roll_back(w, why, options)
    finally:
        _journal_rollback(options, w, why)
        release(w)


async def _roll_back(w: Written, why: str, options: ApplyOptions) -> None:
    res = w.result
    assert res.snapshot is not None
    try:
        # a process that died before fsync'ing it (an agent killed in the window, then a power loss) left its text
        # in the write-ahead log: restored first
        snapshot.recover(snapshot.state_of(res.snapshot))
        snap = load_recipe(res.snapshot)
    except (InputError, OSError) as e:
        res.status, res.error = "failed", f"{why}; the snapshot could not be loaded to roll back: {e}"
        return
    busy = await _locks(w, options)
    if busy is not None:
        res.status, res.error = "failed", f"{why}; not rolled back: {busy}"
        return
    start = len(res.requests)
    changed = await _read_again(w, options, res.requests)
    _at_the_end(res, start)
    if isinstance(changed, str):
        changed = []  # the rollback reads the device itself, and says what it finds
    left = {p.name for p, _ in changed}
    snap = replace(snap, desired=tuple(d for d in snap.desired if d.name not in left))
    # a device whose commit was sent gets the restored values committed too (else its memory keeps the change)
    back_opts = replace(
        options,
        hold_commit=res.commit != "sent",
        confirm=None,
        run_id=None,
        write_all=False,
        applied=res.snapshot,
        soak=None,
        confirm_within=None,
        keep_lock=None,
        lock_held=True,
        on_writing=None,
        restoring=True,
    )  # its result says what the rollback did
    back = None
    if snap.desired:
        try:
            back, finishing = await apply_job(Job(w.name, snap, w.url, w.unit), back_opts)
        except UsageError as e:
            res.status, res.error = "failed", f"{why}; rolling back failed: {e}"
            return
        if finishing is not None:
            await finishing
        _merge(w, back)
    for p, found in changed:
        p.status, p.after_raw = "failed", found
        p.error = f"changed during the window: {changed_text(w, [(p, found)])}; left as found, not rolled back"
    if changed:
        res.status = "failed"
        res.error = f"{why}; changed since the run wrote it: {changed_text(w, changed)}: left as found" + (
            f"; the run's other parameters rolled back ({_back_status(back)})" if back else ""
        )
    elif back is not None and back.status == "ok":
        res.status, res.error = "rolled-back", f"{why}; rolled back from the snapshot (verified)"
    elif back is not None:
        res.status = "failed"
        res.error = f"{why}; the rollback did not verify ({back.status}: {back.error or 'see the parameters'})"
    if back is not None and back.snapshot:
        res.notices.append(f"what the device held before the rollback: {back.snapshot}")


def _at_the_end(res: DeviceResult, start: int) -> None:
    """The requests from ``start`` on were sent at the window's end: its commit's own plan, or the rollback (their
    ``step`` numbers are that plan's, not the apply's)."""
    for r in res.requests[start:]:
        r.window = True


def _back_status(back: DeviceResult) -> str:
    return "verified" if back.status == "ok" else f"{back.status}: {back.error or 'see the parameters'}"


def _merge(w: Written, back: DeviceResult) -> None:
    """The rollback's requests and parameter outcomes into the device's result."""
    res = w.result
    res.requests.extend(back.requests)
    _at_the_end(res, len(res.requests) - len(back.requests))
    res.unrecorded.extend(back.unrecorded)
    by_name = {p.name: p for p in back.parameters}
    for p in res.parameters:
        b = by_name.get(p.name)
        if b is None:
            continue
        if b.after_raw is not None:
            p.after_raw = b.after_raw
        if b.status == "ok":  # written back to the snapshot's value and verified
            p.status, p.error = "rolled-back", f"restored to {b.desired}"
        elif b.status not in ("unchanged", "skipped"):
            p.status, p.error = b.status, f"rollback: {b.error or b.status}"
        elif back.status != "ok" and p.status == "ok":  # never read again: what it holds now is not known
            p.status, p.error = "unverified", f"state unknown: the rollback did not reach it ({back.status})"


def _journal_rollback(options: ApplyOptions, w: Written, why: str) -> None:
    if options.run_id is not None:
        record(
            options,
            {
                "event": "rolled-back",
                "run": options.run_id,
                "time": journal._now(),
                "name": w.name,
                "url": w.result.url,
                "unit": w.unit,
                "status": w.result.status,
                "reason": why,
                "snapshot": w.result.snapshot,
            },
            w.result,
        )


def _taught(options: ApplyOptions, w: Written) -> Profile:
    """The profile with what the device taught (Function 06 where it refuses 16, shorter writes)."""
    prof = w.recipe.profile
    entry = learned.lookup(options.state_dir, profile_ref(prof), learned.device_id(w.url, w.unit))
    return prof if entry is None else learned.with_limits(prof, entry)


async def send_commit(w: Written, options: ApplyOptions) -> None:
    """The profile's held-back ``commit`` steps (unlock and lock around them, as in an apply), after reading the
    run's parameters again; then the window of ``w`` ends. A step that fails makes the device ``failed`` (its
    parameters stay ``ok``: verified, in RAM); a changed parameter: no commit, the rest rolled back."""
    res = w.result
    if res.commit != "held":
        release(w)
        return
    changed = None
    start = len(res.requests)
    try:
        changed = await _commit(w, options)
    finally:
        _at_the_end(res, start)
        _journal_commit(options, w, changed)
        if changed is None:
            release(w)
    if changed is not None:  # the lock is still held: the rollback reads and restores under it
        await roll_back(w, f"commit not sent: {changed}", options)
        res.commit = "not sent"


def _journal_commit(options: ApplyOptions, w: Written, changed: str | None) -> None:
    res = w.result
    if options.run_id is not None:
        record(
            options,
            {
                "event": "commit",
                "run": options.run_id,
                "time": journal._now(),
                "name": w.name,
                "url": res.url,
                "unit": w.unit,
                "result": res.commit,
                **({"error": res.error or changed} if res.commit != "sent" else {}),
            },
            res,
        )


async def _commit(w: Written, options: ApplyOptions) -> str | None:
    """Send the commit: a plan of its own (the checks over the run's parameters, then unlock, commit, lock),
    made against what the run read back; the changed parameters' text instead when the device no longer holds
    what the run wrote (nothing sent then: the caller rolls back the rest)."""
    res = w.result
    prof = _taught(options, w)
    busy = await _locks(w, options)
    if busy is not None:
        res.status, res.error, res.commit = "failed", f"commit not sent: {busy}", "not sent"
        return None
    ours = [p for p in res.parameters if p.status == "ok" and p.after_raw is not None]
    rec = replace(
        w.recipe,
        profile=prof,
        desired=tuple(
            Desired(prof.parameter(p.name), p.desired, tuple(p.after_raw)) for p in ours if p.after_raw is not None
        ),
    )
    plan = Planner(rec, device_id=False, pacing=pacing_for(w.url, prof)).plan(
        Target(res.url, w.unit, profile_ref(prof)),
        {p.name: tuple(p.after_raw) for p in ours if p.after_raw},
        commit_owed=True,
    )
    results = {
        p.name: ParameterResult(
            p.name,
            p.address,
            p.count,
            p.desired,
            tuple(p.after_raw or ()),
            status="ok",
            parameter=prof.parameter(p.name),
        )
        for p in ours
    }
    try:
        async with connected(w.url, w.unit, prof, records=res.requests, backoff=options.backoff) as session:
            ex = Execution(
                session,
                rec,
                res,
                results,
                replace(options, hold_commit=False, soak=None, confirm_within=None),
                lambda regs: values_of([d.parameter for d in rec.desired], regs),
            )
            if not await ex.checks(plan.steps[: plan.checks]):
                why = res.error or "the device could not be read"
                res.status, res.error, res.commit = (
                    "failed",
                    f"commit not sent: re-reading the parameters failed: {why.removesuffix('; nothing was written')}",
                    "not sent",
                )
                return None
            changed = [
                (p, ex.before[p.name])
                for p in ours
                if p.name in ex.before
                and p.after_raw is not None
                and not prof.parameter(p.name).same_value(ex.before[p.name], p.after_raw)
            ]
            if changed:
                res.commit = "not sent"
                return changed_text(w, changed)
            await ex.changes(plan)
    except (Unreachable, DeviceGone, ExceptionResponse) as e:
        res.status, res.error, res.commit = (
            "failed",
            f"commit not sent: re-reading the parameters failed: {e}",
            "not sent",
        )
        return None
    return None
