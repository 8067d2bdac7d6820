"""Keeping only changes that proved themselves: the soak, automatic rollback, held-back commits.

After a verified write the profile's ``health`` checks are read every ``health_interval`` for
``soak`` seconds; the first failed check rolls that device back from its snapshot at once (a
verified rollback, without the profile's ``commit``), and the device ends ``rolled-back``. The
``commit`` steps (a store to non-volatile memory) of the devices that passed are sent only
afterwards, or only once the run is confirmed (``confirm_within``, see ``await_confirmation``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

from ..load.diagnostics import InputError, UsageError
from ..load.durations import format_duration
from ..profile import HealthCheck, Profile
from ..state import journal, lock
from ..state.durable import append_lines
from ..transport import clients as tp
from .session import ApplyOptions, DeviceGone, Session
from .steps import _send_actions

if TYPE_CHECKING:
    from ..recipe.loader import Recipe
    from ..report import DeviceResult


@dataclass(frozen=True)
class Written:
    """A device whose change is verified and waits: for its soak, its commit or the run's confirmation."""

    name: str
    recipe: Recipe
    url: tp.DeviceURL
    unit: int
    result: DeviceResult


def needs_soak(r: DeviceResult) -> bool:
    """Something was written and verified (a device with nothing to write has nothing to watch or undo)."""
    return r.status == "ok" and r.snapshot is not None


def check_soak_profiles(profiles: Sequence[Profile]) -> None:
    """``--soak`` watches the profile's health checks: a profile without any is refused up front."""
    bare = sorted({p.id for p in profiles if not p.health})
    if bare:
        raise UsageError(f"--soak watches the profile's health checks, and profile {', '.join(bare)} declares none "
                         "(health: in the profile, e.g. - {register: 48, equals: 0, description: drive fault code "
                         "is zero}); use --confirm-within to hold the commit without checks")


async def read_health(session: Session, prof: Profile) -> tuple[HealthCheck, int] | None:
    """The first failed check and the word read, or None when the device is healthy."""
    for c in prof.health:
        (word,) = await session.read(c.address, 1, c.function)
        if not c.holds(word):
            return c, word
    return None


