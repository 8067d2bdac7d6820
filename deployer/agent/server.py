"""The agent's HTTP API (version 1, docs/agent.md, ``openapi.json``) on aiohttp.

``ROUTES`` is the whole API: method, path, handler. A handler gets the agent and the request and returns
what is answered as JSON (or a response of its own: the stream, /metrics). Errors are one JSON shape,
never a traceback (the ``errors`` middleware). The outward side (tokens, TLS, the page) adds middlewares
and routes here without touching the agent.
"""

from __future__ import annotations

import asyncio
import json
import os
import sys
import traceback
from collections.abc import Awaitable, Callable
from typing import Any

from aiohttp import web

from ..errors import DeployerError, InputError
from . import user_routes, views
from .access import ROLE, USER, WHO, Access, Directory, Who, access_middleware
from .body import BODY
from .body import read as read_body
from .core import Agent
from .door import Door, door_middleware
from .metrics import CONTENT_TYPE, exposition, registry
from .model import ApiError, RunState
from .refusals import Refusals
from .roles import ROUTE_ROLES, holds

Handler = Callable[[Agent, web.Request], Awaitable[Any]]
MAX_BODY = 1 << 20  # requests are small JSON documents
AGENT: web.AppKey[Agent] = web.AppKey("agent", Agent)
DOOR: web.AppKey[Door] = web.AppKey("door", Door)
REFUSALS: web.AppKey[Refusals] = web.AppKey("refusals", Refusals)


def _device(agent: Agent, request: web.Request) -> Any:
    dev = agent.devices.get(request.match_info["name"])
    if dev is None:
        raise ApiError("not-found", f"no device {request.match_info['name']!r} in this agent's inventory", status=404)
    return dev


def _run(agent: Agent, request: web.Request) -> RunState:
    run = agent.runs.live.get(request.match_info["id"])
    if run is None:
        raise ApiError(
            "not-found",
            f"no run {request.match_info['id']!r} in this agent since its start "
            "(GET /v1/runs lists earlier ones from its database)",
            status=404,
        )
    return run


async def _body(request: web.Request) -> dict[str, Any]:
    """The body as its route's schema allows it (checked before the handler runs: ``_bind``, body.py)."""
    got: dict[str, Any] = request.get(BODY) or {}
    return got


def _int(request: web.Request, key: str, default: int, low: int, high: int) -> int:
    text = request.query.get(key)
    if text is None:
        return default
    try:
        v = int(text)
    except ValueError:
        raise ApiError("usage", f"{key}: not a whole number: {text!r}", status=400) from None
    if not low <= v <= high:
        raise ApiError("usage", f"{key}: {v} is not within {low}..{high}", status=400)
    return v


# ---- handlers -----------------------------------------------------------------------------------


def _by(request: web.Request) -> dict[str, Any]:
    """Who sent the request, as runs and events record it (access.Who.record)."""
    who: Who = request[WHO]
    return who.record()


async def get_agent(agent: Agent, request: web.Request) -> Any:
    who: Who = request[WHO]
    return {
        **views.agent_json(agent),
        "auth": request.app[user_routes.ACCESS].mode,
        "you": {**who.record(), "roles": sorted(who.roles)},
    }


async def list_devices(agent: Agent, request: web.Request) -> Any:
    return {"devices": [views.device_json(agent, d) for d in agent.devices.values()]}


async def get_device(agent: Agent, request: web.Request) -> Any:
    return views.device_json(agent, _device(agent, request), full=True)


async def get_desired(agent: Agent, request: web.Request) -> Any:
    out = {}
    for d in agent.devices.values():
        full = views.device_json(agent, d, full=True)
        out[d.name] = {"recipe": full["adopted_recipe"], "values": full["adopted"]}
    return {"files_sha256": agent.files.sha256 if agent.files else None, "devices": out}


async def get_pending(agent: Agent, request: web.Request) -> Any:
    return views.pending_json(agent)


async def reload(agent: Agent, request: web.Request) -> Any:
    agent.reload()
    return views.pending_json(agent)


async def stop_agent(agent: Agent, request: web.Request) -> Any:
    """What SIGTERM does, for a service manager on Windows (which has no SIGTERM): the agent's windows end, its
    store closes, it exits 0. Behind the token like every route that changes state."""
    stop = request.app.get(STOP)
    if stop is None:  # an application served by a program of its own, not ``deployer agent``
        raise ApiError("usage", "this agent is not run by deployer agent: it has no stop", status=409)
    stop()
    return {"stopping": True}


async def check_now(agent: Agent, request: web.Request) -> Any:
    body = await _body(request)
    names = None
    if body.get("limit"):
        from ..errors import UsageError

        assert agent.files is not None
        try:
            names = [d.name for d in agent.files.inventory.select(str(body["limit"]))]
        except UsageError as e:
            raise ApiError("usage", str(e), status=400) from None
    await agent.watch.check(names)
    return {
        "devices": [views.device_json(agent, d) for d in agent.devices.values() if names is None or d.name in names]
    }


