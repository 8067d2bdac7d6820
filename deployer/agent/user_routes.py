"""The agent's routes about people: ``GET /v1/whoami`` (anyone), and the admin's ``/v1/users`` (docs/agent.md).

An admin adds a user (the token is in the answer, once), gives them roles, disables or enables them, gives them
a new token; each change goes through ``users.edit`` (checked, written whole, never leaving no enabled admin)
and is audited with the admin's name (access.Directory.changed). A user is never removed through the API: the
records keep naming them; disable them.
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING, Any

from aiohttp import web

from ..errors import UsageError
from . import users as people
from .access import WHO, Access, Who
from .body import BODY
from .model import ApiError

if TYPE_CHECKING:
    from .core import Agent

ACCESS: web.AppKey[Access] = web.AppKey("access", Access)


def _who(request: web.Request) -> Who:
    who: Who = request[WHO]
    return who


async def whoami(agent: Agent, request: web.Request) -> Any:
    """Who the agent takes the caller for: their name (null with a site token), roles, credential."""
    who = _who(request)
    return {**who.record(), "roles": sorted(who.roles), "mode": request.app[ACCESS].mode}


def _directory(request: web.Request) -> Any:
    d = request.app[ACCESS].directory
    if d is None:
        raise ApiError(
            "conflict",
            "this agent has no users (it runs with one token for the site); start it with --users FILE to have them",
            status=409,
        )
    return d


async def list_users(agent: Agent, request: web.Request) -> Any:
    d = _directory(request)
    users = d.current()
    if users is None:
        raise ApiError("conflict", f"the users file is invalid: {d.problem}", status=409)
    return {"users": [u.to_json() for u in sorted(users.values(), key=lambda u: u.name)]}


async def _edit(request: web.Request, change: Any) -> tuple[Any, dict[str, people.User]]:
    d = _directory(request)
    d.current()  # an edit of the file made before this one is recorded as the file's first
    d.editing += 1  # meanwhile the table stays as it was: the change is recorded as this admin's, below
    try:  # in a thread: the file's lock may wait for a command's edit, a new token's hash takes a while
        out, now = await asyncio.to_thread(people.edit, d.path, change)
    except people.NoAdminLeft as e:
        raise ApiError("refused", str(e), status=422) from None
    except UsageError as e:
        raise ApiError("usage", str(e), status=400) from None
    finally:
        d.editing -= 1
    d.changed(now, by=_who(request))
    return out, now


def _entry(body: dict[str, Any]) -> dict[str, Any]:
    """The file's entry of a user from a request's fields (the schema checked their shapes)."""
    out: dict[str, Any] = {}
    if body.get("name") is not None:
        out["name"] = body["name"]
    if body.get("roles") is not None:
        out["roles"] = list(body["roles"])
    if body.get("certificate") is not None:
        out["certificate"] = dict(body["certificate"])
    return out


async def add_user(agent: Agent, request: web.Request) -> Any:
    """``POST /v1/users`` ``{"user", "roles", "name"?, "certificate"?, "token": true}``: 201, the token once."""
    body = request.get(BODY) or {}
    name = str(body["user"])

    def change(doc: dict[str, Any]) -> str | None:
        if name in doc["users"]:
            raise UsageError(f"there is a user {name} already (a user is never made twice: the records name them)")
        entry = _entry(body)
        token = None
        if body.get("token", True):
            token, entry["token"] = people.new_token()
        doc["users"][name] = entry
        return token

    token, now = await _edit(request, change)
    return web.json_response({"user": now[name].to_json(), "token": token}, status=201)


async def change_user(agent: Agent, request: web.Request) -> Any:
    """``POST /v1/users/{name}`` ``{"roles"?, "disabled"?, "new_token"?, "name"?, "certificate"?}``."""
    body = request.get(BODY) or {}
    name = request.match_info["name"]

    def change(doc: dict[str, Any]) -> str | None:
        entry = doc["users"].get(name)
        if entry is None:
            raise UsageError(f"no user {name}")
        entry.update(_entry(body))
        if body.get("disabled") is not None:
            if body["disabled"]:
                entry["disabled"] = True
            else:
                entry.pop("disabled", None)
        token = None
        if body.get("new_token"):
            token, entry["token"] = people.new_token()
        return token

    token, now = await _edit(request, change)
    return {"user": now[name].to_json(), "token": token}
