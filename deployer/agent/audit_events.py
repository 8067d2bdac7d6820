"""The one way the agent's door records what it refused and who changed whom: ``audited``.

Every auditable event of the door and of the users (a request refused at the door, a login refused, a role
missing, a user added, disabled, given a new token ...) goes through ``audited`` and nowhere else, so that
the tamper-evident trail (docs/change-control.md) is connected here, in one place, and nothing is left out.
Until then it is an event of the agent's log (database, journal, stderr, ``--notify``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from ..load.messages import printable

if TYPE_CHECKING:
    from .core import Agent


def audited(agent: Agent, kind: str, message: str, **fields: Any) -> dict[str, Any]:
    """Record ``kind`` with ``fields`` (JSON values; None left out) and a one-line ``message`` for people."""
    detail: Mapping[str, Any] = {k: v for k, v in fields.items() if v is not None}
    return agent.event(kind, printable(message), detail=detail)
