"""The one way the agent's auditable events reach the tamper-evident audit trail (docs/change-control.md).

``audited``: the door's and the users' events (a request refused at the door, a login refused, a role missing, a
user added, disabled, given a new token ...), an event of the agent's log and a record of the trail. ``trailed``:
the agent's own events that change or could change a device (drift found, restored, a replaced device restored,
a window confirmed or expired, restores stopped), forwarded from ``Agent.event`` as they happen; ``run_finished``:
an agent run's record per device, each parameter's old and new value. The trail is the site policy's
(``change_control.audit.trail`` of the agent's inventory), else STATE/audit. A trail that cannot take a record
is said as an event of its own (``audit-not-recorded``): the agent's work goes on, the gap is visible.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, Protocol

from ..load.messages import printable

if TYPE_CHECKING:
    from ..api import Report


class _Settings(Protocol):
    @property
    def inventory(self) -> str: ...


class Agent(Protocol):
    """What of the agent its auditing needs (``site.Site``; a protocol: the site calls in here)."""

    state_dir: str

    @property
    def settings(self) -> _Settings: ...

    def event(
        self, kind: str, message: str, *, device: str | None = None, detail: Mapping[str, Any] | None = None
    ) -> dict[str, Any]: ...


# the agent's own events that change, or could change, a device; or say a change did not happen
TRAILED = frozenset(
    {
        "drift",
        "drift-cleared",
        "restored",
        "restore-failed",
        "restore-limit",
        "restores-stopped",
        "replaced",
        "replace-refused",
        "window-confirmed",
        "window-expired",
        "adopt-failed",
        "reload",
    }
)
REFUSED = frozenset(
    {
        "request-refused",
        "login-refused",
        "access-refused",
        "replace-refused",
        "restore-failed",
        "restores-stopped",
        "window-expired",
        "adopt-failed",
    }
)


def audited(agent: Agent, kind: str, message: str, **fields: Any) -> dict[str, Any]:
    """Record ``kind`` with ``fields`` (JSON values; None left out) and a one-line ``message`` for people: an event
    of the agent's log, and a record of the audit trail."""
    detail: Mapping[str, Any] = {k: v for k, v in fields.items() if v is not None}
    ev = agent.event(kind, printable(message), detail=detail)
    user = detail.get("by") or detail.get("user")
    _append(agent, [_record(kind, message, detail, user=str(user) if user is not None else None)])
    return ev


def trailed(agent: Agent, kind: str, message: str, device: str | None, detail: Mapping[str, Any] | None) -> None:
    """An event of the agent's own, on the trail when it is one of ``TRAILED``."""
    if kind in TRAILED:
        _append(agent, [_record(kind, message, dict(detail or {}), device=device)])


def run_finished(agent: Agent, report: Report, *, command: str, by: Mapping[str, Any] | None) -> None:
    """An agent run's records: per device started, each parameter's old and new value and status."""
    from ..audit import record

    user = None if not by else by.get("user")
    records = record.run_records(report, command="rollback" if command == "rollback" else "apply", via="agent")
    for r in records:
        r["user"] = user or "agent"
        r["detail"] = {**r["detail"], "agent_command": command}
    _append(agent, records)


def _record(
    kind: str, message: str, detail: Mapping[str, Any], *, user: str | None = None, device: str | None = None
) -> dict[str, Any]:
    from ..audit import record

    return record.event(
        kind,
        user=user or "agent",
        via="agent",
        device=device,
        result="refused" if kind in REFUSED else "ok",
        detail={"message": message, **detail},
    )


def _append(agent: Agent, records: Sequence[Mapping[str, Any]]) -> None:
    from ..audit import record
    from ..change import policy as policies
    from ..errors import DeployerError

    if not records:
        return
    try:
        pol = policies.load(agent.settings.inventory)
        record.append_cli(agent.state_dir, pol.audit.trail if pol is not None else None, records)
    except DeployerError as e:  # the trail cannot take it (a full disk, an invalid policy): said, not hidden
        with contextlib.suppress(Exception):
            agent.event(
                "audit-not-recorded",
                f"the audit trail could not take {len(records)} record(s): {e}",
                detail={"events": [r.get("event") for r in records]},
            )
