"""Command line: thin over the library API. Each command returns its exit code."""

from __future__ import annotations

import sys
from collections.abc import Sequence

import click

from .diagnostics import EXIT_INVALID, InputError, UsageError


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