async def list_runs(agent: Agent, request: web.Request) -> Any:
    """This agent's runs since its start, then earlier ones from its database (their report files named)."""
    assert agent.store is not None
    live = [r.to_json(report=False) for r in sorted(agent.runs.live.values(), key=lambda r: -r.started)]
    seen = {r["id"] for r in live}
    return {"runs": live + [r for r in agent.store.runs(_int(request, "limit", 100, 1, 10000)) if r["id"] not in seen]}


async def start_run(agent: Agent, request: web.Request) -> Any:
    body = await _body(request)
    command = body.get("command", "apply")
    who: Who = request[WHO]
    if command == "apply":  # one who may take up an edit runs what the files say now; others what was taken up
        run = agent.commands.start_apply({**body, "by": who.record()}, take_up=holds(who.roles, "engineer"))
    elif command == "restore":
        run = agent.commands.start_restore({**body, "by": who.record()})
    else:
        raise ApiError("usage", f"command: {command!r} is not apply or restore", status=400)
    return web.json_response(run.to_json(), status=202)


async def get_run(agent: Agent, request: web.Request) -> Any:
    return _run(agent, request).to_json()


async def stream_run(agent: Agent, request: web.Request) -> web.StreamResponse:
    run = _run(agent, request)
    n = _int(request, "from", 0, 0, 1 << 30)
    resp = web.StreamResponse(headers={"Content-Type": "application/x-ndjson", "Cache-Control": "no-store"})
    await resp.prepare(request)
    while True:
        while n < len(run.events):
            await resp.write((json.dumps(run.events[n]) + "\n").encode())
            n += 1
        if run.events and run.events[-1]["event"] == "run-finished":
            break
        waiter = run.changed
        if n < len(run.events):
            continue
        try:
            await asyncio.wait_for(waiter.wait(), 15)
        except TimeoutError:
            await resp.write(b"\n")  # a keep-alive line: a client sees a dead connection, proxies keep it open
    await resp.write_eof()
    return resp


async def confirm_run(agent: Agent, request: web.Request) -> Any:
    return agent.commands.confirm(_run(agent, request).id, by=_by(request)).to_json(report=False)


async def rollback_run(agent: Agent, request: web.Request) -> Any:
    run = await agent.commands.start_rollback(_run(agent, request).id, by=_by(request))
    return web.json_response(run.to_json(), status=202)


async def confirm(agent: Agent, request: web.Request) -> Any:
    body = await _body(request)
    run = body.get("run")
    return agent.commands.confirm(None if run is None else str(run), by=_by(request)).to_json(report=False)


async def list_windows(agent: Agent, request: web.Request) -> Any:
    return {"windows": views.windows_json(agent)}


async def list_events(agent: Agent, request: web.Request) -> Any:
    assert agent.store is not None
    return {
        "events": agent.store.events(
            after=_int(request, "after", 0, 0, 1 << 62),
            limit=_int(request, "limit", 1000, 1, 10000),
            device=request.query.get("device"),
            kind=request.query.get("kind"),
        )
    }


async def get_ledger(agent: Agent, request: web.Request) -> Any:
    return agent.ledger.to_json()


async def get_status(agent: Agent, request: web.Request) -> Any:
    return views.status_json(agent)


async def approve_plan(agent: Agent, request: web.Request) -> Any:
    """``POST /v1/approvals`` (role approver): ``{"plan": PLAN, "signature": ENTRY?, "meaning": "approved"}`` ->
    the plan with the approval added (the client's signature checked, or the agent's attestation for the user),
    its digest and what it still lacks; audited either way (change/attest.py decides)."""
    from ..audit import record
    from ..change import attest
    from ..change import policy as policies

    body = await _body(request)
    user, role = request.get(USER), request.get(ROLE)
    pol = policies.load(agent.settings.inventory)
    trail = record.folder_of(agent.state_dir, pol.audit.trail if pol is not None else None)
    plan = body.get("plan")
    try:
        out = attest.approve(
            plan,
            user=user,
            entry=body.get("signature"),
            meaning=str(body.get("meaning", "approved")),
            policy=pol,
            key_folder=agent.folder,
        )
    except attest.Refused as e:
        record.append_cli(
            agent.state_dir,
            trail,
            [
                record.event(
                    "approve-refused",
                    user=user,
                    role=role,
                    via="agent",
                    result="refused",
                    detail={"why": str(e), "client": request.remote},
                )
            ],
        )
        raise ApiError("refused" if e.status in (403, 409, 422) else "usage", str(e), status=e.status) from None
    sig = out["signature"]
    record.append_cli(
        agent.state_dir,
        trail,
        [
            record.event(
                "plan-signed",
                user=sig["signer"],
                role=role,
                via="agent",
                result="ok",
                plan=out["digest"],
                detail={k: sig[k] for k in ("signer", "meaning", "time", "attested_by") if k in sig},
            )
        ],
    )
    return out


async def get_openapi(agent: Agent, request: web.Request) -> Any:
    return web.FileResponse(
        os.path.join(os.path.dirname(__file__), "openapi.json"), headers={"Content-Type": "application/json"}
    )


async def get_metrics(agent: Agent, request: web.Request) -> Any:
    return web.Response(body=exposition(request.app[METRICS]), headers={"Content-Type": CONTENT_TYPE})


