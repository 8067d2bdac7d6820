"""The end of a window: the held commit sent, or the change rolled back from its snapshot."""

from __future__ import annotations

import contextlib
from dataclasses import replace

from ..execute.device import _apply_device
from ..execute.session import ApplyOptions, DeviceGone, Session
from ..execute.steps import _send_actions
from ..load.diagnostics import InputError, UsageError
from ..recipe.loader import load_recipe
from ..state import journal, lock
from ..transport import clients as tp
from .held import Written
from .held import record as _journal


async def roll_back(w: Written, why: str, options: ApplyOptions) -> None:
    """Restore ``w`` from its snapshot now (verified, no commit); it ends ``rolled-back``, or ``failed``
    with both reasons when the rollback itself did not verify."""
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

