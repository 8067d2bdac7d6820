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
from . import local_token
from .access import Directory
from .audit_events import audited
from .core import Agent, Settings
from .door import Door
from .notify import Notifier
from .security import check_listen, read_token
from .server import METRICS, REFUSALS, STOP, app
from .wire import Runner


def parse_listen(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:PORT`` for IPv6); where it may be is ``security.check_listen``'s."""
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or int(port) > 65535:
        raise UsageError(f"--listen {text}: expected HOST:PORT, e.g. 127.0.0.1:8470")
    return host.strip("[]") or "127.0.0.1", int(port)


async def serve(
    settings: Settings,
    listen: str = "127.0.0.1:8470",
    *,
    on_ready: Callable[[str], None] | None = None,
    signals: bool = True,
    token: str | None = None,
    tls: ssl.SSLContext | None = None,
    notify: Sequence[str] = (),
    allowed_hosts: Sequence[str] = (),
    users: str | None = None,
) -> int:
    """Run the agent until SIGTERM, SIGINT, Ctrl-Break or ``POST /v1/stop`` (or the task is cancelled); 0 when it
    ended cleanly.

    ``users``: the users file (access.py); else ``token`` for the site; with neither the agent makes a token of
    its own (``local_token``) and says where it is."""
    host, port = parse_listen(listen)
    if users is not None and token is not None:
        raise UsageError("--users and --token-file: one or the other (named users, or one token for the site)")
    check_listen(host, token=token is not None or users is not None, tls=tls is not None, listen=listen)
    directory = Directory(users, None) if users is not None else None  # checked before anything starts
    agent = Agent(settings)
    agent.open()  # the files are checked, the state folder is ours: nothing sent yet
    made: str | None = None
    if token is None and directory is None:
        try:
            made, new = local_token.ensure(agent.folder)
        except OSError as e:
            await agent.stop()
            raise UsageError(f"cannot make the agent's token in {agent.folder}: {e.strerror or e}") from None
        token = read_token(made, "the agent's token file")
    if directory is not None:
        directory.agent = agent
    notifier = Notifier(agent, notify) if notify else None
    door = Door(host, tuple(allowed_hosts))
    application = app(agent, token=token, token_kind="agent token" if made else "token", users=directory, door=door)
    stop = asyncio.Event()
    application[STOP] = stop.set  # POST /v1/stop: a service manager's way on Windows
    if notifier is not None:
        application[METRICS].register(notifier)  # its queues and failures on /metrics
    from ..audit.forward import for_agent  # the policy's audit.syslog: the trail forwarded, its backlog on /metrics

    forwarder = for_agent(settings.inventory, settings.state_dir, application[METRICS])
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
    door.bind(url)
    note = None
    if made is not None:  # as Jupyter does: where the token is, for this user's clients and anyone told
        note = local_token.publish(url, made)
        print(
            f"agent: no --token-file: every request needs the token in {made} ({'made now' if new else 'kept'}, "
            f"{local_token.PROTECTION}); this user's deployer commands find it, anyone else: "
            f"--agent-token-file {made}",
            file=sys.stderr,
            flush=True,
        )
    from ..portable import interrupt_signals, on_signals

    forwarding: asyncio.Future[None] | None = None
    loop = asyncio.get_running_loop()
    undo = []
    if signals:  # the event loop's handlers, or signal.signal on Windows (no SIGHUP there: restart to reload)
        undo.append(on_signals(loop, interrupt_signals(), lambda _sig: stop.set()))
        if hasattr(signal, "SIGHUP"):
            undo.append(on_signals(loop, (signal.SIGHUP,), lambda _sig: _reload(agent)))
    try:
        if notifier is not None:
            notifier.start(url)  # before the agent's start: its first events are sent too
        if forwarder is not None:
            forwarding = asyncio.ensure_future(forwarder.run())
        await agent.start(url)
        if directory is not None:
            on = sorted(u.name for u in directory.users.values() if not u.disabled)
            audited(
                agent,
                "users-loaded",
                f"{len(on)} enabled users from {users}: {', '.join(on)[:300]}",
                file=users,
                users=on,
            )
        print(f"listening on {url}", file=sys.stderr, flush=True)
        if on_ready is not None:
            on_ready(url)
        await stop.wait()
    finally:
        for u in undo:
            u()
        local_token.withdraw(note)
        application[REFUSALS].flush()  # the refusals counted since their last record, before the log closes
        await agent.stop()
        await runner.cleanup()
        if notifier is not None:
            await notifier.stop()
        if forwarding is not None:
            forwarding.cancel()
            await asyncio.gather(forwarding, return_exceptions=True)
    return 0


def _reload(agent: Agent) -> None:
    from .model import ApiError

    with contextlib.suppress(ApiError):  # an invalid edit is an event; nothing changes
        agent.reload()