ROUTES: tuple[tuple[str, str, Handler], ...] = (
    ("GET", "/v1/agent", get_agent),
    ("GET", "/v1/devices", list_devices),
    ("GET", "/v1/devices/{name}", get_device),
    ("GET", "/v1/desired", get_desired),
    ("GET", "/v1/pending", get_pending),
    ("POST", "/v1/reload", reload),
    ("POST", "/v1/stop", stop_agent),
    ("POST", "/v1/check", check_now),
    ("GET", "/v1/runs", list_runs),
    ("POST", "/v1/runs", start_run),
    ("GET", "/v1/runs/{id}", get_run),
    ("GET", "/v1/runs/{id}/stream", stream_run),
    ("POST", "/v1/runs/{id}/confirm", confirm_run),
    ("POST", "/v1/runs/{id}/rollback", rollback_run),
    ("POST", "/v1/confirm", confirm),
    ("GET", "/v1/windows", list_windows),
    ("GET", "/v1/events", list_events),
    ("GET", "/v1/ledger", get_ledger),
    ("GET", "/v1/status", get_status),
    ("POST", "/v1/approvals", approve_plan),
    ("GET", "/v1/openapi.json", get_openapi),
    ("GET", "/metrics", get_metrics),
    ("GET", "/v1/whoami", user_routes.whoami),
    ("GET", "/v1/users", user_routes.list_users),
    ("POST", "/v1/users", user_routes.add_user),
    ("POST", "/v1/users/{name}", user_routes.change_user),
)

METRICS: web.AppKey[Any] = web.AppKey("metrics", object)
STOP: web.AppKey[Callable[[], None]] = web.AppKey("stop")  # set by service.serve: ends the agent


def error_body(kind: str, message: str, exit_code: int, diagnostics: list[str] | None = None) -> dict[str, Any]:
    err: dict[str, Any] = {"kind": kind, "message": message, "exit_code": exit_code}
    if diagnostics:
        err["diagnostics"] = diagnostics
    return {"error": err}


@web.middleware
async def errors(
    request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
) -> web.StreamResponse:
    """Every refusal and failure as the one JSON error shape; never a traceback to the client."""
    try:
        return await handler(request)
    except ApiError as e:
        return web.json_response(error_body(e.kind, str(e), e.exit_code, e.diagnostics), status=e.status)
    except InputError as e:
        return web.json_response(
            error_body("input", "invalid input; nothing was sent", e.exit_code, [str(d) for d in e.diagnostics]),
            status=400,
        )
    except DeployerError as e:
        return web.json_response(
            error_body("usage" if e.exit_code == 1 else "conflict", str(e), e.exit_code),
            status=400 if e.exit_code == 1 else 409,
        )
    except web.HTTPException as e:  # aiohttp's own: 404 for an unknown path, 405, 413 too large ...
        kind = "not-found" if e.status == 404 else "usage"
        return web.json_response(error_body(kind, e.reason or str(e), 1), status=e.status)
    except asyncio.CancelledError:
        raise
    except Exception as e:  # a bug: said in the agent's log with its traceback, to the client as JSON
        traceback.print_exc(file=sys.stderr)
        return web.json_response(error_body("internal", f"internal error: {type(e).__name__}: {e}", 4), status=500)


def app(
    agent: Agent,
    *,
    token: str | None = None,
    token_kind: str = "token",
    users: Directory | None = None,
    door: Door | None = None,
) -> web.Application:
    """The agent's web application: the door (door.py) first, then who sends the request and whether their
    role lets them (access.py: one site ``token``, or the ``users`` file), then the routes."""
    refusals = Refusals(agent)
    access = Access(agent, refusals, token=token, token_kind=token_kind, directory=users)
    door = door if door is not None else Door("127.0.0.1")
    missing = [(m, p) for m, p, _ in ROUTES if (m, p) not in ROUTE_ROLES]
    if missing:  # a route nobody may use is a mistake, not a default: say it before anything starts
        raise ValueError(f"routes without a role in roles.ROUTE_ROLES: {missing}")
    middlewares = [errors, door_middleware(door, refusals), access_middleware(access)]
    application = web.Application(middlewares=middlewares, client_max_size=MAX_BODY)
    application[AGENT] = agent
    application[DOOR] = door
    application[REFUSALS] = refusals
    application[user_routes.ACCESS] = access
    application[METRICS] = registry(agent)
    application[METRICS].register(refusals)
    for method, path, handler in ROUTES:
        application.router.add_route(method, path, _bind(agent, handler))
    from .page import page  # the live page: HTML for people, not part of the versioned API

    application.router.add_get("/", page)
    return application


def _bind(agent: Agent, handler: Handler) -> Callable[[web.Request], Awaitable[web.StreamResponse]]:
    async def call(request: web.Request) -> web.StreamResponse:
        if request.method != "GET":  # every body, whether the handler reads it or not: a malformed one is a 400
            request[BODY] = await read_body(request)
        out = await handler(agent, request)
        if isinstance(out, web.StreamResponse):
            return out
        return web.json_response(out)

    call.__name__ = handler.__name__
    return call
