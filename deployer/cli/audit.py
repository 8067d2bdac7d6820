"""``deployer audit``: verify the trail, show it (as text, JSON or the printable page), forward it to syslog."""

from __future__ import annotations

import datetime
import json
from collections.abc import Callable, Mapping
from typing import Any

import click

from ..errors import EXIT_FAILED, EXIT_INVALID, EXIT_OK, UsageError
from .base import echo, safe


def _where(f: Callable[..., Any]) -> Callable[..., Any]:
    opts = [
        click.option(
            "--state-dir",
            default=".deployer",
            show_default=True,
            type=click.Path(file_okay=False),
            help="the trail is STATE/audit, unless the policy or --trail says otherwise",
        ),
        click.option(
            "--policy",
            type=click.Path(dir_okay=False),
            metavar="INVENTORY",
            help="the site's policy, for its audit settings (default: DEPLOYER_POLICY)",
        ),
        click.option("--trail", type=click.Path(file_okay=False), metavar="FOLDER", help="the trail's folder"),
    ]
    for opt in reversed(opts):
        f = opt(f)
    return f


def _folder(state_dir: str, policy_path: str | None, trail: str | None) -> tuple[str, Any]:
    from ..audit.record import folder_of
    from ..change import policy

    pol = policy.site(policy_path)
    audit = pol.audit if pol is not None else None
    return trail or folder_of(state_dir, audit.trail if audit is not None else None), audit


@click.group()
def audit() -> None:
    """The tamper-evident audit trail (docs/change-control.md)."""


@audit.command("verify")
@_where
@click.option(
    "--copy",
    type=click.Path(dir_okay=False, exists=True),
    metavar="FILE",
    help="a syslog receiver's file: every record it got must be in the trail as it was sent",
)
@click.option(
    "--head", metavar="SEQ:HASH", help="a head noted elsewhere (a printed audit page): the trail must hold it"
)
def verify(state_dir: str, policy: str | None, trail: str | None, copy: str | None, head: str | None) -> int:
    """Check the hash chain: exit 0 when every record holds, 1 naming the first one that does not (edited,
    removed, inserted, reordered, or the end cut off)."""
    from ..audit.verify import verify as check

    folder, _ = _folder(state_dir, policy, trail)
    result = check(folder, copy=copy, head=head)
    for note in result.notes:
        echo(f"note: {safe(note)}", err=True)
    if not result.holds:
        for p in result.problems:
            echo(f"{safe(folder)}/trail.jsonl: {safe(p)}")
        return EXIT_INVALID
    echo(f"{safe(folder)}/trail.jsonl: {result.records} records hold; head seq {result.last_seq} {result.last_hash}")
    return EXIT_OK


def _time(text: str | None, what: str) -> datetime.datetime | None:
    if text is None:
        return None
    from ..change.canonical import parse_time

    t = parse_time(text)
    if t is None:
        raise UsageError(f"{what} {text}: expected an ISO 8601 date or time (2026-11-22, 2026-11-22T10:15Z)")
    return t


def _chosen(
    rec: Mapping[str, Any],
    device: str | None,
    user: str | None,
    since: datetime.datetime | None,
    until: datetime.datetime | None,
) -> bool:
    from ..change.canonical import parse_time

    if device is not None and rec.get("device") != device:
        return False
    if user is not None and rec.get("user") != user:
        return False
    t = parse_time(str(rec.get("time")))
    return not ((since is not None and (t is None or t < since)) or (until is not None and (t is None or t >= until)))


