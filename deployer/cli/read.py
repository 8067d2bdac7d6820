"""diff and pull: the commands that only read devices."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import click

from ..errors import EXIT_CHANGES, EXIT_OK, EXIT_UNREACHABLE, UsageError
from .base import (
    RETRIES,
    TIMEOUT,
    _fleet,
    _n,
    _output,
    _target,
    _unreachable,
    agent_option,
    console,
    describe,
    device_options,
    echo,
    fleet_option,
    limit_option,
    parallel_option,
    read_device,
    recipe_or_inventory,
    safe,
)
from .tables import Cell, show

if TYPE_CHECKING:
    from ..api import Drift, Profile, Recipe
    from ..api.commands import Job


@click.command()
@click.argument("recipe", required=False, type=click.Path(dir_okay=False))
@device_options
@click.option("--json", "as_json", is_flag=True, help="print the differences as JSON")
@fleet_option
@limit_option
@parallel_option
@click.option(
    "--per-device",
    is_flag=True,
    help="with --inventory: one row per device and parameter (default: devices with identical drift together)",
)
@click.option("--matrix", is_flag=True, help="with --inventory: a table of parameters x drifted devices")
@click.option(
    "--html",
    "html_path",
    type=click.Path(dir_okay=False),
    metavar="FILE",
    help="with --inventory: also write the parameters x devices matrix as one self-contained HTML page "
    "(drifted cells marked, filterable)",
)
@click.option(
    "--defaults",
    is_flag=True,
    help="compare the device with its factory settings (the profile's "
    "defaults) instead of a recipe: every readable parameter that has a default",
)
@click.option("--profile", "profile_ref", metavar="ID|FILE", help="with --defaults and no RECIPE: the device's profile")
@agent_option
def diff(
    recipe: str | None,
    device: str | None,
    unit: int | None,
    timeout: float | None,
    retries: int | None,
    as_json: bool,
    inventory: str | None,
    limit: str | None,
    parallel: int,
    per_device: bool,
    matrix: bool,
    html_path: str | None,
    defaults: bool,
    profile_ref: str | None,
    agent_url: str | None,
) -> int:
    """Drift check: exit 2 when the device (any device of --inventory) differs from the recipe, 0 when it matches.

    With --inventory and no RECIPE, each device against its recipe from the inventory. With --defaults,
    the device against its factory settings: exit 2 when some parameter differs from its default. With
    --agent URL: the agent checks its devices now against its adopted state."""
    if agent_url:
        from . import agentclient

        if recipe or device or inventory or defaults:
            raise UsageError(
                "with --agent, diff compares the agent's devices with its adopted state: no RECIPE, "
                "--device, --inventory or --defaults"
            )
        return agentclient.diff(agent_url, limit=limit, as_json=as_json)
    from ..api.commands import diff_values

    if defaults:
        if inventory or limit or per_device or matrix or html_path:
            raise UsageError("--defaults compares one device: use it with RECIPE or --profile, and --device")
        return diff_defaults(recipe, profile_ref, device, unit, timeout, retries, as_json)
    if profile_ref:
        raise UsageError("--profile goes with --defaults (a recipe names its own profile)")
    maybe = recipe_or_inventory(recipe, inventory)
    if inventory:
        if device:
            raise UsageError("--device and --inventory exclude each other")
        if per_device and matrix:
            raise UsageError("--per-device and --matrix exclude each other")
        return diff_fleet(
            maybe,
            _fleet(maybe, inventory, limit, timeout, retries, unit),
            parallel=parallel,
            as_json=as_json,
            view="per-device" if per_device else "matrix" if matrix else "grouped",
            html_path=html_path,
        )
    given = [
        o
        for o, v in (("--limit", limit), ("--per-device", per_device), ("--matrix", matrix), ("--html", html_path))
        if v
    ]
    if given:
        raise UsageError(f"{given[0]} needs --inventory")
    assert maybe is not None
    rec = maybe
    url, u = _target(rec, device, unit, timeout, retries, required=True)
    assert url is not None
    current = read_device(rec.profile, [d.name for d in rec.desired], url, u)
    if current is None:
        return EXIT_UNREACHABLE
    rows = diff_values(rec, current)
    drift = [r for r in rows if r.device_raw is not None]
    if as_json:
        echo(
            json.dumps(
                {"recipe": recipe, "device": describe(url), "unit": u, "drift": [r.to_json() for r in rows]}, indent=2
            )
        )
    elif rows:
        show(console(), ["parameter", "recipe", "device value", ""], drift_rows(rows))
        console().print(
            f"{len(drift)} of {_n(len(rec.desired), 'parameter')} "
            f"differ{'s' if len(drift) == 1 else ''} from the recipe"
        )
    else:
        console().print(
            "no drift: the device holds "
            + ("the recipe's value" if len(rec.desired) == 1 else f"all {len(rec.desired)} values of the recipe")
        )
    return EXIT_CHANGES if drift else EXIT_OK


def diff_defaults(
    recipe: str | None,
    profile_ref: str | None,
    device: str | None,
    unit: int | None,
    timeout: float | None,
    retries: int | None,
    as_json: bool,
) -> int:
    """diff --defaults: what differs from the factory settings; exit 2 when something does."""
    from ..api import load_profile as resolve_profile
    from ..api import load_recipe
    from ..api.commands import defaults_diff, device_url

    if recipe and profile_ref:
        raise UsageError("pass RECIPE or --profile, not both (a recipe names its profile)")
    if recipe:
        rec = load_recipe(recipe)
        prof = rec.profile
        url, u = _target(rec, device, unit, timeout, retries, required=True)
    elif profile_ref and device:
        prof = resolve_profile(profile_ref)
        url, u = device_url(device, timeout=timeout, retries=retries), unit if unit is not None else 1
    else:
        raise UsageError("diff --defaults needs RECIPE, or --profile ID|FILE and --device URL")
    assert url is not None
    names = [p.name for p in prof.parameters if p.readable and p.default is not None and not p.action]
    current = read_device(prof, names, url, u)
    if current is None:
        return EXIT_UNREACHABLE
    differs, _ = defaults_diff(prof, current)
    no_default = [p.name for p in prof.parameters if p.readable and p.default is None and not p.action]
    if as_json:
        echo(
            json.dumps(
                {
                    "profile": prof.id,
                    "device": describe(url),
                    "unit": u,
                    "differs": [d.to_json() for d in differs],
                    "compared": len(names),
                    "no_default": no_default,
                },
                indent=2,
            )
        )
    else:
        out = console()
        if differs:
            show(
                out,
                ["parameter", "factory default", "device value"],
                [[d.name, d.default, (d.device, "yellow")] for d in differs],
            )
        out.print(
            f"{len(differs)} of {_n(len(names), 'parameter')} with a factory default differ from it"
            if differs
            else f"factory settings: all {_n(len(names), 'parameter')} with a default hold it"
        )
        if no_default:
            out.print(f"not compared: {_n(len(no_default), 'parameter')} without a default in profile {safe(prof.id)}")
    return EXIT_CHANGES if differs else EXIT_OK


def drift_rows(rows: Sequence[Drift], device: str | None = None) -> list[list[Cell]]:
    """parameter, recipe, device value, status (with the device's name first for fleets)."""
    return [
        [
            *([device] if device is not None else []),
            r.name,
            r.desired,
            r.device or "-",
            ("drift", "yellow") if r.device_raw is not None else "not readable",
        ]
        for r in rows
    ]


def diff_fleet(
    rec: Recipe | None,
    jobs: Sequence[Job],
    *,
    parallel: int,
    as_json: bool,
    view: str = "grouped",
    html_path: str | None = None,
) -> int:
    """The fleet's drift: devices with identical drift together (``view`` ``per-device``: a row per device
    and parameter; ``matrix``: parameters x drifted devices); exit 2 naming every drifted device, 3 if
    any could not be read."""
    from ..api.commands import diff_values, read_jobs
    from .progress import read_fleet  # rich: only fleets pay for importing it

    values = read_fleet(read_jobs(jobs), parallel)
    rows = {j.name: diff_values(j.recipe, v) for j in jobs if not isinstance(v := values[j.name], Exception)}
    drifted = [n for n, r in rows.items() if any(d.device_raw is not None for d in r)]
    down = _unreachable(values)
    if html_path:
        _drift_page(jobs, values, rows, html_path)
    if as_json:
        echo(
            json.dumps(
                {
                    "recipe": rec.path if rec else None,
                    "devices": [
                        {
                            "name": j.name,
                            "url": describe(j.url),
                            "unit": j.unit,
                            "drift": [d.to_json() for d in rows[j.name]],
                        }
                        if j.name in rows
                        else {"name": j.name, "url": describe(j.url), "unit": j.unit, "error": str(values[j.name])}
                        for j in jobs
                    ],
                    "drifted": drifted,
                    "unreachable": down,
                },
                indent=2,
            )
        )
    else:
        from .summary import drift_changes, drift_matrix, print_groups

        out = console()
        if view == "per-device":
            show(
                out,
                ["device", "parameter", "recipe", "device value", ""],
                [row for j in jobs for row in drift_rows(rows.get(j.name, []), j.name)],
            )
        elif view == "matrix":
            headers, body = drift_matrix(
                rows, {j.name: {d.name: d.text for d in j.recipe.desired} for j in jobs if j.name in rows}
            )
            show(out, headers, body)
        else:
            print_groups(out, {n: drift_changes(r) for n, r in rows.items()}, [], same="as the recipe says")
        out.print(
            f"drift on {len(drifted)} of {_n(len(jobs), 'device')}"
            + (f": {', '.join(safe(n) for n in drifted)}" if drifted else "")
            + (f"; {len(down)} unreachable: {', '.join(safe(n) for n in down)}" if down else "")
        )
    if down:
        return EXIT_UNREACHABLE
    return EXIT_CHANGES if drifted else EXIT_OK


@click.command()
@click.option(
    "--profile",
    "profile_ref",
    metavar="ID|FILE",
    help="the device's profile (with --inventory: for devices whose entry names neither a profile nor "
    "a recipe; otherwise each device's recipe's profile)",
)
@click.option("--device", metavar="URL")
@click.option("--unit", type=click.IntRange(1, 247), help="unit id (default 1, or the inventory's)")
@click.option("--timeout", type=TIMEOUT)
@click.option("--retries", type=RETRIES)
@click.option(
    "-o",
    "--output",
    type=click.Path(),
    help="write the recipe here (default: stdout); with --inventory a folder: one NAME.yaml per device",
)
@click.option("--name", help="the recipe's name (default: pulled-PROFILE)")
@click.option(
    "--html",
    "html_path",
    type=click.Path(dir_okay=False),
    metavar="FILE",
    help="also write what each device holds as one self-contained HTML page: the as-found half of the "
    "commissioning record (prints a section per device with a signature line)",
)
@click.option(
    "--non-default",
    is_flag=True,
    help="write only the values that differ from the factory settings "
    "(the profile's defaults; parameters without a default are kept)",
)
@fleet_option
@limit_option
@parallel_option
def pull(
    profile_ref: str | None,
    device: str | None,
    unit: int | None,
    timeout: float | None,
    retries: int | None,
    output: str | None,
    name: str | None,
    html_path: str | None,
    non_default: bool,
    inventory: str | None,
    limit: str | None,
    parallel: int,
) -> int:
    """Read every writable parameter of a device into a recipe that applies back as a no-op."""
    from ..api import load_profile as resolve_profile
    from ..api.commands import check_output, device_url, out_of_range, pull_names, pulled_recipe

    if inventory:
        if device or name:
            raise UsageError("with --inventory, --device and --name do not apply (one recipe per device)")
        if not output:
            raise UsageError("with --inventory, pass -o DIR: one recipe per device goes there")
        return pull_fleet(
            inventory,
            limit,
            profile_ref,
            output,
            timeout=timeout,
            retries=retries,
            unit=unit,
            parallel=parallel,
            html_path=html_path,
            non_default=non_default,
        )
    if limit:
        raise UsageError("--limit needs --inventory")
    if not profile_ref or not device:
        raise UsageError("pass --profile ID|FILE and --device URL (or --inventory FILE -o DIR)")
    prof = resolve_profile(profile_ref)
    url = device_url(device, timeout=timeout, retries=retries)
    u = unit if unit is not None else 1
    if output:
        check_output(output, what="the recipe")  # before reading the device: a FIFO, a link, a folder
    current = read_device(prof, pull_names(prof), url, u)
    if current is None:
        return EXIT_UNREACHABLE
    if html_path:
        _as_found_page([(name or f"pulled-{prof.id}", describe(url), u, prof, current)], html_path)
    comment = _pulled_from(describe(url), u)
    if non_default:
        current, comment = _non_default(prof, current, comment)
    text = pulled_recipe(
        prof, current, name=name or f"pulled-{prof.id}", url=describe(url), unit=u, comment=comment, relative_to=output
    )
    # a value outside the profile's range is kept as a comment, not set: count only what the recipe sets
    left = out_of_range(prof, current)
    said = f"{_n(len(current) - len(left), 'parameter')} written to {output}" + (
        f"; {len(left)} outside the profile's range kept as comments: {', '.join(left)}" if left else ""
    )
    _output(text, output, said, replace=True)
    return EXIT_OK


def _pulled_from(url: str, unit: int) -> str:
    return f"Pulled from {url} unit {unit} at {time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}"


def _non_default(
    prof: Profile,
    current: dict[str, tuple[int, ...]],
    comment: str,
) -> tuple[dict[str, tuple[int, ...]], str]:
    """pull --non-default: the values that are not factory settings, and a comment saying what was left out."""
    from ..api.commands import non_default

    kept = non_default(prof, current)
    unknown = sum(1 for n in kept if prof.parameter(n).default is None)
    comment += (
        f"\nOnly the values that differ from the factory defaults of profile {prof.id}: "
        f"{_n(len(current) - len(kept), 'parameter')} at the default left out"
        + (f"; {_n(unknown, 'parameter')} without a default in the profile kept" if unknown else "")
    )
    return kept, comment


def pull_fleet(
    inventory: str,
    limit: str | None,
    profile_ref: str | None,
    folder: str,
    *,
    timeout: float | None,
    retries: int | None,
    unit: int | None,
    parallel: int,
    html_path: str | None = None,
    non_default: bool = False,
) -> int:
    """DIR/NAME.yaml per device, each with the device's profile; exit 3 if any device could not be read."""
    from ..api.commands import check_folder, pull_jobs, pulled_recipe
    from ..api.commands import write_output as write_atomic

    jobs = pull_jobs(inventory, limit=limit, profile=profile_ref, timeout=timeout, retries=retries, unit=unit)
    check_folder(folder, what=f"recipes into {folder}")
    from .progress import read_fleet  # rich: only fleets pay for importing it

    values = read_fleet(jobs, parallel)
    written = 0
    for j in jobs:
        cur = values[j.name]
        if isinstance(cur, Exception):
            continue
        path = os.path.join(folder, f"{_safe(j.name)}.yaml")
        comment = _pulled_from(describe(j.url), j.unit)
        if non_default:
            cur, comment = _non_default(j.profile, dict(cur), comment)
        text = pulled_recipe(
            j.profile, cur, name=f"pulled-{j.name}", url=describe(j.url), unit=j.unit, comment=comment, relative_to=path
        )
        write_atomic(path, text)
        written += 1
    down = _unreachable(values)
    if html_path:
        from .base import record_meta

        _as_found_page(
            [(j.name, describe(j.url), j.unit, j.profile, values[j.name]) for j in jobs],
            html_path,
            record_meta(inventory),
        )
    echo(
        f"{_n(written, 'recipe')} written to {safe(folder)}"
        + (f"; {len(down)} unreachable: {', '.join(safe(n) for n in down)}" if down else ""),
        err=True,
    )
    return EXIT_UNREACHABLE if down else EXIT_OK


def _safe(name: str) -> str:
    from ..api.commands import file_name

    return file_name(name)  # the same name on every system: no CON.yaml, no 300-character name


def _as_found_page(
    devices: Sequence[tuple[str, str, int, Profile, object]], path: str, meta: Sequence[tuple[str, str]] = ()
) -> None:
    """``pull --html``: per device its values (engineering text and registers), or why it could not be read."""
    from ..api.commands import run_info
    from ..pages import as_found_page
    from .base import command_line, write_page

    entries = []
    for name, url, unit, prof, cur in devices:
        entry: dict[str, object] = {"name": name, "url": url, "unit": unit, "profile": prof.id, "sha": prof.digest}
        if isinstance(cur, dict):
            entry["values"] = [
                (n, prof.parameter(n).show_registers(tuple(v)), tuple(v), prof.parameter(n).manual)
                for n, v in cur.items()
            ]
        else:
            entry["error"] = str(cur)
        entries.append(entry)
    write_page(as_found_page(entries, run=run_info(command_line(), time.time()), meta=meta), path)
    echo(f"page: {safe(path)}", err=True)


def _drift_page(
    jobs: Sequence[Job], values: Mapping[str, object], rows: Mapping[str, Sequence[Drift]], path: str
) -> None:
    """``diff --inventory --html``: parameters x devices; each cell what the device holds, marked where it
    is not the recipe's value."""
    from ..api.commands import run_info
    from ..pages import drift_page
    from .base import command_line, write_page

    params: dict[str, None] = {}
    for j in jobs:
        params.update((d.name, None) for d in j.recipe.desired)
    names = list(params)
    cells: list[list[tuple[str] | tuple[str, str] | None]] = [[None] * len(jobs) for _ in names]
    index = {n: i for i, n in enumerate(names)}
    for col, j in enumerate(jobs):
        cur = values[j.name]
        if not isinstance(cur, dict):
            continue
        drifted = {r.name: r for r in rows.get(j.name, ()) if r.device_raw is not None}
        for d in j.recipe.desired:
            raw = cur.get(d.name)
            held = "-" if raw is None else d.parameter.show_registers(tuple(raw))
            cells[index[d.name]][col] = (held, d.text) if d.name in drifted else (held,)
    labels = [j.name if isinstance(values[j.name], dict) else f"{j.name} (unreachable)" for j in jobs]
    write_page(drift_page(labels, names, cells, run=run_info(command_line(), time.time())), path)
    echo(f"page: {safe(path)}", err=True)