async def soak(devices: Sequence[Written], options: ApplyOptions, *,
               on_failed: Callable[[Written], None] | None = None, report: str | None = None) -> list[Written]:
    """Watch ``devices`` together for ``options.soak`` seconds; roll back each one whose health fails.

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
    if run is not None:
        _journal(options, {"event": "soak-started", "run": run, "time": journal._now(), "seconds": options.soak,
                           "interval": options.health_interval, "devices": [w.name for w in todo],
                           "report": report})
    start = time.monotonic()
    deadline = start + options.soak
    passed: list[Written] = []
    failed: list[Written] = []

    # one connection per bus, one request at a time on it: a gateway allows few connections, and the
    # devices behind it share one line anyway
    lines: dict[str, tuple[tp.Transport, asyncio.Lock, asyncio.Future[str | None]]] = {}

    async def connect(transport: tp.Transport) -> str | None:
        try:
            await transport.connect()
        except tp.Unreachable as e:
            return f"the device could not be reached: {e}"
        return None

    async def watch(w: Written) -> None:
        if w.url.bus not in lines:
            transport = tp.open_transport(w.url)
            lines[w.url.bus] = (transport, asyncio.Lock(), asyncio.ensure_future(connect(transport)))
        transport, one_at_a_time, connected = lines[w.url.bus]
        records: list[Any] = []
        session = Session(transport, w.unit, retries=w.url.retries, backoff=options.backoff, records=records)
        reads = 0
        why: str | None = await asyncio.shield(connected)
        while why is None:
            try:
                async with one_at_a_time:
                    bad = await read_health(session, w.recipe.profile)
                reads += len(w.recipe.profile.health)
            except (DeviceGone, tp.ExceptionResponse) as e:
                why = f"could not be read: {e}"
                break
            if bad is not None:
                check, word = bad
                why = check.failure(word)
                break
            left = deadline - time.monotonic()
            if left <= 0:
                break
            await asyncio.sleep(min(options.health_interval, left))
        seen = time.monotonic() - start
        if why is None:
            w.result.notices.append(f"soak passed: {reads} health reads over {format_duration(options.soak or 0)}")
            passed.append(w)
            return
        why = f"health check failed after {seen:.1f} s of the {format_duration(options.soak or 0)} soak: {why}"
        if run is not None:
            _journal(options, {"event": "health-failed", "run": run, "time": journal._now(), "name": w.name,
                               "url": w.result.url, "unit": w.unit, "reason": why})
        failed.append(w)
        if on_failed is not None:
            on_failed(w)
        rollbacks.append(asyncio.ensure_future(roll_back(w, why, options)))
        await asyncio.shield(rollbacks[-1])  # an interrupt must not cut a rollback short

    rollbacks: list[asyncio.Future[None]] = []
    interrupted = False
    try:
        await asyncio.gather(*(watch(w) for w in todo))
    except asyncio.CancelledError:  # Ctrl-C: a change that has not proven itself is undone, not left behind
        interrupted = True
        for w in todo:
            if w not in passed and w not in failed:
                failed.append(w)
                rollbacks.append(asyncio.ensure_future(roll_back(w, "interrupted during the soak", options)))
        await asyncio.gather(*rollbacks, return_exceptions=True)
        raise
    finally:
        for transport, _, _ in lines.values():
            await transport.close()
        if run is not None:
            _journal(options, {"event": "soak-finished", "run": run, "time": journal._now(),
                               "passed": [w.name for w in passed],
                               "rolled_back": [w.name for w in failed if w.result.status == "rolled-back"],
                               "failed": [w.name for w in failed if w.result.status != "rolled-back"],
                               **({"interrupted": True} if interrupted else {})})
    return [w for w in todo if w in passed]


async def roll_back(w: Written, why: str, options: ApplyOptions) -> None:
    """Restore ``w`` from its snapshot now (verified, no commit); it ends ``rolled-back``, or ``failed``
    with both reasons when the rollback itself did not verify."""
    from ..recipe.loader import load_recipe
    from .device import _apply_device

    res = w.result
    assert res.snapshot is not None
    try:
        snap = load_recipe(res.snapshot)
    except (InputError, OSError) as e:
        res.status, res.error = "failed", f"{why}; the snapshot could not be loaded to roll back: {e}"
        _journal_rollback(options, w, why)
        return
    # a device whose commit was sent gets the restored values committed too (else its memory keeps the change)
    back_opts = replace(options, hold_commit=res.commit != "sent", confirm=None, run_id=None, expected=None,
                        write_all=False, applied=res.snapshot, soak=None, confirm_within=None)
    try:
        back, finishing = await _apply_device(snap, w.url, w.unit, name=w.name, options=back_opts)
    except UsageError as e:
        res.status, res.error = "failed", f"{why}; rolling back failed: {e}"
        _journal_rollback(options, w, why)
        return
    if finishing is not None:
        await finishing
    res.requests.extend(back.requests)
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
    if back.status == "ok":
        res.status, res.error = "rolled-back", f"{why}; rolled back from the snapshot (verified)"
    else:
        res.status = "failed"
        res.error = f"{why}; the rollback did not verify ({back.status}: {back.error or 'see the parameters'})"
    if back.snapshot:
        res.notices.append(f"what the device held before the rollback: {back.snapshot}")
    _journal_rollback(options, w, why)


def _journal_rollback(options: ApplyOptions, w: Written, why: str) -> None:
    if options.run_id is not None:
        _journal(options, {"event": "rolled-back", "run": options.run_id, "time": journal._now(), "name": w.name,
                           "url": w.result.url, "unit": w.unit, "status": w.result.status, "reason": why,
                           "snapshot": w.result.snapshot})


async def send_commit(w: Written, options: ApplyOptions) -> None:
    """The profile's held-back ``commit`` steps (unlock and lock around them, as in an apply)."""
    prof, res = w.recipe.profile, w.result
    if not prof.commit or res.commit != "held":
        return
    try:
        held = await lock.acquire_device(w.url.bus, w.unit, timeout=options.lock_timeout,
                                         command=lock.command_line(), directory=options.lock_dir)
    except lock.Locked as e:
        res.status, res.error = "partial", f"commit not sent: {e}"
        return
    try:
        transport = tp.open_transport(w.url)
        session = Session(transport, w.unit, retries=w.url.retries, backoff=options.backoff, records=res.requests)
        try:
            await transport.connect()
            if prof.unlock:
                await _send_actions(session, prof, prof.unlock)
            try:
                for action in prof.commit:
                    try:
                        await _send_actions(session, prof, [action])
                    except (DeviceGone, tp.ExceptionResponse) as e:
                        res.status = "partial"
                        res.error = f"commit '{action.description or hex(action.address)}' failed: {e}"
                        res.commit = "failed"
                        return
                res.commit = "sent"
            finally:
                if prof.unlock and prof.lock:
                    with contextlib.suppress(DeviceGone, tp.ExceptionResponse):
                        await _send_actions(session, prof, prof.lock)
        except (tp.Unreachable, DeviceGone, tp.ExceptionResponse) as e:
            res.status, res.error, res.commit = "partial", f"commit not sent: {e}", "failed"
        finally:
            await transport.close()
    finally:
        for h in reversed(held):
            h.release()
    if options.run_id is not None:
        _journal(options, {"event": "commit", "run": options.run_id, "time": journal._now(), "name": w.name,
                           "url": res.url, "unit": w.unit, "result": res.commit})