@audit.command("show")
@_where
@click.option("--device", help="only records of this device")
@click.option("--user", help="only records of this user")
@click.option("--since", metavar="TIME", help="from this time on (ISO 8601, UTC unless it says otherwise)")
@click.option("--until", metavar="TIME", help="before this time")
@click.option("--json", "as_json", is_flag=True, help="the records as JSON lines")
@click.option(
    "--html",
    "html_path",
    type=click.Path(dir_okay=False),
    metavar="FILE",
    help="write the audit-trail page (prints as the record, with the trail's head)",
)
def show(
    state_dir: str,
    policy: str | None,
    trail: str | None,
    device: str | None,
    user: str | None,
    since: str | None,
    until: str | None,
    as_json: bool,
    html_path: str | None,
) -> int:
    """The trail's records, chosen by device, user and time."""
    from ..audit.trail import lines
    from ..audit.verify import verify as check

    folder, _ = _folder(state_dir, policy, trail)
    t0, t1 = _time(since, "--since"), _time(until, "--until")
    records = []
    for line in lines(folder):
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        if isinstance(rec, dict) and _chosen(rec, device, user, t0, t1):
            records.append(rec)
    if html_path:
        from ..pages.audit import audit_page
        from .base import command_line, write_page

        result = check(folder)
        verified = "every record holds" if result.holds else f"DOES NOT HOLD: {result.problems[0]}"
        filters = [(k, v) for k, v in (("device", device), ("user", user), ("since", since), ("until", until)) if v]
        write_page(
            audit_page(
                records,
                filters=filters,
                head=f"{result.last_seq}:{result.last_hash}",
                verified=verified,
                command=command_line("deployer audit show"),
            ),
            html_path,
        )
        echo(f"page: {safe(html_path)}", err=True)
    if as_json:
        for rec in records:
            echo(json.dumps(rec, ensure_ascii=False))
        return EXIT_OK
    for r in records:
        who = f"{r.get('user')}" + (f" ({r.get('role')})" if r.get("role") else "")
        echo(
            f"{r.get('seq')} {safe(r.get('time'))} {safe(r.get('event'))} {safe(who)}"
            + (f" device {safe(r['device'])}" if r.get("device") else "")
            + (f" {safe(r['result'])}" if r.get("result") else "")
            + (f" reason {safe(r['reason'])}" if r.get("reason") else "")
        )
    return EXIT_OK


@audit.command("forward")
@_where
@click.option("--syslog", metavar="URL", help="tcp://HOST:PORT or tls://HOST:PORT (default: the policy's audit.syslog)")
@click.option(
    "--ca",
    type=click.Path(dir_okay=False, exists=True),
    metavar="FILE",
    help="with tls://: the CA certificates the receiver's must chain to (default: the policy's, else the system's)",
)
@click.option("--follow", is_flag=True, help="keep forwarding new records until SIGTERM or Ctrl-C (a service)")
@click.option(
    "--settle",
    type=click.FloatRange(0.0, 60.0),
    default=1.0,
    show_default=True,
    metavar="S",
    help="seconds a sent batch waits before it counts as received (a receiver that died meanwhile "
    "closed its connection: the batch goes again)",
)
@click.option(
    "--retry-max",
    type=click.FloatRange(0.1, 3600.0),
    default=30.0,
    show_default=True,
    metavar="S",
    help="the longest wait between two attempts to reach the receiver",
)
def forward(
    state_dir: str,
    policy: str | None,
    trail: str | None,
    syslog: str | None,
    ca: str | None,
    follow: bool,
    settle: float,
    retry_max: float,
) -> int:
    """Send the trail's records to a syslog receiver (RFC 5424, octet counting), from where it left off."""
    import asyncio

    from ..audit.forward import forward as run

    folder, settings = _folder(state_dir, policy, trail)
    url = syslog or (settings.syslog if settings is not None else None)
    if url is None:
        raise UsageError("no syslog receiver: --syslog URL, or audit.syslog in the policy")
    try:
        fw = asyncio.run(
            run(
                folder,
                url,
                ca=ca or (settings.syslog_ca if settings is not None else None),
                follow=follow,
                settle=settle,
                retry_max=retry_max,
                **({"max_backlog": settings.max_backlog} if settings is not None else {}),
            )
        )
    except (OSError, TimeoutError) as e:
        echo(f"error: syslog {safe(url)}: {safe(e)}; nothing lost: the records wait in the trail", err=True)
        return EXIT_FAILED
    echo(f"{fw.sent} record(s) forwarded to {safe(url)}; backlog {fw.backlog}", err=True)
    return EXIT_OK
