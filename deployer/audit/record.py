"""What goes into the audit trail: one record per event, and the records of a command-line run.

``event`` makes a record's fields (``trail.append`` numbers and chains it); ``append_cli`` appends for a
command-line process, in the policy's trail folder or ``STATE/audit``; ``run_records`` says a finished apply or
rollback device by device, each parameter with its old and new value.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from ..errors import StateError
from . import trail

if TYPE_CHECKING:
    from ..report import Report

FOLDER = "audit"
# events that say something was refused: warnings in syslog, counted apart
REFUSALS = frozenset({"apply-refused", "approve-refused", "login-refused"})


def folder_of(state_dir: str, configured: str | None = None) -> str:
    """The trail's folder: the policy's ``audit.trail``, else ``STATE/audit``."""
    return configured or os.path.join(os.path.abspath(state_dir), FOLDER)


def event(
    name: str,
    *,
    user: str | None = None,
    role: str | None = None,
    via: str = "cli",
    reason: str | None = None,
    device: str | None = None,
    result: str | None = None,
    run: str | None = None,
    plan: str | None = None,
    detail: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """One record's fields; ``user`` defaults to the operating system's user."""
    from ..portable import user_name

    return {
        "event": name,
        "user": user or user_name(),
        "role": role,
        "via": via,
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "reason": reason,
        "device": device,
        "result": result,
        "run": run,
        "plan": plan,
        "detail": dict(detail or {}),
    }


def append_cli(state_dir: str, configured: str | None, records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Append for this process; StateError when the trail cannot take them (the caller fails closed or says so)."""
    where = folder_of(state_dir, configured)
    try:
        return trail.append(where, records)
    except OSError as e:
        from ..state.durable import disk_error

        raise StateError(f"cannot write the audit trail {where}: {disk_error(e)}") from None


def _values(p: Any) -> tuple[Any, Any]:
    """Engineering text where the profile reads it, else the raw registers."""
    old = p.before if p.before is not None else None if p.before_raw is None else list(p.before_raw)
    new = p.after if p.after is not None else None if p.after_raw is None else list(p.after_raw)
    return old, new


def run_records(
    report: Report, *, command: str, change: Mapping[str, Any] | None = None, via: str = "cli"
) -> list[dict[str, Any]]:
    """A finished apply or rollback: a record per device that was started, with each parameter's old and new
    value and status (``applied`` or ``rolled-back``), the plan's digest and reason where it ran a plan."""
    from ..portable import user_name

    name = "rolled-back" if command == "rollback" else "applied"
    change = change or {}
    user = user_name()  # once: without $USER it reads the password database (a fleet has thousands of records)
    out = []
    for d in report.devices:
        if d.status == "skipped" and not d.parameters:
            continue
        params = []
        for p in d.parameters:
            old, new = _values(p)
            params.append({"name": p.name, "old": old, "new": new, "desired": p.desired, "status": p.status})
        out.append(
            event(
                name,
                user=user,
                reason=change.get("reason"),
                device=d.name,
                result=d.status,
                run=report.run_id,
                plan=change.get("digest"),
                via=via,
                detail={
                    "url": d.url,
                    "unit": d.unit,
                    "profile": d.profile,
                    "snapshot": d.snapshot,
                    "error": d.error,
                    "parameters": params,
                    **({"author": change["author"]} if change.get("author") else {}),
                    **({"ticket": change["ticket"]} if change.get("ticket") else {}),
                },
            )
        )
    return out
