"""``deployer agent``: the site agent (docs/agent.md)."""

from __future__ import annotations

import click

from .base import Duration


@click.command()
@click.argument("inventory", type=click.Path(dir_okay=False))
@click.option(
    "--state-dir",
    default=".deployer",
    show_default=True,
    type=click.Path(file_okay=False),
    help="journal, snapshots and the agent's database (agent/agent.sqlite3)",
)
@click.option(
    "--listen",
    default="127.0.0.1:8470",
    show_default=True,
    metavar="HOST:PORT",
    help="where the HTTP API listens (beyond loopback only with --token-file and TLS); port 0: any free one",
)
@click.option(
    "--users",
    "users_file",
    type=click.Path(dir_okay=False),
    metavar="FILE",
    help="named users with roles (the users file: deployer users add ...); read again when it changes",
)
@click.option(
    "--token-file",
    type=click.Path(dir_okay=False),
    metavar="FILE",
    help="one token for the site instead of users (first line of FILE; whoever has it holds every role). "
    "With neither the agent makes one in STATE/agent/token (mode 0600), says so, and listens on "
    "loopback only; this user's deployer commands find it",
)
@click.option(
    "--allowed-host",
    "allowed_hosts",
    multiple=True,
    metavar="NAME",
    help="another name clients reach the agent by (repeatable); besides its loopback names, the --listen "
    "host and this machine's names, a request whose Host or Origin names anything else is refused",
)
@click.option(
    "--tls-cert", type=click.Path(dir_okay=False), metavar="FILE", help="serve HTTPS with this certificate (PEM)"
)
@click.option("--tls-key", type=click.Path(dir_okay=False), metavar="FILE", help="the certificate's private key (PEM)")
@click.option(
    "--tls-client-ca",
    type=click.Path(dir_okay=False),
    metavar="FILE",
    help="accept client certificates this CA signed, as the users file maps them to users (needs --users)",
)
@click.option(
    "--notify",
    multiple=True,
    metavar="URL",
    help="POST every event as JSON to URL (repeatable); retried with back-off, never holding up devices",
)
@click.option(
    "--check-every",
    type=Duration(),
    default="5m",
    show_default=True,
    metavar="DURATION",
    help="read every device and compare it with the adopted desired state this often",
)
@click.option(
    "--on-drift",
    type=click.Choice(["report", "restore"]),
    default="report",
    show_default=True,
    help="restore: write the adopted values back (a run with every guarantee), --max-restores an hour",
)
@click.option(
    "--on-replace",
    type=click.Choice(["report", "restore"]),
    default="report",
    show_default=True,
    help="restore: write a replaced device's as-left values back (not per_unit parameters; same model)",
)
@click.option(
    "--bus-share",
    type=click.FloatRange(0.01, 1.0),
    default=0.2,
    show_default=True,
    metavar="FRACTION",
    help="at most this share of a bus's time goes to watching",
)
@click.option(
    "--max-restores",
    type=click.IntRange(0, 1000),
    default=3,
    show_default=True,
    metavar="N",
    help="restores per device and hour; a device that keeps drifting back is reported, not fought",
)
@click.option(
    "--first-restore-soak",
    type=Duration(),
    default="10s",
    show_default=True,
    metavar="DURATION",
    help="the first restores after the start (--on-drift/--on-replace restore) go staged: one device of each "
    "profile first, its health checks watched this long (0: read once after the write), then the "
    "rest; the first device not ending ok stops them (a restores-stopped event) until a restart",
)
@click.option(
    "--endurance-warn",
    type=click.FloatRange(0.0, 1.0),
    default=0.8,
    show_default=True,
    metavar="FRACTION",
    help="warn when a register has taken this share of its profile's endurance",
)
def agent(
    inventory: str,
    state_dir: str,
    listen: str,
    check_every: float,
    on_drift: str,
    on_replace: str,
    bus_share: float,
    max_restores: int,
    first_restore_soak: float,
    endurance_warn: float,
    token_file: str | None,
    tls_cert: str | None,
    tls_key: str | None,
    notify: tuple[str, ...],
    allowed_hosts: tuple[str, ...],
    users_file: str | None,
    tls_client_ca: str | None,
) -> int:
    """Run the site agent: own INVENTORY's devices, watch them, serve the HTTP API (until SIGTERM or Ctrl-C).

    It takes each device's lock and marks the device where every process on the machine looks, whatever
    DEPLOYER_LOCK_DIR each was given, so a plain apply to its devices is refused; run through it with
    --agent URL. --check-every, --on-drift and
    --on-replace are defaults: an inventory's agent: settings (defaults, a group, a device) win. It
    prints 'listening on URL' on stderr when ready. SIGHUP reads the files again (shown as pending; never
    written by itself; Windows has no SIGHUP: restart the agent there).

    Every request needs a credential and each route a role: --users FILE (named users: deployer users
    add ...), or --token-file FILE (one token for the site), or neither (a token of its own in
    STATE/agent/token; loopback only).
    """
    import asyncio

    from ..agent.core import Settings
    from ..agent.notify import check_url
    from ..agent.security import read_token, server_ssl
    from ..agent.service import serve

    if check_every <= 0:
        raise click.BadParameter("must be more than 0", param_hint="--check-every")
    settings = Settings(
        inventory,
        state_dir=state_dir,
        check_every=check_every,
        on_drift=on_drift,
        on_replace=on_replace,
        bus_share=bus_share,
        max_restores=max_restores,
        first_restore_soak=first_restore_soak,
        endurance_warn=endurance_warn,
    )
    if tls_client_ca is not None and users_file is None:
        raise click.UsageError("--tls-client-ca maps certificates to users: give --users FILE too")
    token = read_token(token_file) if token_file else None
    tls = server_ssl(tls_cert, tls_key, tls_client_ca)
    for url in notify:
        check_url(url)
    return asyncio.run(
        serve(settings, listen, token=token, tls=tls, notify=notify, allowed_hosts=allowed_hosts, users=users_file)
    )
