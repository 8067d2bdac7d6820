"""The one way to a device, for every command: the transport its URL names, paced as the URL and the profile
say, on its bus's rules (one request at a time per serial line or gateway, one open port), as a ``Session``.

apply, plan --device, diff, pull, rollback, the soak's health reads, a window's commit and rollback, probe,
scan and the agent all open devices here, so a gateway that needs its pauses gets them from every command.
"""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator

from ..planning.model import Pacing
from ..planning.steps import pacing_for
from ..profile import Profile
from ..report import RequestRecord
from ..transport import clients as tp
from .session import Session


@contextlib.asynccontextmanager
async def connected(
    url: tp.DeviceURL,
    unit: int,
    profile: Profile | None,
    *,
    records: list[RequestRecord] | None = None,
    backoff: float = 0.05,
    notices: list[str] | None = None,
    pacing: Pacing | None = None,
) -> AsyncIterator[Session]:
    """A session with the device at ``url``/``unit``, closed on the way out. Raises Unreachable when no connection
    can be made. ``records``: every request is logged there; ``notices``: told when the serial line went out of
    step (a late answer: the session's ``trust``); ``pacing``: ``pacing_for(url, profile)`` when the caller has it."""
    transport = tp.open_transport(url)
    p = pacing if pacing is not None else pacing_for(url, profile)
    transport.set_pacing(p.after_connect, p.between_requests)
    transport.backoff = backoff
    await transport.connect()
    session = Session(
        transport, unit, retries=url.retries, backoff=backoff, records=records if records is not None else []
    )
    try:
        yield session
    finally:
        await transport.close()
        doubt = session.trust.notice()  # the line went out of step: how, what it cost, the timeout that serves
        if doubt is not None and notices is not None:
            notices.append(doubt)
        if transport.connect_failures and notices is not None:  # a gateway's slots full a moment, a busy machine
            notices.append(connect_notice(transport.connect_failures))


def connect_notice(failures: int) -> str:
    """What the report says of connections that failed though the device took a test connection right after."""
    if failures == 1:
        what = "once, though a test connection right after it"
    else:
        what = f"{failures} times, though a test connection after each"
    return (
        f"connecting failed {what} got through; tried again (the URL's retries): the device or its gateway was slow "
        "to take a connection"
    )


def opened(url: tp.DeviceURL, profile: Profile | None) -> tp.Transport:
    """A transport for ``url`` paced for ``profile``, not connected yet: for the callers that keep one connection
    per bus for several devices and connect it themselves (the soak's health reads, scan)."""
    transport = tp.open_transport(url)
    p = pacing_for(url, profile)
    transport.set_pacing(p.after_connect, p.between_requests)
    return transport
