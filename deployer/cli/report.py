"""``deployer report``: an earlier run's report, as the text the run printed at its end, or as a page."""

from __future__ import annotations

import click

from ..errors import EXIT_OK
from .base import cli


@cli.command()
@click.argument("report_file", metavar="RUN.json", type=click.Path(dir_okay=False))
@click.option(
    "--html",
    "html_path",
    type=click.Path(dir_okay=False),
    metavar="FILE",
    help="write the report as one self-contained HTML page (sortable, filterable; it prints as the "
    "commissioning record: the outcome and one sign-off block, then as found / as left per device)",
)
@click.option(
    "--meta",
    multiple=True,
    metavar="KEY=VALUE",
    help="with --html: a line of the record's page header (site=..., project=..., customer=..., line=...)",
)
@click.option(
    "--compact",
    is_flag=True,
    help="with --html: one table row per device, parameters only for devices that changed or did not end ok",
)
@click.option(
    "--profile",
    "profile_refs",
    multiple=True,
    metavar="ID|FILE",
    help="show the values of this profile's devices with it (a report of an older version does not "
    "describe its profiles); repeatable",
)
def report(
    report_file: str, html_path: str | None, meta: tuple[str, ...], compact: bool, profile_refs: tuple[str, ...]
) -> int:
    """Show a run's report (apply --report, rollback --report, a fleet's live report file).

    Values are shown in engineering units as the report describes its profiles (or with a --profile
    given here), else as register words; a file the report names is never opened. Reports of older
    versions show what they have. Exit 0; 1 if RUN.json is not a report (or not valid: FILE:LINE:COL).
    """
    from ..api import load_report as read_report
    from .base import console, safe, write_page
    from .outcome import print_report
    from .progress import fleet_summary

    run = read_report(report_file, profile_refs)
    out = console()
    info = run.run or {}
    if info.get("command"):
        out.print(f"command: {safe(info['command'])}", soft_wrap=True)
    who = ", ".join(f"{k} {safe(info[k])}" for k in ("user", "host", "started", "version") if info.get(k))
    if who:
        out.print(who, soft_wrap=True)
    if len(run.devices) > 1:
        print_report(run, out, only_not_ok=True)
        fleet_summary(run, out)
    else:
        print_report(run, out)
    if html_path:
        from ..pages import run_page
        from .base import record_meta

        write_page(run_page(run, meta=record_meta(None, meta), compact=compact), html_path)
        console(stderr=True).print(f"page: {safe(html_path)}")
    return EXIT_OK
