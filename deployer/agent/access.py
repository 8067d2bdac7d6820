"""Who sends a request, and whether they may: the credential, then the role its route needs (docs/agent.md).

Three modes, one of them per agent:

- ``--users FILE``: named users (users.py), each with their own token (kept as a hash) or TLS client certificate
  (``--tls-client-ca``), and roles (roles.py). The file is read again when it changes, before the request
  that finds it changed, so a user disabled is refused at once, without a restart; a file that became invalid
  refuses every request until it is fixed (the agent cannot tell anyone apart). Changes are audited.
- ``--token-file FILE``: one token for the site, whoever holds it holds every role and has no name (small sites).
- neither: the token the agent made itself (local_token.py), the same as one token.

The request then carries who it is (``WHO``; ``USER`` and ``ROLE`` for the handlers and the records: the user's
name, None with a site token, and the role the route needed), and nothing else names the user: a client does
not say who it is. A credential refused is a 401, a role missing a 403 naming it; both are counted and audited
(refusals.py).
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from aiohttp import web

from ..errors import InputError
from ..load.messages import printable
from ..load.yamlsrc import file_stamp
from . import users as people
from .audit_events import audited
from .refusals import Refusals, where
from .roles import ROLES, ROUTE_ROLES, holds, role_of

if TYPE_CHECKING:
    from .core import Agent

# what the request carries once it is let in (request[...]): who it is, their name (None: a site token), the role
USER, ROLE, WHO = "deployer.user", "deployer.role", "deployer.who"
OPEN_PATHS = frozenset({"/"})  # the live page's shell: HTML, no data; its script asks with a credential
ALL = frozenset(ROLES)
CACHE = 10_000  # tokens checked once and remembered (their digest) until the users file changes
NOBODY = "none (the route has no role in roles.ROUTE_ROLES)"  # a role no user holds


@dataclass(frozen=True)
class Who:
    """Who sent a request: a user of the users file, or the holder of the site's one token (no name)."""

    user: str | None
    roles: frozenset[str]
    credential: str  # "token" (--token-file), "agent token" (made by the agent), "user token", "certificate"
    full_name: str | None = None

    def record(self) -> dict[str, Any]:
        """What runs, events and the audit trail say of them."""
        out: dict[str, Any] = {"user": self.user, "credential": self.credential}
        if self.full_name:
            out["name"] = self.full_name
        return out

    def said(self) -> str:
        return (
            f"{self.user} ({', '.join(sorted(self.roles, key=ROLES.index))})"
            if self.user
            else f"the holder of the {self.credential}"
        )


class Refused(Exception):
    """A credential refused: why, as the 401 says it."""


