"""The agent's door: what a browser can be made to send is refused before any credential or route is looked at.

A web page in any browser on the gateway (or on a machine that reaches the agent) can send requests to it:
a "simple" cross-origin POST (a form, ``fetch`` with ``no-cors`` and ``text/plain``) needs no preflight, and
DNS rebinding makes a hostile name resolve to 127.0.0.1 so that the browser treats the agent as the hostile
page's own origin. So, on every request:

- ``Host`` must be one of the agent's own names (loopback names, the ``--listen`` host, this machine's names,
  ``--allowed-host``) or the very address the connection reached, with the agent's port: a rebound name
  is refused;
- ``Origin``, when a browser sends one, must be the agent's own origin (scheme, name or address, port);
  ``Origin: null`` (a sandboxed frame, a file) is refused, and so is ``Sec-Fetch-Site: cross-site`` or
  ``same-site``;
- a request that is not GET or HEAD must say ``Content-Type: application/json``, which no simple request
  can: a browser must ask first (a preflight), and the agent answers no preflight.

Each refusal is a 403 (415 for the content type) in the API's error shape, counted and audited.
"""

from __future__ import annotations

import contextlib
import ipaddress
import socket
import urllib.parse
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass, field

from aiohttp import web

from .refusals import Refusals, where

LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")
_READS = frozenset({"GET", "HEAD"})
_WILDCARDS = frozenset({"", "0.0.0.0", "::"})


@dataclass
class Door:
    """The agent's own names and where it listens (``bind`` sets the port the system chose)."""

    listen_host: str
    allowed: tuple[str, ...] = ()
    scheme: str = "http"
    port: int = 0
    names: frozenset[str] = field(default_factory=frozenset)

    def __post_init__(self) -> None:
        names = {*LOOPBACK_NAMES, *(a.lower().strip("[]") for a in self.allowed)}
        if self.listen_host not in _WILDCARDS:
            names.add(self.listen_host.lower().strip("[]"))
        for n in _machine_names():
            names.add(n.lower())
        self.names = frozenset(names)

    def bind(self, url: str) -> None:
        u = urllib.parse.urlsplit(url)
        self.scheme, self.port = u.scheme, int(u.port or (443 if u.scheme == "https" else 80))

    def _own(self, host: str, port: int | None, scheme: str, reached: str | None) -> bool:
        default = 443 if scheme == "https" else 80
        if (port if port is not None else default) != self.port or scheme != self.scheme:
            return False
        host = host.lower()
        if host in self.names:
            return True
        try:
            addr = ipaddress.ip_address(host)
        except ValueError:
            return False  # a name the agent does not know as its own: a rebound name, or --allowed-host it
        return addr.is_loopback or (reached is not None and _same_address(addr, reached))

    def host_ok(self, value: str, reached: str | None) -> bool:
        host, port = _split_host(value)
        return host is not None and self._own(host, port, self.scheme, reached)

    def origin_ok(self, value: str, reached: str | None) -> bool:
        try:
            u = urllib.parse.urlsplit(value)
            port = u.port
        except ValueError:
            return False
        if u.scheme not in ("http", "https") or not u.hostname or u.path not in ("", "/") or u.query:
            return False
        return self._own(u.hostname, port, u.scheme, reached)


def _split_host(value: str) -> tuple[str | None, int | None]:
    """``name:port``, ``[v6]:port``, ``name``: (host, port); (None, None) when it is none of them."""
    value = value.strip()
    if value.startswith("["):
        host, sep, rest = value[1:].partition("]")
        if not sep or (rest and not rest.startswith(":")):
            return None, None
        port_text = rest[1:] if rest else ""
    elif value.count(":") == 1:
        host, _, port_text = value.partition(":")
    elif ":" in value:
        return None, None  # an IPv6 address without its brackets is not a Host value
    else:
        host, port_text = value, ""
    if not host:
        return None, None
    if not port_text:
        return host, None
    if not port_text.isdigit() or int(port_text) > 65535:
        return None, None
    return host, int(port_text)


def _same_address(addr: ipaddress.IPv4Address | ipaddress.IPv6Address, reached: str) -> bool:
    try:
        mine = ipaddress.ip_address(reached.split("%")[0])
    except ValueError:
        return False
    if isinstance(mine, ipaddress.IPv6Address) and mine.ipv4_mapped is not None:
        mine = mine.ipv4_mapped
    return addr == mine


def _machine_names() -> Iterable[str]:
    """This machine's host name and its fully qualified name (how people on the plant network reach it)."""
    out = {socket.gethostname()}
    with contextlib.suppress(OSError):  # getfqdn swallows lookup errors itself; an odd resolver may not
        out.add(socket.getfqdn())
    return [n for n in out if n]


def _refuse(
    refusals: Refusals, request: web.Request, why: str, status: int, kind: str, message: str
) -> web.StreamResponse:
    refusals.door[why] = refusals.door.get(why, 0) + 1
    info = where(request)
    refusals.refused(
        "request-refused",
        (why, info["remote"]),
        f"refused {info['method']} {info['path']} from {info['remote']}: {message}",
        why=why,
        **info,
        host=request.headers.get("Host", "")[:200] or None,
        origin=request.headers.get("Origin", "")[:200] or None,
    )
    body = {"error": {"kind": kind, "message": message, "exit_code": 1}}
    return web.json_response(body, status=status)


def door_middleware(door: Door, refusals: Refusals) -> Callable[..., Awaitable[web.StreamResponse]]:
    @web.middleware
    async def check(
        request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        sock = request.transport.get_extra_info("sockname") if request.transport is not None else None
        reached = str(sock[0]) if sock else None
        host = request.headers.get("Host")
        if host is not None and not door.host_ok(host, reached):
            return _refuse(
                refusals,
                request,
                "host",
                403,
                "forbidden",
                f"Host {host[:100]!r} is not this agent's name (a name that merely resolves to it, as in "
                "DNS rebinding, is refused; deployer agent --allowed-host NAME adds a name)",
            )
        origin = request.headers.get("Origin")
        if origin is not None and not door.origin_ok(origin, reached):
            return _refuse(
                refusals,
                request,
                "origin",
                403,
                "forbidden",
                f"Origin {origin[:100]!r} is not this agent: a page from elsewhere cannot use it",
            )
        site = request.headers.get("Sec-Fetch-Site")
        if site is not None and site.lower() not in ("same-origin", "none"):
            return _refuse(
                refusals,
                request,
                "fetch-site",
                403,
                "forbidden",
                f"a {site[:40]} browser request: a page from elsewhere cannot use this agent",
            )
        if request.method not in _READS and request.content_type != "application/json":
            got = request.headers.get("Content-Type")
            return _refuse(
                refusals,
                request,
                "content-type",
                415,
                "usage",
                f"a {request.method} request must say Content-Type: application/json "
                f"({'it said ' + repr(got[:100]) if got else 'it said none'}), with a JSON body or none",
            )
        return await handler(request)

    return check
