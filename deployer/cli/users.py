"""``deployer users``: the site agent's users and their roles (docs/agent.md#users-and-roles).

Each command changes the users file directly (``--users FILE``: to make the first admin, or on the gateway
itself; the running agent takes the change up at its next request and audits it as an edit of the file), or
asks the agent as an admin (``--agent URL`` with your credential: audited with your name). A token is printed
once, on stdout alone (what it says about it goes to stderr): only its hash is kept.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import click

from ..agent.roles import ROLES
from ..errors import EXIT_OK, UsageError
from .base import agent_options, echo, safe


def _where(f: Callable[..., Any]) -> Callable[..., Any]:
    f = click.option(
        "--users",
        "users_file",
        metavar="FILE",
        type=click.Path(dir_okay=False),
        envvar="DEPLOYER_USERS",
        help="change the users file itself (env DEPLOYER_USERS); the running agent takes it up",
    )(f)
    f = click.option(
        "--agent",
        "agent_url",
        metavar="URL",
        envvar="DEPLOYER_AGENT",
        help="ask the agent at URL, as an admin (env DEPLOYER_AGENT); audited with your name",
    )(f)
    return agent_options(f)


def _role_option(f: Callable[..., Any]) -> Callable[..., Any]:
    return click.option(
        "--role", "roles", multiple=True, required=True, type=click.Choice(ROLES), help="a role (repeatable)"
    )(f)


def _one(users_file: str | None, agent_url: str | None) -> str | None:
    """The agent's URL to ask, or None for the file (one of them; DEPLOYER_AGENT gives way to --users)."""
    if users_file is not None and agent_url is not None:
        ctx = click.get_current_context()
        if ctx.get_parameter_source("agent_url") == click.core.ParameterSource.ENVIRONMENT:
            return None
        raise UsageError("--users FILE or --agent URL: the file itself, or through the agent as an admin")
    if users_file is None and agent_url is None:
        raise UsageError("say where: --users FILE (the file itself) or --agent URL (through the agent, as an admin)")
    return agent_url


def _edit(users_file: str, change: Callable[[dict[str, Any]], Any], *, create: bool = False) -> Any:
    from ..agent import users as people

    return people.edit(users_file, change, create=create)


def _entry(doc: dict[str, Any], name: str) -> dict[str, Any]:
    entry: dict[str, Any] | None = doc["users"].get(name)
    if entry is None:
        raise UsageError(f"no user {name}")
    return entry


def _show_token(name: str, token: str | None) -> None:
    if token is not None:
        echo(f"{safe(name)}'s token, shown this once (only its hash is kept; hand it over safely):", err=True)
        echo(token)


def _certificate(cn: str | None, sha256: str | None) -> dict[str, str] | None:
    if cn and sha256:
        raise UsageError("--cert-cn or --cert-sha256: one certificate mapping per user")
    return {"cn": cn} if cn else {"sha256": sha256.replace(":", "").lower()} if sha256 else None


@click.group()
def users() -> None:
    """The site agent's users: names, roles (viewer, operator, engineer, approver, admin) and credentials.

    deployer agent --users FILE reads the file; these commands change it, directly (--users FILE) or
    through the agent as an admin (--agent URL). A user is disabled, never removed: records name them.
    """


@users.command("add")
@click.argument("name")
@_role_option
@click.option("--name", "full_name", metavar="TEXT", help="the person's printed name, as records show it")
@click.option("--cert-cn", metavar="CN", help="a TLS client certificate whose subject CN is this logs in as the user")
@click.option("--cert-sha256", metavar="HEX", help="the same, by the certificate's SHA-256 fingerprint")
@click.option("--no-token", is_flag=True, help="no token (a client certificate only)")
@_where
def add(
    name: str,
    roles: tuple[str, ...],
    full_name: str | None,
    cert_cn: str | None,
    cert_sha256: str | None,
    no_token: bool,
    users_file: str | None,
    agent_url: str | None,
) -> int:
    """Add the user NAME with --role ...; prints their token once (the file makes itself with the first user)."""
    agent_url = _one(users_file, agent_url)
    cert = _certificate(cert_cn, cert_sha256)
    if no_token and cert is None:
        raise UsageError("--no-token needs --cert-cn or --cert-sha256: the user could not log in at all")
    if agent_url is not None:
        from .agentclient import client

        out = client(agent_url).add_user(
            name, list(roles), name=full_name, certificate=cert, token=False if no_token else None
        )
        echo(f"{safe(name)}: added ({', '.join(roles)}) in the agent at {safe(agent_url)}", err=True)
        _show_token(name, out.get("token"))
        return EXIT_OK
    from ..agent import users as people

    def change(doc: dict[str, Any]) -> str | None:
        if name in doc["users"]:
            raise UsageError(f"there is a user {name} already")
        entry: dict[str, Any] = {"roles": list(roles)}
        if full_name:
            entry["name"] = full_name
        if cert is not None:
            entry["certificate"] = cert
        token = None
        if not no_token:
            token, entry["token"] = people.new_token()
        doc["users"][name] = entry
        return token

    assert users_file is not None
    token, _ = _edit(users_file, change, create=True)
    echo(f"{safe(name)}: added ({', '.join(roles)}) to {safe(users_file)}", err=True)
    _show_token(name, token)
    return EXIT_OK