class Directory:
    """The users file as the agent sees it: read at start (InputError: the agent does not start), read again
    when it changes; the changes audited (who made them: an admin through the API, else an edit of the file)."""

    def __init__(self, path: str, agent: Agent | None) -> None:
        self.path, self.agent = path, agent
        self._stamp = file_stamp(path)
        self.users: dict[str, people.User] = people.load(path)
        self.problem: str | None = None
        self._verified: dict[bytes, tuple[str, str]] = {}  # sha256(token) -> (user, its hash then)
        self._scrypt: asyncio.Semaphore | None = None
        self.editing = 0  # the API's edits under way: their change is theirs to record (``changed``), not a file's

    def current(self) -> dict[str, people.User] | None:
        """The users now (None while the file is invalid), read again when the file changed."""
        if self.editing:
            return None if self.problem else self.users
        stamp = file_stamp(self.path)
        if stamp != self._stamp:
            self._stamp = stamp
            try:
                now = people.load(self.path)
            except (InputError, OSError) as e:
                said = "; ".join(map(str, e.diagnostics)) if isinstance(e, InputError) else str(e)
                self.problem = said[:2000]
                if self.agent is not None:
                    audited(
                        self.agent,
                        "users-invalid",
                        f"the users file {self.path} is invalid: every request "
                        f"is refused until it is fixed: {said[:500]}",
                        file=self.path,
                        problem=said[:2000],
                    )
                return None
            self.problem = None
            self.changed(now, by=None)
        return None if self.problem else self.users

    def changed(self, now: dict[str, people.User], *, by: Who | None) -> None:
        """The users are ``now`` (read from the file, or written by the API as ``by``): audit what changed."""
        before, self.users = self.users, now
        self._stamp = file_stamp(self.path)
        self._verified.clear()
        if self.agent is not None:
            for kind, name, fields in changes(before, now):
                who = by.user if by is not None else None
                via = "api" if by is not None else "file"
                audited(
                    self.agent,
                    kind,
                    f"{kind.replace('-', ' ')}: {name}" + (f" by {who}" if who else " (an edit of the users file)"),
                    user=name,
                    by=who,
                    via=via,
                    **fields,
                )

    async def by_token(self, token: str) -> people.User:
        users = self.current()
        if users is None:
            raise Refused("the agent's users file is invalid: nobody can be told apart until it is fixed")
        tid = people.token_id(token)
        found = next((u for u in users.values() if tid is not None and u.token_id == tid), None)
        if found is None or found.token_hash is None:
            raise Refused("a token that is no user's")
        key = hashlib.sha256(token.encode()).digest()
        if self._verified.get(key) != (found.name, found.token_hash):
            if self._scrypt is None:  # one scrypt at a time: a flood of wrong tokens takes one core at most
                self._scrypt = asyncio.Semaphore(1)
            async with self._scrypt:
                ok = await asyncio.to_thread(people.check_token, token, found.token_hash)
            if not ok:
                raise Refused(f"a wrong token for {found.name}")
            if len(self._verified) >= CACHE:
                self._verified.clear()
            self._verified[key] = (found.name, found.token_hash)
        return found

    def by_certificate(self, cn: str | None, sha256: str) -> people.User:
        users = self.current()
        if users is None:
            raise Refused("the agent's users file is invalid: nobody can be told apart until it is fixed")
        for u in users.values():
            if u.cert_sha256 == sha256 or (cn is not None and u.cert_cn == cn):
                return u
        raise Refused(f"a client certificate (CN={cn}) that is no user's")


def changes(
    before: Mapping[str, people.User], after: Mapping[str, people.User]
) -> list[tuple[str, str, dict[str, Any]]]:
    """What changed between two tables of users, as audit records: (kind, user, fields)."""
    out: list[tuple[str, str, dict[str, Any]]] = []
    for name in sorted(before.keys() | after.keys()):
        a, b = before.get(name), after.get(name)
        if a is None and b is not None:
            out.append(("user-added", name, {"roles": sorted(b.roles), "disabled": b.disabled or None}))
            continue
        if b is None:
            out.append(("user-removed", name, {}))
            continue
        assert a is not None
        if a.disabled != b.disabled:
            out.append(("user-disabled" if b.disabled else "user-enabled", name, {}))
        if a.roles != b.roles:
            out.append(("user-roles-changed", name, {"roles": sorted(b.roles), "was": sorted(a.roles)}))
        if (a.token_id, a.token_hash) != (b.token_id, b.token_hash):
            out.append(("user-token-replaced" if b.token_hash else "user-token-removed", name, {}))
        if (a.cert_cn, a.cert_sha256) != (b.cert_cn, b.cert_sha256):
            out.append(("user-certificate-changed", name, {"certificate": b.to_json()["certificate"]}))
        if a.full_name != b.full_name:
            out.append(("user-changed", name, {"name": b.full_name, "was": a.full_name}))
    return out