def _journal(options: ApplyOptions, record: dict[str, Any]) -> None:
    append_lines(journal.path_of(options.state_dir), [record])


# ---- confirmation (apply --confirm-within, deployer confirm) -------------------------------


def pending_path(state_dir: str, run: str) -> str:
    """The report of a run that waits for its confirmation (what ``status`` points a rollback at)."""
    return os.path.join(os.path.abspath(state_dir), "pending", f"{run}.json")


async def await_confirmation(run: str, seconds: float, options: ApplyOptions, *,
                             on_wait: Callable[[float], None] | None = None,
                             poll: float = 0.2) -> bool:
    """Wait until ``deployer confirm`` wrote a ``confirmed`` line for ``run`` (True) or ``seconds`` ran out.

    ``on_wait`` gets the deadline (time.time()) once the ``confirm-awaited`` line is on disk.
    """
    path = journal.path_of(options.state_dir)
    deadline = time.time() + seconds
    _journal(options, {"event": "confirm-awaited", "run": run, "time": journal._now(), "pid": os.getpid(),
                       "deadline": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(deadline)),
                       "deadline_epoch": deadline, "report": pending_path(options.state_dir, run)})
    offset = os.path.getsize(path)
    if on_wait is not None:
        on_wait(deadline)
    while True:
        offset, got = _confirmed_since(path, offset, run)
        if got:
            return True
        left = deadline - time.time()
        if left <= 0:
            _journal(options, {"event": "confirm-expired", "run": run, "time": journal._now()})
            return False
        try:
            await asyncio.sleep(min(poll, left))
        except asyncio.CancelledError:
            _journal(options, {"event": "confirm-interrupted", "run": run, "time": journal._now()})
            raise


def _confirmed_since(path: str, offset: int, run: str) -> tuple[int, bool]:
    """Read the journal's new complete lines from ``offset``: is one of them ``confirmed`` for ``run``?"""
    with open(path, "rb") as f:
        f.seek(offset)
        data = f.read()
    end = data.rfind(b"\n") + 1  # a line being appended right now is read next time, whole
    for line in data[:end].splitlines():
        with contextlib.suppress(ValueError):
            rec = json.loads(line)
            if isinstance(rec, dict) and rec.get("event") == "confirmed" and rec.get("run") == run:
                return offset + end, True
    return offset + end, False


