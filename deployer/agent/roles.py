"""Who may do what through the agent: the roles, and the one role each route needs (docs/agent.md).

Roles are not ranked: each is a set of routes. Every role may read (the viewer's routes): an operator or an
approver must see what they act on. No other role contains another: an admin manages users and the policy and
cannot, by that role, run, approve or take up anything (separation of duties); a person who does both holds
both roles.

The table is checked before the route runs and before the router says whether the route exists (an unknown
path answers 404 to someone who holds the role its pattern needs), so a route added without a role here is
refused to everyone (``server.app`` will not even start with one).
"""

from __future__ import annotations

from collections.abc import Iterable

ROLES = ("viewer", "operator", "engineer", "approver", "admin")

ABOUT = {
    "viewer": "read the agent's state, its events and metrics, the live page",
    "operator": "start runs (the files as an engineer took them up, or the adopted state back), confirm, roll back",
    "engineer": "take up an edit of the files: the plan of what would change, which runs then adopt",
    "approver": "approve (or review) a plan",
    "admin": "users and policy; stop the agent",
}

# (method, route pattern as aiohttp writes it) -> the role it needs
ROUTE_ROLES: dict[tuple[str, str], str] = {
    ("GET", "/v1/agent"): "viewer",
    ("GET", "/v1/whoami"): "viewer",
    ("GET", "/v1/devices"): "viewer",
    ("GET", "/v1/devices/{name}"): "viewer",
    ("GET", "/v1/desired"): "viewer",
    ("GET", "/v1/pending"): "viewer",
    ("POST", "/v1/check"): "viewer",  # reads the devices now; writes nothing
    ("GET", "/v1/runs"): "viewer",
    ("GET", "/v1/runs/{id}"): "viewer",
    ("GET", "/v1/runs/{id}/stream"): "viewer",
    ("GET", "/v1/windows"): "viewer",
    ("GET", "/v1/events"): "viewer",
    ("GET", "/v1/ledger"): "viewer",
    ("GET", "/v1/status"): "viewer",
    ("GET", "/v1/openapi.json"): "viewer",
    ("GET", "/metrics"): "viewer",
    ("POST", "/v1/reload"): "engineer",
    ("POST", "/v1/runs"): "operator",
    ("POST", "/v1/runs/{id}/confirm"): "operator",
    ("POST", "/v1/runs/{id}/rollback"): "operator",
    ("POST", "/v1/confirm"): "operator",
    ("POST", "/v1/approvals"): "approver",  # change control's route (docs/change-control.md)
    ("POST", "/v1/stop"): "admin",  # ends the agent (a Windows service manager's SIGTERM): its devices go unheld
    ("GET", "/v1/users"): "admin",
    ("POST", "/v1/users"): "admin",
    ("POST", "/v1/users/{name}"): "admin",
}


def holds(roles: Iterable[str], needed: str) -> bool:
    """Whether a user of ``roles`` may use a route that needs ``needed`` (any role reads)."""
    have = set(roles)
    return needed in have or (needed == "viewer" and bool(have))


def role_of(method: str, path: str) -> str | None:
    """The role the pattern matching ``path`` needs (None: no route of the table looks like it)."""
    found = ROUTE_ROLES.get((method, path))
    if found is not None:
        return found
    parts = path.split("/")
    for (m, pattern), role in ROUTE_ROLES.items():
        want = pattern.split("/")
        if (
            m == method
            and len(want) == len(parts)
            and all(w == p or (w.startswith("{") and w.endswith("}") and p) for w, p in zip(want, parts, strict=True))
        ):
            return role
    return None
