"""Commands for devices that do not follow the book: what they taught (learned), scan, probe."""

from __future__ import annotations

import json

import click

from ..load.diagnostics import EXIT_OK, UsageError
from .base import console
from .tables import show

_STATE = click.option("--state-dir", default=".deployer", show_default=True, type=click.Path(file_okay=False),
                      help="the state directory apply keeps what devices taught in")


@click.group()
def learned() -> None:
    """Limits devices taught by their refusals (STATE/learned.json): list or forget them."""


@learned.command("list")
@_STATE
@click.option("--json", "as_json", is_flag=True, help="print the entries as JSON")
def learned_list(state_dir: str, as_json: bool) -> int:
    """What each device taught: profile, device, limits, what was seen, when."""
    from ..state import learned as store

    entries = store.load(state_dir)
    if as_json:
        click.echo(json.dumps([e.to_json() for e in entries], indent=2))
        return EXIT_OK
    out = console()
    if not entries:
        out.print(f"nothing learned in {store.path_of(state_dir)}")
        return EXIT_OK
    show(out, ["profile", "device", "limits", "seen", "when"],
         [[e.profile, e.device, e.describe_limits(), e.seen, e.when] for e in entries])
    return EXIT_OK


@learned.command("forget")
@_STATE
@click.option("--profile", "profile", metavar="PROFILE", help="only this profile (a built-in id or a file)")
@click.option("--device", "device", metavar="URL", help="only this device (with --unit)")
@click.option("--unit", type=click.IntRange(1, 247), default=1, show_default=True, help="the device's unit id")
@click.option("--all", "everything", is_flag=True, help="forget everything learned")
def learned_forget(state_dir: str, profile: str | None, device: str | None, unit: int, everything: bool) -> int:
    """Forget what devices taught: the next plan and apply use the profile's own limits again."""
    import os

    from ..profile import is_profile_path
    from ..state import learned as store
    from ..state.lock import device_key
    from ..transport.urls import BadURL, parse_url

    if not (profile or device or everything):
        raise UsageError("say what to forget: --profile PROFILE, --device URL [--unit N], or --all")
    ref = None
    if profile:
        ref = os.path.abspath(profile) if is_profile_path(profile) else profile  # as profile_ref names it
    key = None
    if device:
        try:
            key = device_key(parse_url(device).bus, unit)
        except BadURL as e:
            raise UsageError(str(e)) from None
    gone = store.forget(state_dir, profile=ref, device=key)
    out = console()
    for entry in gone:
        out.print(f"forgot {entry.describe_limits()} of {entry.device} ({entry.profile})")
    if not gone:
        out.print("nothing matched: nothing was forgotten")
    return EXIT_OK
