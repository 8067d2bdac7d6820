"""Running the agent as a process: the HTTP server, the signals, the ``listening on`` line (``deployer agent``)."""

from __future__ import annotations

import asyncio
import contextlib
import signal
import ssl
import sys
from collections.abc import Callable, Sequence

from aiohttp import web

from ..errors import UsageError
from .core import Agent, Settings
from .notify import Notifier
from .security import check_listen
from .server import METRICS, STOP, app
from .wire import Runner


def parse_listen(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:PORT`` for IPv6); where it may be is ``security.check_listen``'s."""
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or int(port) > 65535:
        raise UsageError(f"--listen {text}: expected HOST:PORT, e.g. 127.0.0.1:8470")
    return host.strip("[]") or "127.0.0.1", int(port)


async def serve(settings: Settings, listen: str = "127.0.0.1:8470", *,
                on_ready: Callable[[str], None] | None = None, signals: bool = True,
                token: str | None = None, tls: ssl.SSLContext | None = None, notify: Sequence[str] = ()) -> int:
    """Run the agent until SIGTERM, SIGINT, Ctrl-Break or ``POST /v1/stop`` (or the task is cancelled); 0 when it
    ended cleanly."""
    host, port = parse_listen(listen)
    check_listen(host, token=token is not None, tls=tls is not None, listen=listen)
    agent = Agent(settings)
    agent.open()  # the files are checked, the state folder is ours: nothing sent yet
    notifier = Notifier(agent, notify) if notify else None
    application = app(agent, token=token)
    stop = asyncio.Event()
    application[STOP] = stop.set  # POST /v1/stop: a service manager's way on Windows
    if notifier is not None:
        application[METRICS].register(notifier)  # its queues and failures on /metrics
    runner = Runner(application, access_log=None, handle_signals=False)
    await runner.setup()
    site = web.TCPSite(runner, host, port, reuse_address=True, ssl_context=tls)
    try:
        await site.start()
    except OSError as e:
        await runner.cleanup()
        await agent.stop()
        raise UsageError(f"--listen {listen}: {e.strerror}") from None
    sock = runner.addresses[0] if runner.addresses else (host, port)  # port 0: the one the system chose
    shown = f"[{sock[0]}]" if ":" in str(sock[0]) else str(sock[0])
    url = f"{'https' if tls is not None else 'http'}://{shown}:{sock[1]}"
    from ..portable import interrupt_signals, on_signals

    loop = asyncio.get_running_loop()
    undo = []
    if signals:  # the event loop's handlers, or signal.signal on Windows (no SIGHUP there: restart to reload)
        undo.append(on_signals(loop, interrupt_signals(), lambda _sig: stop.set()))
        if hasattr(signal, "SIGHUP"):
            undo.append(on_signals(loop, (signal.SIGHUP,), lambda _sig: _reload(agent)))
    try:
        if notifier is not None:
            notifier.start(url)  # before the agent's start: its first events are sent too
        await agent.start(url)
        print(f"listening on {url}", file=sys.stderr, flush=True)
        if on_ready is not None:
            on_ready(url)
        await stop.wait()
    finally:
        for u in undo:
            u()
        await agent.stop()
        await runner.cleanup()
        if notifier is not None:
            await notifier.stop()
    return 0


def _reload(agent: Agent) -> None:
    from .core import ApiError

    with contextlib.suppress(ApiError):  # an invalid edit is an event; nothing changes
        agent.reload()
