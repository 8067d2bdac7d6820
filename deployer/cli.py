"""Command line: thin over the library API. Each command returns its exit code."""

from __future__ import annotations

import sys
from collections.abc import Sequence

import click
from rich.console import Console
from rich.table import Table

from .diagnostics import EXIT_INVALID, EXIT_OK, Diagnostic, InputError, UsageError


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="modbus-deployer")
def cli() -> None:
    """Deploy parameter sets (recipes) to Modbus devices: plan, apply, verify, report."""


def report_input_error(err: InputError) -> None:
    for d in err.diagnostics:
        click.echo(str(d), err=True)
    n = len(err.diagnostics)
    click.echo(f"{n} error{'s' if n != 1 else ''}; nothing was sent to any device", err=True)


# --- validate, profiles (foundation) ---------------------------------------------------


def console() -> Console:
    """stdout console; wide when not a terminal so piped tables are not squeezed."""
    return Console(width=None if sys.stdout.isatty() else 200, highlight=False)


def _n(count: int, noun: str) -> str:
    return f"{count} {noun}{'' if count == 1 else 's'}"


def _kind(data: object) -> str | None:
    if not isinstance(data, dict):
        return None
    if data.get("schema") == "deployer.plan/1":
        return "plan"
    if "recipe" in data:
        return "recipe"
    if "devices" in data:
        return "inventory"
    if "profile" in data and ("parameters" in data or "tables" in data):
        return "profile"
    return None


def validate_file(path: str) -> str:
    """Check one file of any kind; returns a one-line summary or raises InputError."""
    from . import yamlsrc
    from .fleet import load_inventory
    from .profile import load_profile, resolve_profile
    from .recipe import load_recipe

    data, src = yamlsrc.load(path)
    kind = _kind(data)
    if kind == "profile":
        prof = load_profile(path)
        return f"profile {prof.id}: {_n(len(prof.parameters), 'parameter')}"
    if kind == "recipe":
        rec = load_recipe(path)
        return f"recipe {rec.name}: {_n(len(rec.desired), 'parameter')} for profile {rec.profile.id}"
    if kind == "inventory":
        inv = load_inventory(path)
        errors: list[Diagnostic] = []
        for dev in inv.devices:
            if dev.profile is not None:
                try:
                    resolve_profile(dev.profile)
                except UsageError as e:
                    errors.append(src.error(("devices", dev.name, "profile"), str(e)))
                except InputError as e:
                    errors.extend(e.diagnostics)
        if errors:
            raise InputError(errors)
        return f"inventory: {_n(len(inv.devices), 'device')}"
    if kind == "plan":
        from .planner import plan_from_json

        plan = plan_from_json(data, path)
        return f"plan: {len(plan.writes)} write requests for {plan.device.profile}"
    raise InputError([src.error((), "cannot tell what this file is: a profile has 'profile' and 'parameters', "
                                     "a recipe has 'recipe', an inventory has 'devices'")])


@cli.command()
@click.argument("files", nargs=-1, required=True, type=click.Path(dir_okay=False))
def validate(files: tuple[str, ...]) -> int:
    """Check profiles, recipes and inventories (and saved plans); exit 1 if any is invalid."""
    bad = 0
    for f in files:
        try:
            click.echo(f"{f}: ok ({validate_file(f)})")
        except InputError as e:
            bad += 1
            for d in e.diagnostics:
                click.echo(str(d), err=True)
    if bad:
        click.echo(f"{bad} of {len(files)} file{'s' if len(files) != 1 else ''} invalid", err=True)
        return EXIT_INVALID
    return EXIT_OK


@cli.group()
def profiles() -> None:
    """The built-in device profiles."""


@profiles.command("list")
def profiles_list() -> int:
    """List the built-in profiles."""
    from .profile import builtin_profile, builtin_profile_ids

    table = Table("profile", "parameters", "description", box=None)
    for pid in builtin_profile_ids():
        prof = builtin_profile(pid)
        first = prof.description.split(". ")[0].rstrip(".")
        table.add_row(pid, str(len(prof.parameters)), first)
    console().print(table)
    return EXIT_OK


@profiles.command("show")
@click.argument("profile")
def profiles_show(profile: str) -> int:
    """Show a profile's parameters in engineering units (a built-in id or a file)."""
    from .codec import format_decimal
    from .profile import resolve_profile

    prof = resolve_profile(profile)
    out = console()
    out.print(f"[bold]{prof.id}[/bold]: {prof.description}")
    lim = prof.limits
    out.print(f"addressing {prof.addressing}, word order {prof.word_order}; up to {lim.write_registers} registers "
              f"per write (FC{lim.write_function:02d}), {lim.read_registers} per read")
    table = Table("parameter", "address", "type", "unit", "resolution", "range", "access", "default",
                  "description", box=None)
    for p in prof.parameters:
        rng = "" if p.min is None and p.max is None else (
            f"{'' if p.min is None else format_decimal(p.min)}..{'' if p.max is None else format_decimal(p.max)}")
        if p.values:
            rng = ", ".join(f"{label}={raw}" for label, raw in p.values)
        default = "" if p.default is None else format_decimal(p.default)
        table.add_row(p.name, f"0x{p.address:04X} ({p.address})", p.type, p.unit or "",
                      format_decimal(p.scale), rng, p.access, default, p.description)
    out.print(table)
    return EXIT_OK

# --- plan (planner) ---------------------------------------------------------------------

# --- simulate (simulator) ---------------------------------------------------------------

# --- apply, diff, pull, rollback, demo (executor) ---------------------------------------


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point: map every user error to its exit code, never a traceback."""
    try:
        rv = cli.main(args=list(argv) if argv is not None else None, standalone_mode=False)
    except click.exceptions.UsageError as e:  # DESIGN.md: usage errors exit 1, not click's 2
        e.show()
        sys.exit(EXIT_INVALID)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(EXIT_INVALID)
    except click.exceptions.ClickException as e:
        e.show()
        sys.exit(EXIT_INVALID)
    except InputError as e:
        report_input_error(e)
        sys.exit(EXIT_INVALID)
    except UsageError as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(EXIT_INVALID)
    except KeyboardInterrupt:
        click.echo("interrupted", err=True)
        sys.exit(130)
    sys.exit(rv if isinstance(rv, int) else 0)


if __name__ == "__main__":
    main()