class Access:
    """The agent's mode (one site token, or the users file) and its refusals."""

    def __init__(
        self,
        agent: Agent | None,
        refusals: Refusals,
        *,
        token: str | None = None,
        token_kind: str = "token",
        directory: Directory | None = None,
    ) -> None:
        if (token is None) == (directory is None):
            raise ValueError("one site token or a users file")
        self.agent, self.refusals, self.directory = agent, refusals, directory
        self._token = token.encode() if token is not None else None
        self.token_kind = token_kind

    @property
    def mode(self) -> str:
        return "users" if self.directory is not None else "token"

    async def identify(self, request: web.Request) -> Who:
        """Who the request's credential names (Refused: none, or one that names nobody now)."""
        scheme, _, given = request.headers.get("Authorization", "").partition(" ")
        given = given.strip()
        bearer = scheme.lower() == "bearer" and bool(given)
        if self._token is not None:
            if bearer and hmac.compare_digest(given.encode(), self._token):
                return Who(None, ALL, self.token_kind)
            raise Refused("a wrong token" if bearer else "no credential")
        assert self.directory is not None
        cert = _peer_certificate(request)
        user = None
        if bearer:
            user = await self.directory.by_token(given)
        if cert is not None:
            by_cert = self.directory.by_certificate(*cert)
            if user is not None and by_cert.name != user.name:
                raise Refused(f"the client certificate is {by_cert.name}'s and the token {user.name}'s")
            user = user or by_cert
        if user is None:
            raise Refused("a wrong token" if scheme else "no credential")
        if user.disabled:
            raise Refused(f"{user.name} is disabled")
        return Who(user.name, user.roles, "user token" if bearer else "certificate", user.full_name)


def _peer_certificate(request: web.Request) -> tuple[str | None, str] | None:
    """The verified client certificate of a TLS connection: (subject CN, SHA-256 of its DER), or None."""
    transport = request.transport
    ssl_object = transport.get_extra_info("ssl_object") if transport is not None else None
    if ssl_object is None:
        return None
    der = ssl_object.getpeercert(binary_form=True)
    if not der:
        return None
    subject = (ssl_object.getpeercert() or {}).get("subject", ())
    cn = next((str(v) for rdn in subject for k, v in rdn if k == "commonName"), None)
    return cn, hashlib.sha256(der).hexdigest()


def needed_role(request: web.Request) -> str | None:
    """The role the request's route needs: the route that will run when one matched, else the table's pattern."""
    resource = request.match_info.route.resource
    if resource is not None:
        # a route without a role is nobody's (server.app does not even start with one)
        return ROUTE_ROLES.get((request.method, resource.canonical), NOBODY)
    return role_of(request.method, request.path)


def _refuse(status: int, kind: str, message: str) -> web.StreamResponse:
    body = {"error": {"kind": kind, "exit_code": 1, "message": message}}
    headers = {"WWW-Authenticate": 'Bearer realm="deployer"'} if status == 401 else None
    return web.json_response(body, status=status, headers=headers)


def access_middleware(access: Access) -> Callable[..., Awaitable[web.StreamResponse]]:
    refusals = access.refusals

    @web.middleware
    async def check(
        request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        if request.method == "GET" and request.path in OPEN_PATHS:
            return await handler(request)
        info = where(request)
        try:
            who = await access.identify(request)
        except Refused as e:
            refusals.unauthorized += 1
            refusals.refused(
                "login-refused",
                (info["remote"],),
                f"refused {info['method']} {info['path']} from {info['remote']}: {e}",
                why=str(e),
                **info,
            )
            hint = (
                "this agent needs your token: Authorization: Bearer TOKEN (deployer: --agent-token-file FILE "
                "or DEPLOYER_AGENT_TOKEN; deployer users token NAME makes a new one)"
                if access.mode == "users"
                else "this agent needs its token: Authorization: Bearer TOKEN (deployer: --agent-token-file "
                "FILE or DEPLOYER_AGENT_TOKEN; an agent given no --token-file keeps it in STATE/agent/token)"
            )
            return _refuse(401, "unauthorized", f"{e}: {hint}" if str(e) != "no credential" else hint)
        role = needed_role(request)
        if role is not None and not holds(who.roles, role):
            refusals.forbidden[role] = refusals.forbidden.get(role, 0) + 1
            refusals.refused(
                "access-refused",
                (str(who.user), request.method, info["path"]),
                f"refused {info['method']} {info['path']} to {who.said()}: it needs the role {role}",
                user=who.user,
                roles=sorted(who.roles),
                needed=role,
                **info,
            )
            return _refuse(
                403,
                "forbidden",
                f"{printable(who.user or '?')} may not {request.method} "
                f"{info['path']}: that needs the role {role}, which {who.user} does not hold "
                f"(they hold {', '.join(sorted(who.roles, key=ROLES.index))})",
            )
        request[WHO], request[USER], request[ROLE] = who, who.user, role
        return await handler(request)

    return check
