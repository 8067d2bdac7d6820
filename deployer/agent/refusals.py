"""Requests the agent refused: counted for ``/metrics`` (every one) and audited (``audit_events.audited``).

A scanner or a hostile page can send thousands of refused requests a second; each would be an event committed
to the database (fsync'ed) and a line in the log. So the first refusal of a kind from one address (or one
user) is audited at once, the ones that follow within a minute are counted, and the next record says how
many there were (``repeated``); the counts still open when the agent stops are recorded then. ``/metrics``
counts every one.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from aiohttp import web
from prometheus_client.core import CounterMetricFamily, Metric

from ..load.messages import printable
from .audit_events import audited

if TYPE_CHECKING:
    from .core import Agent

EVERY = 60.0  # seconds between two records of one kind of refusal from one address or user
KEEP = 1000  # keys remembered; beyond that the oldest are recorded and forgotten


@dataclass
class _Held:
    last: float
    repeated: int = 0
    fields: dict[str, Any] = field(default_factory=dict)
    message: str = ""


class Refusals:
    """Counters by kind and label, and the audit of each kind of refusal, at most once a minute per key."""

    def __init__(self, agent: Agent | None) -> None:
        self.agent = agent
        self.unauthorized = 0  # no credential, a wrong one, a disabled user
        self.forbidden: dict[str, int] = {}  # a role missing, by the role
        self.door: dict[str, int] = {}  # refused at the door (host, origin, fetch-site, content-type), by why
        self._held: dict[tuple[str, ...], _Held] = {}

    def refused(self, kind: str, key: tuple[str, ...], message: str, **fields: Any) -> None:
        """One refusal: audited now when the key's last record is a minute old, else counted for the next."""
        now = time.monotonic()
        k = (kind, *key)
        held = self._held.get(k)
        if held is not None and now - held.last < EVERY:
            held.repeated += 1
            held.fields, held.message = fields, message
            return
        if len(self._held) >= KEEP:
            self.flush(older_than=EVERY)
            if len(self._held) >= KEEP:
                self.flush()
        repeated = held.repeated if held is not None else 0
        self._held[k] = _Held(now)
        self._record(kind, message, fields, repeated)

    def flush(self, older_than: float = 0.0) -> None:
        """Record the counts still held (at the agent's stop; or to forget old keys)."""
        now = time.monotonic()
        for k, held in list(self._held.items()):
            if now - held.last >= older_than:
                del self._held[k]
                if held.repeated:
                    self._record(k[0], held.message, held.fields, held.repeated, last=True)

    def _record(self, kind: str, message: str, fields: dict[str, Any], repeated: int, *, last: bool = False) -> None:
        if self.agent is None or self.agent.store is None:
            return
        more = f" ({repeated} more like it {'since' if not last else 'after'} the last record)" if repeated else ""
        audited(self.agent, kind, message + more, **fields, repeated=repeated or None)

    def collect(self) -> Iterator[Metric]:
        u = CounterMetricFamily(
            "deployer_http_unauthorized_requests",
            "requests refused for want of a valid credential (none, a wrong one, a disabled user)",
        )
        u.add_metric([], self.unauthorized)
        yield u
        f = CounterMetricFamily(
            "deployer_http_forbidden_requests", "requests refused for want of a role", labels=["role"]
        )
        for role, n in sorted(self.forbidden.items()):
            f.add_metric([role], n)
        yield f
        d = CounterMetricFamily(
            "deployer_http_refused_requests",
            "requests refused at the door: a Host or Origin not the agent's own, a cross-site "
            "browser request, a body not sent as application/json",
            labels=["why"],
        )
        for why, n in sorted(self.door.items()):
            d.add_metric([why], n)
        yield d


def where(request: web.Request) -> dict[str, Any]:
    """What a refusal record says of the request: its address, method and path (cut, printable)."""
    return {"remote": request.remote or "?", "method": request.method, "path": printable(request.path[:200])}