@dataclass
class Awaiting:
    """A run that asked for confirmation and has no answer yet (from the journal)."""

    run: str
    pid: int | None
    deadline: str
    deadline_epoch: float
    report: str
    recipe: str | None = None

    @property
    def alive(self) -> bool:
        if self.pid is None:
            return False
        try:
            os.kill(self.pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            return True
        return True


def awaiting(state_dir: str) -> list[Awaiting]:
    """Runs whose ``confirm-awaited`` line has no answer (``confirmed``, ``confirm-expired``,
    ``confirm-interrupted``) or ``run-finished`` after it."""
    out: dict[str, Awaiting] = {}
    recipes: dict[str, str | None] = {}
    for rec in journal.read(state_dir):
        if rec is None or not rec.get("run"):
            continue
        run, event = str(rec["run"]), rec.get("event")
        if event == "run-started":
            recipes[run] = rec.get("recipe")
        elif event == "confirm-awaited":
            out[run] = Awaiting(run, rec.get("pid"), str(rec.get("deadline", "")),
                                float(rec.get("deadline_epoch", 0)), str(rec.get("report", "")), recipes.get(run))
        elif event in ("confirmed", "confirm-expired", "confirm-interrupted", "run-finished"):
            out.pop(run, None)
    return list(out.values())


def soaking(state_dir: str) -> dict[str, str | None]:
    """Runs whose last ``soak-started`` line has no ``soak-finished`` or ``run-finished`` after it: run -> the
    report of the run so far (None from a run without one)."""
    out: dict[str, str | None] = {}
    for rec in journal.read(state_dir):
        if rec is None or not rec.get("run"):
            continue
        run, event = str(rec["run"]), rec.get("event")
        if event == "soak-started":
            out[run] = rec.get("report")
        elif event in ("soak-finished", "run-finished"):
            out.pop(run, None)
    return out


def confirm_run(state_dir: str, run: str | None = None) -> Awaiting:
    """``deployer confirm [RUN]``: write the ``confirmed`` line the waiting run looks for (UsageError if none)."""
    waiting = awaiting(state_dir)
    where = journal.path_of(state_dir)
    if run is not None:
        match = [a for a in waiting if a.run == run]
        if not match:
            raise UsageError(f"run {run} does not wait for a confirmation in {where}"
                             + (f" (waiting: {', '.join(a.run for a in waiting)})" if waiting else ""))
        target = match[0]
    elif not waiting:
        soaks = soaking(state_dir)
        soaking_now = sorted(r.run for r in journal.unfinished(state_dir)[0] if r.run in soaks and r.running)
        if soaking_now:
            raise UsageError(f"run {', '.join(soaking_now)} is still soaking: it asks for the confirmation once its "
                             "soak passed (deployer status shows it)")
        raise UsageError(f"no run waits for a confirmation in {where} (wrong --state-dir?)")
    elif len(waiting) > 1:
        raise UsageError("several runs wait for a confirmation: name one (deployer confirm RUN): "
                         + ", ".join(f"{a.run} ({a.recipe or '?'}, until {a.deadline})" for a in waiting))
    else:
        target = waiting[0]
    if not target.alive:
        raise UsageError(f"run {target.run} waited for a confirmation, but its process (PID {target.pid}) is gone: "
                         "nothing can send its commit. Its devices hold uncommitted values; restore them with: "
                         f"deployer rollback --report {target.report} --state-dir {state_dir}")
    if time.time() > target.deadline_epoch:
        raise UsageError(f"run {target.run}: the confirmation time ran out at {target.deadline}; "
                         "it is rolling back (see deployer status)")
    _journal(ApplyOptions(state_dir=state_dir), {"event": "confirmed", "run": target.run, "time": journal._now(),
                                                  "user": journal.user_name(), "pid": os.getpid()})
    return target