@users.command("list")
@click.option("--json", "as_json", is_flag=True, help="as JSON")
@_where
def list_users(as_json: bool, users_file: str | None, agent_url: str | None) -> int:
    """The users, their roles, credentials and whether they are disabled (never a token or its hash)."""
    agent_url = _one(users_file, agent_url)
    if agent_url is not None:
        from .agentclient import client

        shown = client(agent_url).users()
    else:
        from ..agent import users as people

        assert users_file is not None
        shown = [u.to_json() for u in sorted(people.load(users_file).values(), key=lambda u: u.name)]
    if as_json:
        echo(json.dumps({"users": shown}, indent=2))
        return EXIT_OK
    for u in shown:
        creds = [
            c
            for c in (
                "token" if u["token"] else None,
                f"certificate {next(iter(u['certificate'].items()))[1]}" if u["certificate"] else None,
            )
            if c
        ]
        echo(
            f"{safe(u['user'])}{' (' + safe(u['name']) + ')' if u['name'] else ''}: {', '.join(u['roles'])}; "
            f"{', '.join(creds) or 'no credential'}{'; DISABLED' if u['disabled'] else ''}"
        )
    if not shown:
        echo("no users")
    return EXIT_OK


def _change(name: str, users_file: str | None, agent_url: str | None, what: str, **changes: Any) -> int:
    """One change to a user, in the file or through the agent; a new token printed once."""
    agent_url = _one(users_file, agent_url)
    if agent_url is not None:
        from .agentclient import client

        out = client(agent_url).change_user(name, **changes)
        token = out.get("token")
    else:
        from ..agent import users as people

        def change(doc: dict[str, Any]) -> str | None:
            entry = _entry(doc, name)
            if changes.get("roles") is not None:
                entry["roles"] = list(changes["roles"])
            if changes.get("disabled") is True:
                entry["disabled"] = True
            elif changes.get("disabled") is False:
                entry.pop("disabled", None)
            if changes.get("new_token"):
                new, entry["token"] = people.new_token()
                return new
            return None

        assert users_file is not None
        token, _ = _edit(users_file, change)
    echo(f"{safe(name)}: {what}", err=True)
    _show_token(name, token)
    return EXIT_OK


@users.command("disable")
@click.argument("name")
@_where
def disable(name: str, users_file: str | None, agent_url: str | None) -> int:
    """Disable NAME: refused at their next request, without a restart (their records stay)."""
    return _change(name, users_file, agent_url, "disabled", disabled=True)


@users.command("enable")
@click.argument("name")
@_where
def enable(name: str, users_file: str | None, agent_url: str | None) -> int:
    """Enable NAME again."""
    return _change(name, users_file, agent_url, "enabled", disabled=False)


@users.command("roles")
@click.argument("name")
@_role_option
@_where
def roles_command(name: str, roles: tuple[str, ...], users_file: str | None, agent_url: str | None) -> int:
    """Give NAME exactly these roles (--role, repeatable)."""
    return _change(name, users_file, agent_url, f"roles now {', '.join(roles)}", roles=list(roles))


@users.command("token")
@click.argument("name")
@_where
def token_command(name: str, users_file: str | None, agent_url: str | None) -> int:
    """A new token for NAME, printed once; their old one is refused from now on."""
    return _change(name, users_file, agent_url, "a new token (the old one is refused from now on)", new_token=True)


@users.command("whoami")
@click.option(
    "--agent", "agent_url", metavar="URL", envvar="DEPLOYER_AGENT", required=True, help="the agent (env DEPLOYER_AGENT)"
)
@agent_options
def whoami(agent_url: str) -> int:
    """Who the agent takes you for: your user, roles and credential."""
    from .agentclient import client

    me = client(agent_url).whoami()
    who = me.get("user") or f"no user: the holder of the site's {me.get('credential')}"
    echo(
        f"{safe(who)}: {', '.join(me.get('roles') or [])} ({safe(me.get('credential'))}; the agent has "
        f"{'users' if me.get('mode') == 'users' else 'one token for the site'})"
    )
    return EXIT_OK
