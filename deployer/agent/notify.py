"""``deployer agent --notify URL``: a JSON POST per event to each URL (docs/operations.md, "Notifications").

The agent's event hook only appends to a bounded queue per URL; one background task per URL sends them in
order and retries a failed delivery with back-off, so a receiver that is down or slow never holds up
device work. When a queue is full its oldest event is dropped (said on stderr): the events stay in the
agent's database (``GET /v1/events``) whatever happens here.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
import threading
from collections import deque
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit

import aiohttp
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from ..errors import UsageError
from .core import Agent

PAYLOAD_VERSION = 1
QUEUE = 1000  # events kept per receiver while it is down
FIRST_BACKOFF = 0.5  # seconds; doubled after every failed try, up to MAX_BACKOFF
MAX_BACKOFF = 30.0
TIMEOUT = 10.0  # one POST, connect to answer


def check_url(url: str) -> str:
    u = urlsplit(url)
    if u.scheme not in ("http", "https") or not u.hostname:
        raise UsageError(f"--notify {url}: expected an http:// or https:// URL")
    return url


def _shown(url: str) -> str:
    """The URL without a password in it (a receiver's basic-auth user:password is nobody's business)."""
    u = urlsplit(url)
    if u.password is None:
        return url
    host = u.hostname or ""
    netloc = f"{u.username}:***@{host}" + (f":{u.port}" if u.port else "")
    return u._replace(netloc=netloc).geturl()


def payload(agent_url: str, ev: Mapping[str, Any]) -> dict[str, Any]:
    """What is POSTed: the event as ``GET /v1/events`` shows it, with the agent's address and a version."""
    return {
        "version": PAYLOAD_VERSION,
        "agent": agent_url,
        "id": ev.get("id"),
        "time": ev.get("time"),
        "device": ev.get("device"),
        "kind": ev.get("kind"),
        "message": ev.get("message"),
        "detail": ev.get("detail"),
    }


@dataclass
class _Receiver:
    url: str
    queue: deque[dict[str, Any]] = field(default_factory=lambda: deque(maxlen=QUEUE))
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    sent: int = 0
    dropped: int = 0
    failing: bool = False


class Notifier:
    """Sends the agent's events to ``urls``; ``start`` inside the agent's event loop, ``stop`` at its end."""

    def __init__(
        self,
        agent: Agent,
        urls: Sequence[str],
        *,
        first_backoff: float = FIRST_BACKOFF,
        max_backoff: float = MAX_BACKOFF,
    ) -> None:
        self.receivers = [_Receiver(check_url(u)) for u in dict.fromkeys(urls)]
        self.first_backoff, self.max_backoff = first_backoff, max_backoff
        self.agent_url = ""
        self._tasks: list[asyncio.Task[None]] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread = 0
        self._session: aiohttp.ClientSession | None = None
        agent.on_event.append(self.put)

    def start(self, agent_url: str) -> None:
        self.agent_url = agent_url
        self._loop = asyncio.get_running_loop()
        self._thread = threading.get_ident()
        self._session = aiohttp.ClientSession(
            timeout=aiohttp.ClientTimeout(total=TIMEOUT), headers={"User-Agent": "deployer-agent"}
        )
        self._tasks = [asyncio.ensure_future(self._send_forever(r)) for r in self.receivers]

    def put(self, ev: Mapping[str, Any]) -> None:
        """The agent's event hook: never waits (an event from another thread is handed to the loop)."""
        body = payload(self.agent_url, ev)
        if self._loop is None:
            return
        if threading.get_ident() == self._thread:
            self._enqueue(body)
        else:
            with contextlib.suppress(RuntimeError):  # the loop has closed: the database still has it
                self._loop.call_soon_threadsafe(self._enqueue, body)

    def _enqueue(self, body: dict[str, Any]) -> None:
        for r in self.receivers:
            if len(r.queue) == r.queue.maxlen:
                r.dropped += 1
                print(
                    f"agent: notify {_shown(r.url)}: {QUEUE} events waiting, the oldest dropped "
                    f"({r.dropped} so far; GET /v1/events has them all)",
                    file=sys.stderr,
                    flush=True,
                )
            r.queue.append(body)
            r.wake.set()

    async def _send_forever(self, r: _Receiver) -> None:
        backoff = self.first_backoff
        while True:
            if not r.queue:
                r.wake.clear()
                await r.wake.wait()
                continue
            body = r.queue[0]
            why = await self._post(r.url, body)
            if why is None or why.startswith("refused"):
                if r.queue and r.queue[0] is body:
                    r.queue.popleft()
                if why is None:
                    r.sent += 1
                    if r.failing:
                        print(f"agent: notify {_shown(r.url)}: delivered again", file=sys.stderr, flush=True)
                    r.failing, backoff = False, self.first_backoff
                else:  # the receiver says this event is wrong: retrying would not change its mind
                    print(
                        f"agent: notify {_shown(r.url)}: event {body['id']} {why}; not sent again",
                        file=sys.stderr,
                        flush=True,
                    )
                continue
            if not r.failing:
                print(
                    f"agent: notify {_shown(r.url)}: {why}; retrying with back-off (up to {self.max_backoff:g} s)",
                    file=sys.stderr,
                    flush=True,
                )
            r.failing = True
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2, self.max_backoff)

    async def _post(self, url: str, body: Mapping[str, Any]) -> str | None:
        """None when delivered; else why not (``refused ...`` for an answer that retrying would not change)."""
        assert self._session is not None
        try:
            async with self._session.post(url, json=body) as resp:
                if 200 <= resp.status < 300:
                    return None
                if 400 <= resp.status < 500 and resp.status not in (408, 425, 429):
                    return f"refused with HTTP {resp.status}"
                return f"HTTP {resp.status}"
        except (TimeoutError, aiohttp.ClientError, OSError) as e:
            return f"{type(e).__name__}: {e}" if str(e) else type(e).__name__

    async def stop(self, grace: float = 2.0) -> None:
        """The agent stops: a short while to send what waits (its 'stopped' event), then let go."""
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(self._drained(), grace)
        for t in self._tasks:
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self._session is not None:
            await self._session.close()
        for r in self.receivers:
            if r.queue:
                print(
                    f"agent: notify {_shown(r.url)}: {len(r.queue)} events not delivered (GET /v1/events has them)",
                    file=sys.stderr,
                    flush=True,
                )

    async def _drained(self) -> None:
        while any(r.queue for r in self.receivers):
            await asyncio.sleep(0.05)

    def collect(self) -> Iterator[Metric]:
        """For ``/metrics``: per receiver, events waiting, delivered, dropped, and whether it fails now."""
        waiting = GaugeMetricFamily("deployer_notify_waiting", "events queued for the receiver", labels=["url"])
        sent = CounterMetricFamily("deployer_notify_sent", "events the receiver took", labels=["url"])
        dropped = CounterMetricFamily("deployer_notify_dropped", "events dropped from a full queue", labels=["url"])
        failing = GaugeMetricFamily(
            "deployer_notify_failing", "1 while deliveries to the receiver fail", labels=["url"]
        )
        for r in self.receivers:
            label = [_shown(r.url)]
            waiting.add_metric(label, len(r.queue))
            sent.add_metric(label, r.sent)
            dropped.add_metric(label, r.dropped)
            failing.add_metric(label, 1.0 if r.failing else 0.0)
        yield from (waiting, sent, dropped, failing)

    def status(self) -> list[dict[str, Any]]:
        return [
            {"url": r.url, "waiting": len(r.queue), "sent": r.sent, "dropped": r.dropped, "failing": r.failing}
            for r in self.receivers
        ]
