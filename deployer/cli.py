"""Command line: thin over the library API. Each command returns its exit code."""

from __future__ import annotations

import asyncio
import json
import os
import sys
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import click

from .diagnostics import (
    EXIT_CHANGES,
    EXIT_INVALID,
    EXIT_OK,
    EXIT_UNREACHABLE,
    Diagnostic,
    InputError,
    UsageError,
)
from .tables import Cell, show

if TYPE_CHECKING:
    from collections.abc import Mapping

    from rich.console import Console

    from .api import Drift
    from .executor import Job, ReadJob
    from .planner import Plan
    from .profile import Profile
    from .recipe import Recipe
    from .report import DeviceResult, Report
    from .transport import DeviceURL
    from .yamlsrc import Source


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


def console(*, stderr: bool = False) -> Console:
    """stdout (or stderr) console; wide when not a terminal so piped lines are not squeezed."""
    from rich.console import Console  # only commands that print pay for importing rich

    if stderr:
        return Console(stderr=True, highlight=False)
    return Console(width=None if sys.stdout.isatty() else 200, highlight=False)


def describe(url: DeviceURL) -> str:
    """The URL as users write it."""
    from .urls import describe as describe_url

    return describe_url(url)


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
    params = data.get("parameters")
    declares = isinstance(params, dict) and any(isinstance(v, dict) and "register" in v for v in params.values())
    if "profile" in data and (declares or data.keys() & {"tables", "addressing", "limits", "identity", "commit"}):
        return "profile"
    if "profile" in data or "extends" in data:
        return "recipe"  # a recipe without its 'recipe' key: let the schema say so
    return None


def validate_file(path: str) -> str:
    """Check one file of any kind; returns a one-line summary or raises InputError."""
    from . import yamlsrc

    data, src = yamlsrc.load(path, hand_over=True)  # the loader below takes it over: parsed once
    try:
        return _validate_kind(path, _kind(data), data, src)
    finally:
        yamlsrc.forget(path)


def _validate_kind(path: str, kind: str | None, data: Any, src: Source) -> str:
    from .fleet import load_inventory
    from .profile import load_profile, resolve_profile
    from .recipe import load_recipe

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
                    resolve_profile(dev.profile, relative_to=path, kind="inventory")
                except UsageError as e:
                    errors.append(src.error(("devices", dev.name, "profile"), str(e)))
                except InputError as e:
                    errors.extend(e.diagnostics)
        if errors:
            raise InputError(errors)
        return f"inventory: {_n(len(inv.devices), 'device')}"
    if kind == "plan":
        from .planner import plan_from_json

        plan = plan_from_json(data, path, src=src)
        return f"plan: {_n(len(plan.writes), 'write request')} for profile {plan.device.profile}"
    what = ("cannot tell what this file is" if isinstance(data, dict) else
            f"expected a mapping, got {'a list' if isinstance(data, list) else 'a single value'}")
    raise InputError([src.error((), f"{what}: a profile has 'profile' and 'parameters', a recipe has 'recipe', "
                                     "an inventory has 'devices'")])


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
    """The built-in device profiles, and importing new ones."""


@profiles.command("list")
def profiles_list() -> int:
    """List the built-in profiles."""
    from .profile import builtin_profile, builtin_profile_ids

    rows: list[list[Cell]] = []
    for pid in builtin_profile_ids():
        prof = builtin_profile(pid)
        first = prof.description.split(". ")[0].rstrip(".")
        rows.append([pid, str(len(prof.parameters)), first])
    show(console(), ["profile", "parameters", "description"], rows)
    return EXIT_OK


def _type_text(p: Any) -> str:
    """'uint32 CDAB', 'bool bit 3', 'uint16 bits 3..5', 'string[8] ascii' (the layout only when not the default)."""
    from .codec import mask_shift

    if p.is_string:
        return f"string[{p.count}] {p.encoding}" + (" BA" if p.byte_swap else "")
    if p.mask:
        shift, width = mask_shift(p.mask)
        return f"{p.type} bit {shift}" if width == 1 else f"{p.type} bits {shift}..{shift + width - 1}"
    return p.type if p.layout in ("AB", "ABCD", "ABCDEFGH") else f"{p.type} {p.layout}"


@profiles.group("import")
def profiles_import() -> None:
    """Write a profile from a vendor's register list (CSV) or a SunSpec model."""


def _pairs(items: Sequence[str], what: str) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip() or not value.strip():
            raise UsageError(f"{what} '{item}': expected NAME=VALUE")
        out[key.strip()] = value.strip()
    return out


def _write_imported(draft: Any, out: str | None, source: str, warnings: Sequence[str] = ()) -> int:
    import re

    from .profile.emit import check

    pid = str(draft.header["profile"])
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", pid):  # the profile schema's pattern
        raise UsageError(f"--id '{pid}': letters, digits, '.', '_' and '-', starting with a letter or digit")

    for w in warnings:
        click.echo(f"warning: {w}", err=True)
    text, prof = check(draft, out or "<stdout>", f"Imported by 'deployer profiles import' from {source}.\n"
                                                "Check it against the manual before the first deployment.")
    _output(text, out, f"{out}: profile {prof.id} with {_n(len(prof.parameters), 'parameter')}")
    return EXIT_OK


def _output(text: str, path: str | None, summary: str) -> None:
    """``text`` into the file ``path`` (saying ``summary`` on stderr), or onto stdout."""
    if path:
        with open(path, "w", encoding="utf-8") as f:
            f.write(text)
        click.echo(summary, err=True)
    else:
        click.echo(text, nl=False)


@profiles_import.command("csv")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--id", "profile_id", required=True, help="Profile id to write (e.g. acme-drive).")
@click.option("-o", "--out", help="Profile file to write (default: stdout).")
@click.option("--column", "columns", multiple=True, metavar="OURS=HEADER",
              help="Which header holds a column, e.g. --column address='Reg No'. Repeatable.")
@click.option("--addressing", type=click.Choice(["address", "register-number", "modicon"]), default="address",
              show_default=True, help="How the address column counts.")
@click.option("--delimiter", help="Cell separator (default: sniffed from , ; or tab).")
@click.option("--byte-order", help="Layout of rows without a byte_order cell: ABCD, CDAB, BADC, DCBA (or "
              "none, byte, word, word_byte).")
def profiles_import_csv(file: str, profile_id: str, out: str | None, columns: Sequence[str], addressing: str,
                        delimiter: str | None, byte_order: str | None) -> int:
    """A profile from a CSV register list (columns: name, address, type, unit, scale, min, max, access ...)."""
    from .profile.csv_import import read_csv

    draft = read_csv(file, profile_id=profile_id, columns=_pairs(columns, "--column"), addressing=addressing,
                     delimiter=delimiter, byte_order=byte_order)
    return _write_imported(draft, out, file)


@profiles_import.command("xlsx")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--id", "profile_id", required=True, help="Profile id to write (e.g. acme-drive).")
@click.option("--sheet", help="Worksheet to read (default: the first).")
@click.option("-o", "--out", help="Profile file to write (default: stdout).")
@click.option("--column", "columns", multiple=True, metavar="OURS=HEADER",
              help="Which header holds a column, e.g. --column address='Reg No'. Repeatable.")
@click.option("--addressing", type=click.Choice(["address", "register-number", "modicon"]), default="address",
              show_default=True, help="How the address column counts.")
@click.option("--byte-order", help="Layout of rows without a byte_order cell: ABCD, CDAB, BADC, DCBA (or "
              "none, byte, word, word_byte).")
def profiles_import_xlsx(file: str, profile_id: str, sheet: str | None, out: str | None, columns: Sequence[str],
                         addressing: str, byte_order: str | None) -> int:
    """A profile from an Excel register list (the same columns as csv; needs openpyxl)."""
    from .profile.csv_import import read_xlsx

    draft = read_xlsx(file, profile_id=profile_id, sheet=sheet, columns=_pairs(columns, "--column"),
                      addressing=addressing, byte_order=byte_order)
    return _write_imported(draft, out, file)


@profiles.group("export")
def profiles_export() -> None:
    """Write a profile in another format."""


@profiles_export.command("csv")
@click.argument("profile")
@click.option("-o", "--out", help="CSV file to write (default: stdout).")
def profiles_export_csv(profile: str, out: str | None) -> int:
    """A profile as a CSV register list ('profiles import csv' reads it back; wire addresses, tables as rows)."""
    from .profile import resolve_profile
    from .profile.csv_import import profile_to_csv

    prof = resolve_profile(profile)
    _output(profile_to_csv(prof), out, f"{out}: {_n(len(prof.parameters), 'register row')} of profile {prof.id}")
    return EXIT_OK


@profiles_import.command("sunspec")
@click.argument("model")
@click.option("--at", "at", default="40002", show_default=True,
              help="Protocol address of the model's ID register (the first model after 'SunS' sits at 40002).")
@click.option("--sf", "sfs", multiple=True, metavar="NAME=N", help="A scale factor the device reports, e.g. "
              "--sf WMax_SF=0. Repeatable.")
@click.option("--count", "counts", multiple=True, metavar="GROUP=N", help="Repetitions of a group whose count the "
              "device reports, e.g. --count curve=4. Repeatable.")
@click.option("--device", metavar="URL", help="Read the scale factors from this device (the model at --at); "
              "--sf wins over what it says.")
@click.option("--unit", type=click.IntRange(1, 247), default=1, show_default=True, help="unit id of --device")
@click.option("--id", "profile_id", help="Profile id (default: sunspec-MODEL-NAME).")
@click.option("-o", "--out", help="Profile file to write (default: stdout).")
def profiles_import_sunspec(model: str, at: str, sfs: Sequence[str], counts: Sequence[str], device: str | None,
                            unit: int, profile_id: str | None, out: str | None) -> int:
    """A profile from a SunSpec model (number, name or model JSON), using pysunspec2's definitions."""
    from .profile import parse_register
    from .profile.sunspec import read_model

    try:
        factors = {k: int(v) for k, v in _pairs(sfs, "--sf").items()}
        repeats = {k: int(v) for k, v in _pairs(counts, "--count").items()}
    except ValueError as e:
        raise UsageError(f"--sf/--count: a count or scale factor is a whole number ({e})") from None
    try:
        address = parse_register(at)
    except ValueError:
        raise UsageError(f"--at {at}: not a register address (40002, 0x9C42 or 9C42h)") from None
    if device is not None:  # the device says its scale factors: read them with a first, unscaled profile
        found = _device_scale_factors(model, address, repeats, device, unit)
        if found is None:
            return EXIT_UNREACHABLE
        factors = {**found, **factors}
    draft, warnings = read_model(model, at=address, scale_factors=factors, counts=repeats, profile_id=profile_id)
    return _write_imported(draft, out, f"SunSpec model {model}", warnings)


def _device_scale_factors(model: str, at: int, counts: dict[str, int], device: str, unit: int
                          ) -> dict[str, int] | None:
    """The model's scale factors as the device reports them; None (after saying why) when it cannot be read."""
    from .codec import decode
    from .profile.emit import check
    from .profile.sunspec import read_model, scale_factor_points
    from .transport import BadURL, parse_url

    try:
        url = parse_url(device)
    except BadURL as e:
        raise UsageError(str(e)) from None
    names = scale_factor_points(model)
    if not names:
        return {}
    _, first = check(read_model(model, at=at, counts=counts)[0], "<model>")
    current = read_device(first, names, url, unit)  # checks the model ID at --at first (identity)
    if current is None:
        return None
    found = {n: int(decode(current[n], "int16")) for n in names if n in current}
    click.echo(f"scale factors from {device}: " + ", ".join(f"{n}={v}" for n, v in found.items()), err=True)
    return found


@profiles.command("show")
@click.argument("profile")
def profiles_show(profile: str) -> int:
    """Show a profile's parameters in engineering units (a built-in id or a file)."""
    from .codec import format_decimal, layout_name
    from .profile import resolve_profile

    prof = resolve_profile(profile)
    out = console()
    out.print(f"[bold]{prof.id}[/bold]: {prof.description}")
    lim = prof.limits
    layout = layout_name(prof.word_order, prof.byte_swap)
    out.print(f"addressing {prof.addressing}, byte order {layout}; up to {lim.write_registers} registers "
              f"per write (FC{lim.write_function:02d}), {lim.read_registers} per read")
    rows: list[list[Cell]] = []
    for p in prof.parameters:
        rng = "" if p.min is None and p.max is None else (
            f"{'' if p.min is None else format_decimal(p.min)}..{'' if p.max is None else format_decimal(p.max)}")
        if p.values:
            rng = ", ".join(f"{label}={raw}" for label, raw in p.values)
        default = "" if p.default is None else p.default if isinstance(p.default, str) else (
            str(bool(p.default)).lower() if p.type == "bool" else format_decimal(p.default))
        rows.append([p.name, f"0x{p.address:04X} ({p.address})", _type_text(p), p.unit or "",
                     "" if p.is_string or p.type == "bool" else format_decimal(p.scale), rng, p.access, default,
                     p.description])
    show(out, ["parameter", "address", "type", "unit", "resolution", "range", "access", "default", "description"],
         rows)
    return EXIT_OK

@profiles.command("new")
@click.argument("output", type=click.Path(dir_okay=False))
@click.option("--id", "profile_id", help="the profile's id (default: the file name without .yaml)")
@click.option("--force", is_flag=True, help="overwrite an existing file")
def profiles_new(output: str, profile_id: str | None, force: bool) -> int:
    """Write a commented profile skeleton to OUTPUT, ready to fill in from the device's manual."""
    import re

    from .skeleton import profile_skeleton
    from .yamlsrc import schema

    pid = profile_id or os.path.splitext(os.path.basename(output))[0]
    pattern = schema("profile")["properties"]["profile"]["pattern"]
    if not re.match(pattern, pid):
        raise UsageError(f"'{pid}' is not a profile id (letters, digits, '.', '_', '-'); pass --id ID")
    text = profile_skeleton(pid, output)
    if os.path.exists(output) and not force:
        raise UsageError(f"{output} exists; pass --force to overwrite it")
    with open(output, "w", encoding="utf-8") as f:
        f.write(text)
    click.echo(f"wrote {output}: fill it in from the manual, then run: deployer validate {output}", err=True)
    return EXIT_OK


# --- reference docs, explain (docgen) ----------------------------------------------------


@cli.command("docs")
@click.option("--out", "out_dir", default=os.path.join("docs", "reference"), show_default=True,
              type=click.Path(file_okay=False), help="where the reference pages go")
@click.option("--check", is_flag=True, help="write nothing; exit 1 when a page differs from the schemas")
def docs_command(out_dir: str, check: bool) -> int:
    """Generate the reference pages (one per file kind) from the JSON Schemas."""
    from .docgen import stale_pages, write_pages

    if check:
        stale = stale_pages(out_dir)
        for path in stale:
            click.echo(f"{path}: stale (run: deployer docs --out {out_dir})", err=True)
        return EXIT_INVALID if stale else EXIT_OK
    changed = write_pages(out_dir)
    click.echo(f"{len(changed)} page{'s' if len(changed) != 1 else ''} updated in {out_dir}", err=True)
    return EXIT_OK


@cli.command()
@click.argument("key")
def explain(key: str) -> int:
    """Explain a key of a profile, recipe, inventory, plan or report, or a device URL option
    (e.g. max_frame_bytes, profile:scale, baudrate)."""
    import difflib

    from .docgen import all_keys, find_keys, render_text, url_option_text

    texts = [render_text(k) for k in find_keys(key)]
    kind, _, name = key.rpartition(":")
    if kind in ("", "url"):
        texts += [t for t in [url_option_text(name)] if t]
    if not texts:
        names = sorted({k.path for k in all_keys()} | {k.path.rsplit(".", 1)[-1] for k in all_keys()})
        hint = difflib.get_close_matches(name, names, n=3)
        raise UsageError(f"no key '{key}' in any schema" + (f"; did you mean {', '.join(hint)}?" if hint else
                                                            "; try e.g. 'deployer explain scale'"))
    click.echo("\n\n".join(texts))
    return EXIT_OK


# --- plan (planner) ---------------------------------------------------------------------

_device_options = [
    click.option("--device", "device", metavar="URL", help="device URL (default: the recipe's device.url)"),
    click.option("--unit", type=click.IntRange(0, 247), help="unit id (default: the recipe's, else 1)"),
    click.option("--timeout", type=click.FloatRange(min=0, min_open=True), help="seconds per attempt"),
    click.option("--retries", type=click.IntRange(0, 20), help="retries after a timeout or busy answer"),
]


def device_options(f: Callable[..., Any]) -> Callable[..., Any]:
    for opt in reversed(_device_options):
        f = opt(f)
    return f


LIMIT_HELP = ("inventory devices: names, groups and glob patterns, comma-separated (!X excludes); "
              "@REPORT.json = the devices of that report that did not end ok")
fleet_option = click.option("--inventory", type=click.Path(dir_okay=False), help="every device of an inventory")
limit_option = click.option("--limit", metavar="SEL", help=LIMIT_HELP)
parallel_option = click.option("--parallel", type=click.IntRange(1, 1000), default=8, show_default=True,
                               help="devices at once (devices on one bus always go one at a time)")


def _target(recipe: Recipe, device: str | None, unit: int | None, timeout: float | None,
            retries: int | None, *, required: bool) -> tuple[DeviceURL | None, int]:
    """The device URL and unit from the options, else the recipe's; parsed before any I/O."""
    from .urls import BadURL, parse_url  # not transport: an offline plan does not import pymodbus

    text = device or (recipe.device.url if recipe.device else None)
    u = unit if unit is not None else (recipe.device.unit if recipe.device and recipe.device.unit is not None else 1)
    if text is None:
        if required:
            raise UsageError("no device: pass --device URL or set device.url in the recipe")
        return None, u
    try:
        return parse_url(text, timeout=timeout, retries=retries), u
    except BadURL as e:
        raise UsageError(str(e)) from None


def read_device(profile: Profile, names: Sequence[str], url: DeviceURL, unit: int
                ) -> dict[str, tuple[int, ...]] | None:
    """Current values for plan --device, diff and pull; None (after saying why) when unreachable."""
    from .executor import read_current
    from .transport import TransportError

    try:
        return asyncio.run(read_current(profile, names, url, unit))
    except TransportError as e:
        click.echo(f"error: {e}", err=True)
        return None


def _hexwords(regs: Sequence[int] | None) -> str:
    return "-" if regs is None else " ".join([format(w, "04X") for w in regs])


def _line_of(url: DeviceURL | None) -> tuple[str, int, int, str]:
    """(framing, baud, bits per character, text) of the line the plan goes over: the URL's serial settings,
    else the Modbus default 19200 baud 8E1 on RTU."""
    if url is not None and url.scheme in ("rtu", "ascii"):
        ln = url.line
        bits = 1 + ln.bytesize + (ln.parity != "N") + ln.stopbits
        return url.scheme, ln.baudrate, bits, f"{ln.baudrate} baud {ln.bytesize}{ln.parity}{ln.stopbits}"
    return "rtu", 19200, 11, "19200 baud"


def print_plan(plan: Plan, profile: Profile, *, changes_only: bool, out: Console,
               url: DeviceURL | None = None) -> None:
    from .planner import line_cost, wire_stats

    req_of: dict[str, list[int]] = {}
    for i, w in enumerate(plan.writes, 1):
        for n in w.parameters:
            req_of.setdefault(n, []).append(i)
    headers = ["parameter", "address", "raw", "value", "request"]
    if changes_only:
        headers = ["parameter", "address", "current -> desired", "raw", "action", "request"]
    rows: list[list[Cell]] = []
    for pp in plan.parameters:
        if changes_only and pp.action == "unchanged":
            continue
        addr = f"0x{pp.address:04X} ({pp.address})"
        reqs = ",".join(str(i) for i in req_of.get(pp.name, [])) or "-"
        if changes_only:
            p = profile.parameter(pp.name)
            cur = p.format_registers(pp.current_raw) if pp.current_raw is not None else "?"
            rows.append([pp.name, addr, f"{cur} -> {pp.desired}", _hexwords(pp.desired_raw), pp.action, reqs])
        else:
            rows.append([pp.name, addr, _hexwords(pp.desired_raw), pp.desired, reqs])
    if rows:
        show(out, headers, rows)
        if not changes_only and any(profile.parameter(pp.name).mask for pp in plan.parameters):
            out.print("bit fields: raw shows their own bits; apply reads each such register right before writing "
                      "it and keeps its other bits as the device holds them")
    elif changes_only:
        out.print("No changes: the device already holds every value of the recipe.")
    st = wire_stats(plan)
    naive = sum(1 for pp in plan.parameters if pp.action != "unchanged")
    unchanged = sum(1 for pp in plan.parameters if pp.action == "unchanged")
    framing, baud, bits, line = _line_of(url)
    chars, seconds = line_cost(plan, framing=framing, baud=baud, char_bits=bits)
    units = (f"{_n(chars, 'character')} on an ASCII line" if framing == "ascii"
             else f"{_n(chars, 'byte')} on an RTU line")
    out.print(
        f"{_n(len(plan.writes), 'write request')} "
        f"({_n(int(st['registers']), 'register')}; one request per parameter would take {naive})"
        + (f", {unchanged} unchanged" if unchanged else "")
        + f"; {units}, about {seconds * 1000:.0f} ms at {line}"
        + (" (broadcast: no answers)" if plan.device.unit == 0 else ""))


def print_frames(plan: Plan, out: Console) -> None:
    from .frames import Framing, request_frame, response_frame

    unit = plan.device.unit
    for i, w in enumerate(plan.writes, 1):
        names = ", ".join(w.parameters)
        out.print(f"request {i}: FC{w.function:02d} at 0x{w.address:04X}, {w.count} registers ({names})")
        framing: Framing
        for framing in ("rtu", "ascii", "tcp"):
            q = request_frame(w, unit, framing, transaction_id=i)
            out.print(f"  {framing:5} query    {_show(q, framing)}")
            if unit == 0:  # broadcast: no device answers
                out.print(f"  {'':5} response none (broadcast)")
                continue
            a = response_frame(w, unit, framing, transaction_id=i)
            out.print(f"  {'':5} response {_show(a, framing)}")


def _show(frame: bytes, framing: str) -> str:
    return frame.decode("ascii").strip() if framing == "ascii" else frame.hex(" ").upper()


@cli.command()
@click.argument("recipe", type=click.Path(dir_okay=False))
@device_options
@click.option("--json", "as_json", is_flag=True, help="print the plan as JSON")
@click.option("--out", "out_path", type=click.Path(dir_okay=False), help="write the plan (JSON) for 'apply PLAN.json'")
@click.option("--detailed-exitcode", is_flag=True, help="exit 2 when something would change, 0 when nothing would")
@click.option("--show-frames", is_flag=True, help="print the exact bytes of each request (RTU, ASCII, TCP)")
@click.option("--write-all", is_flag=True, help="plan every parameter, even those the device already holds")
@fleet_option
@limit_option
@parallel_option
def plan(recipe: str, device: str | None, unit: int | None, timeout: float | None, retries: int | None,
         as_json: bool, out_path: str | None, detailed_exitcode: bool, show_frames: bool, write_all: bool,
         inventory: str | None, limit: str | None, parallel: int) -> int:
    """Show the requests that apply would send. Offline, or with --device against what the device holds."""
    from .planner import Target, make_plan, plan_to_json
    from .recipe import load_recipe
    from .report import write_json

    rec = load_recipe(recipe)
    if inventory:
        if device or out_path or show_frames:
            raise UsageError("with --inventory, --device, --out and --show-frames do not apply (one plan per device)")
        return plan_fleet(rec, _fleet(rec, inventory, limit, timeout, retries, unit), parallel=parallel,
                          as_json=as_json, detailed_exitcode=detailed_exitcode, write_all=write_all)
    if limit:
        raise UsageError("--limit needs --inventory")
    url, u = _target(rec, device, unit, timeout, retries, required=False)
    current = None
    if device is not None:
        assert url is not None
        current = read_device(rec.profile, [d.name for d in rec.desired], url, u)
        if current is None:
            return EXIT_UNREACHABLE
    target = Target(describe(url) if url else None, u, rec.profile_ref or rec.profile.id)
    p = make_plan(rec, target, current, write_all=write_all)
    data = plan_to_json(p)
    if out_path:
        write_json(data, out_path)
    if as_json:
        click.echo(json.dumps(data, indent=2))
    else:
        out = console()
        out.print(f"profile: {rec.profile.id} ({rec.profile.source or 'built-in'})")
        print_plan(p, rec.profile, changes_only=current is not None, out=out, url=url)
        if show_frames:
            print_frames(p, out)
        if out_path:
            out.print(f"plan written to {out_path}; run it unchanged with: deployer apply {out_path}")
    if detailed_exitcode and p.writes:
        return EXIT_CHANGES
    return EXIT_OK


def read_fleet(jobs: Sequence[ReadJob], parallel: int) -> dict[str, dict[str, tuple[int, ...]] | Exception]:
    """Current values of every device (a live display on a terminal); errors are said on stderr."""
    from .api import read_fleet_async
    from .progress import FleetProgress

    err = console(stderr=True)
    progress = FleetProgress(len(jobs), err, live=err.is_terminal, verb="reading", lines=False)
    with progress:
        values = asyncio.run(read_fleet_async(
            jobs, parallel=parallel, on_done=lambda n, e: progress.done(n, "unreachable" if e else "ok")))
    for name, v in values.items():
        if isinstance(v, Exception):
            click.echo(f"{name}: unreachable - {v}", err=True)
    return dict(values)


def _unreachable(values: Mapping[str, object]) -> list[str]:
    return [n for n, v in values.items() if isinstance(v, Exception)]


def plan_fleet(rec: Recipe, jobs: Sequence[Job], *, parallel: int, as_json: bool, detailed_exitcode: bool,
               write_all: bool) -> int:
    """A plan per device against what it holds; exit 3 if any device could not be read, else as plan."""
    from .api import read_jobs
    from .planner import Target, make_plan, plan_to_json

    values = read_fleet(read_jobs(jobs), parallel)
    plans = {}
    for j in jobs:
        cur = values[j.name]
        if not isinstance(cur, Exception):
            plans[j.name] = make_plan(j.recipe, Target(describe(j.url), j.unit, j.recipe.profile_ref
                                                       or j.recipe.profile.id), cur, write_all=write_all)
    changing = [n for n, p in plans.items() if p.writes]
    if as_json:
        click.echo(json.dumps({"recipe": rec.path, "devices": [
            {"name": j.name, "plan": plan_to_json(plans[j.name])} if j.name in plans
            else {"name": j.name, "error": str(values[j.name])} for j in jobs]}, indent=2))
    else:
        out = console()
        for j in jobs:
            if j.name in plans and plans[j.name].writes:
                out.print(f"[bold]{j.name}[/bold] {describe(j.url)} unit {j.unit}:")
                print_plan(plans[j.name], j.recipe.profile, changes_only=True, out=out)
        down = _unreachable(values)
        out.print(f"{len(changing)} of {len(jobs)} devices would change" + (f": {', '.join(changing)}" if changing
                                                                            else "")
                  + (f"; {len(down)} unreachable: {', '.join(down)}" if down else ""))
    if _unreachable(values):
        return EXIT_UNREACHABLE
    return EXIT_CHANGES if detailed_exitcode and changing else EXIT_OK


# --- simulate (simulator) ---------------------------------------------------------------


def _register(text: str) -> int:
    from .profile import parse_register

    try:
        return parse_register(text)
    except ValueError:
        raise click.BadParameter(f"not a register address: {text!r} (e.g. 4354, 0x1102, 1102h)") from None


@cli.command()
@click.argument("profile")
@click.option("--listen", default="tcp://127.0.0.1:5020", show_default=True, metavar="URL",
              help="tcp://HOST:PORT, rtu+tcp://HOST:PORT, rtu:///dev/X?baudrate=B, ascii:///dev/X")
@click.option("--unit", "units", type=click.IntRange(1, 247), multiple=True, help="unit id(s) served (default 1)")
@click.option("--init", "init_recipe", type=click.Path(dir_okay=False), help="start with a recipe's values")
@click.option("--set", "set_registers", multiple=True, metavar="ADDR=RAW",
              help="start a register (protocol address) with a raw value, read-only ones too, e.g. a status word "
                   "saying 'running': --set 0x10=8. Repeatable.")
@click.option("--latency-ms", type=click.FloatRange(min=0), default=0, help="delay every answer")
@click.option("--baud", type=click.IntRange(min=50), help="delay answers by their line time at this baud rate (8E1)")
@click.option("--drop-every", type=click.IntRange(min=0), default=0, help="never answer every Nth request")
@click.option("--busy-first", type=click.IntRange(min=0), default=0, help="answer the first N writes with 06 (busy)")
@click.option("--fail-register", "fail_registers", multiple=True, metavar="ADDR",
              help="writes reaching this wire address answer 04 (repeatable; 4354, 0x1102 or 1102h)")
@click.option("--disconnect-after", type=click.IntRange(min=0), default=0, help="drop the connection every N requests")
@click.option("--state", "state_path", type=click.Path(dir_okay=False), help="dump registers as JSON on exit/SIGUSR1")
@click.option("--log", "log_path", type=click.Path(dir_okay=False), help="one JSON line per request")
@click.option("--loose-limits", is_flag=True, help="accept requests beyond the profile's limits")
@click.option("--gap-reads", is_flag=True, help="answer reads of undeclared registers between declared ones (zeros)")
def simulate(profile: str, listen: str, units: tuple[int, ...], init_recipe: str | None,
             set_registers: tuple[str, ...], latency_ms: float,
             baud: int | None, drop_every: int, busy_first: int, fail_registers: tuple[str, ...],
             disconnect_after: int, state_path: str | None, log_path: str | None, loose_limits: bool,
             gap_reads: bool) -> int:
    """Serve a simulated device for PROFILE (a built-in id or a file) until Ctrl-C."""
    from .profile import resolve_profile
    from .recipe import load_recipe
    from .simulator import Faults, Simulator, init_from_recipe, parse_listen, serve

    prof = resolve_profile(profile)
    try:
        parse_listen(listen)
    except ValueError as e:
        raise UsageError(str(e)) from None
    init = init_from_recipe(load_recipe(init_recipe)) if init_recipe else {}
    for item in set_registers:
        addr, sep, raw = item.partition("=")
        if not sep:
            raise UsageError(f"--set {item}: expected ADDR=RAW, e.g. 0x10=8")
        try:
            address, value = _register(addr.strip()), _register(raw.strip())
        except click.BadParameter:
            raise UsageError(f"--set {item}: expected ADDR=RAW with numbers, e.g. 0x10=8") from None
        if value > 0xFFFF:
            raise UsageError(f"--set {item}: a register holds 0..65535")
        init[address] = value
    faults = Faults(latency_ms=latency_ms, baud=baud, drop_every=drop_every, busy_first=busy_first,
                    fail_registers=frozenset(_register(r) for r in fail_registers),
                    disconnect_after=disconnect_after)
    try:
        sim = Simulator(prof, listen=listen, units=units or (1,), init=init, faults=faults, log_path=log_path,
                        state_path=state_path, strict_limits=not loose_limits, gap_reads=gap_reads)
    except ValueError as e:  # a --set register the profile does not declare
        raise UsageError(str(e)) from None

    def ready(s: Simulator) -> None:
        which = ", ".join(str(u) for u in s.units)
        click.echo(f"simulating {prof.id} unit{'s' if len(s.units) > 1 else ''} {which} on {s.url} (Ctrl-C to stop)",
                   err=True)

    try:
        asyncio.run(serve(sim, on_ready=ready))
    except (OSError, RuntimeError) as e:
        click.echo(f"error: cannot listen on {listen}: {e}", err=True)
        return EXIT_INVALID
    return EXIT_OK


# --- apply, diff, pull, rollback, demo (executor) ---------------------------------------

_STATUS_ORDER = {"failed": 0, "mismatch": 1, "unverified": 2, "skipped": 3, "ok": 4, "unchanged": 5}
_STATUS_STYLE = {"ok": "green", "unchanged": "dim", "failed": "bold red", "mismatch": "bold red",
                 "unverified": "yellow", "skipped": "yellow", "partial": "yellow", "unreachable": "bold red",
                 "sent": "cyan"}


def print_report(report: Report, out: Console, *, only_not_ok: bool = False) -> None:
    """Per device, every parameter; ``only_not_ok`` (fleets): only the devices that need a look, by parameter."""
    for d in report.devices:
        if only_not_ok and d.status in ("ok", "skipped"):
            continue
        style = _STATUS_STYLE.get(d.status, "")
        out.print(f"[bold]{d.name}[/bold] {d.url} unit {d.unit} ({d.profile}): [{style}]{d.status}[/{style}]"
                  + (f" - {d.error}" if d.error else ""))
        rows = sorted(d.parameters, key=lambda p: (_STATUS_ORDER.get(p.status, 9), p.address))
        if only_not_ok:
            rows = [p for p in rows if p.status not in ("ok", "unchanged")]
        if d.status != "unreachable" and rows:
            show(out, ["parameter", "before", "desired", "after", "status", ""],
                 [[p.name, p.before or "-", p.desired, p.after or "-", (p.status, _STATUS_STYLE.get(p.status, "")),
                   p.error or ""] for p in rows])
        if d.status == "sent":
            out.print("broadcast sent: every request went out; no device answers a broadcast, so nothing was "
                      "read back or verified")
        for note in d.notices:
            out.print(f"note: {note}")
        if d.snapshot:
            out.print(f"snapshot: {d.snapshot}  (undo with: deployer rollback {d.snapshot})")
        out.print(f"{d.write_requests} write and {d.read_requests} read requests")
    s = report.summary()
    if len(report.devices) > 1 and not only_not_ok:
        out.print(f"{s['devices']} devices: {s['ok']} ok, " + (f"{s['sent']} sent, " if s["sent"] else "")
                  + f"{s['partial']} partial, {s['failed']} failed, {s['unreachable']} unreachable "
                  f"in {s['seconds']:.2f} s")


def _is_plan_file(path: str) -> bool:
    if path.endswith(".json"):
        return True
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    return head.lstrip().startswith(b"{") and b"deployer.plan/" in head


def run_apply(source: str | None, *, device: str | None, unit: int | None, timeout: float | None,
              retries: int | None, yes: bool, report_path: str | None, as_json: bool, inventory: str | None,
              limit: str | None, parallel: int, on_error: str, write_all: bool, allow_broadcast: bool, state_dir: str,
              lock_timeout: float = 0.0, force: bool = False, from_report: str | None = None,
              batch: str | None = None, max_failures: str | None = None, command: str = "apply") -> int:
    """apply / rollback: everything validated, then confirmed, then sent."""
    from . import journal
    from .api import fleet_options, run_fleet_async
    from .executor import ApplyOptions, Job, apply_many
    from .planner import load_plan
    from .recipe import load_recipe
    from .report import write_json

    expected: Plan | None = None
    jobs: list[Job] = []
    moved: list[str] = []  # rollback to another device than the snapshot's: asked about first
    if not (inventory or from_report) and (batch or max_failures or limit):
        raise UsageError("--limit, --batch and --max-failures need --inventory")
    if from_report is not None:  # rollback --report: every device of that run from its own snapshot
        if inventory or device or unit is not None:
            raise UsageError("rollback --report restores each device from its own snapshot, to the device it was "
                             "taken from: --inventory, --device and --unit do not apply")
        jobs = _rollback_report_jobs(from_report, force=force, timeout=timeout, retries=retries)
        if limit:  # names and patterns select among that run's devices (it has no groups)
            from .fleet import FleetDevice, Inventory, select

            chosen = {d.name for d in select(Inventory(from_report, tuple(FleetDevice(j.name, describe(j.url))
                                                                          for j in jobs)), limit)}
            jobs = [j for j in jobs if j.name in chosen]
        label = from_report
    else:
        assert source is not None
        label = source
        if _is_plan_file(source):
            if inventory or write_all:
                raise UsageError("a saved plan runs unchanged: --inventory and --write-all do not apply to it")
            rec, expected = load_plan(source)
        else:
            rec = load_recipe(source, force=force)
        if rec.snapshot is not None and inventory:
            raise UsageError(f"{source} is one device's snapshot: it restores only the device it was taken from. "
                             "To roll back a fleet run, use: deployer rollback --report REPORT.json")
        if inventory:
            if device:
                raise UsageError("--device and --inventory exclude each other")
            jobs = _fleet(rec, inventory, limit, timeout, retries, unit)
        else:
            one, u = _target(rec, device, unit, timeout, retries, required=True)
            assert one is not None
            jobs.append(Job(rec.name, rec, one, u))
            if rec.snapshot is not None and rec.device is not None and rec.device.url is not None:
                taken, taken_unit = _target(rec, None, None, timeout, retries, required=True)
                assert taken is not None
                if (taken.bus, taken_unit) != (one.bus, u):
                    moved.append(f"{source} was taken from {describe(taken)} unit {taken_unit}, not "
                                 f"{describe(one)} unit {u}")
    for j in jobs:
        if j.unit == 0 and not allow_broadcast:
            raise UsageError(f"{j.name}: unit 0 is broadcast (no device answers, nothing can be verified); "
                             "pass --allow-broadcast to send it anyway")

    out = console()
    err = console(stderr=True)
    confirm = None
    if not yes:
        if not sys.stdin.isatty():
            raise UsageError("refusing to write without confirmation: stdin is not a terminal; pass --yes")
        for why in moved:
            if not click.confirm(f"{why}. Restore it to that other device?", default=False, err=True):
                raise UsageError("nothing was written (declined)")
        ask_lock = asyncio.Lock()
        profiles = {j.name: j.recipe.profile for j in jobs}

        async def confirm(p: Plan, res: DeviceResult) -> bool:
            async with ask_lock:  # one question at a time, even for fleets
                err.print(f"[bold]{res.name}[/bold] {res.url} unit {res.unit}:")
                print_plan(p, profiles[res.name], changes_only=True, out=err)
                return await asyncio.to_thread(click.confirm, "Write these values?", default=False, err=True)
    elif moved:
        for why in moved:
            err.print(f"warning: {why}; restoring it there (--yes)")

    fleet_run = bool(inventory or from_report)
    if fleet_run:
        fleet_options(len(jobs), parallel=parallel, batch=batch, max_failures=max_failures, report_path=report_path)
    run_id = journal.new_run_id()
    journal.run_started(state_dir, run_id, command=command, argv=_ARGV, recipe=label,
                        devices=[(j.name, describe(j.url), j.unit) for j in jobs])
    options = ApplyOptions(on_error=on_error, write_all=write_all,  # type: ignore[arg-type]
                           allow_broadcast=allow_broadcast, state_dir=state_dir, expected=expected, confirm=confirm,
                           run_id=run_id, applied=os.path.abspath(label), lock_timeout=lock_timeout)
    if fleet_run:
        import gc

        from .progress import FleetProgress  # rich's live display: only fleets pay for importing it

        if _OWN_PROCESS:  # the command's own process only: the library and callers keep their collector
            # what is loaded now (modules, profiles, recipes) lives as long as the command: later collections
            # need not walk it, and a fleet allocates fast, so collect less often (the cyclic collector
            # took 35-50 ms of a 0.7 s run of 200 devices, a 20 ms pause among them)
            gc.freeze()
            gc.set_threshold(20_000, 20, 10)
        # a live display on a terminal (not while asking questions), else a line per device
        progress = FleetProgress(len(jobs), err, live=err.is_terminal and yes)
        with progress:
            report = asyncio.run(run_fleet_async(
                jobs, recipe_name=label, parallel=parallel, batch=batch, max_failures=max_failures, options=options,
                report_path=report_path, on_start=lambda j: progress.start(j.name), on_done=progress.device_done))
    else:
        report = asyncio.run(apply_many(jobs, parallel=parallel, options=options, recipe_name=label))
        if report_path:
            write_json(report.to_json(), report_path)
    journal.run_finished(state_dir, run_id, report, command=command, argv=_ARGV)
    if as_json:
        if fleet_run:
            from .fleet import report_text

            click.echo(report_text(report), nl=False)
        else:
            click.echo(json.dumps(report.to_json(), indent=2))
    elif fleet_run:
        from .progress import fleet_summary

        print_report(report, out, only_not_ok=True)
        fleet_summary(report, out)
    else:
        print_report(report, out)
    return report.exit_code


def _fleet(rec: Recipe, inventory: str, limit: str | None, timeout: float | None, retries: int | None,
           unit: int | None) -> list[Job]:
    from .api import fleet

    return fleet(rec, inventory, limit=limit, timeout=timeout, retries=retries, unit=unit)


def _rollback_report_jobs(path: str, *, force: bool, timeout: float | None, retries: int | None) -> list[Job]:
    """One job per device of an earlier run that has a snapshot: its own snapshot, to its own device."""
    from .executor import Job
    from .recipe import load_recipe
    from .snapshot import snapshots_of_report

    found, without = snapshots_of_report(path)
    if without:
        click.echo(f"nothing to roll back on {', '.join(without)}: nothing was written there", err=True)
    if not found:
        raise UsageError(f"{path}: no device of that run has a snapshot (nothing was written): nothing to roll back")
    jobs: list[Job] = []
    errors: list[Diagnostic] = []
    for rs in found:
        try:
            rec = load_recipe(rs.snapshot, force=force)
        except InputError as e:
            errors.extend(e.diagnostics)
            continue
        if rec.snapshot is None or rec.device is None or rec.device.url is None:
            errors.append(Diagnostic(rs.snapshot, 1, 1, f"{rs.name}: not a snapshot with its device (made by an "
                                                        "older deployer?): roll it back with rollback SNAPSHOT "
                                                        "--device URL"))
            continue
        url, u = _target(rec, None, None, timeout, retries, required=True)
        assert url is not None
        jobs.append(Job(rs.name, rec, url, u))
    if errors:
        raise InputError(errors)
    return jobs


def apply_options(f: Callable[..., Any]) -> Callable[..., Any]:
    opts = [
        click.option("--yes", "-y", is_flag=True, help="do not ask for confirmation"),
        click.option("--report", "report_path", type=click.Path(dir_okay=False), help="write the report JSON here"),
        click.option("--json", "as_json", is_flag=True, help="print the report JSON"),
        fleet_option,
        limit_option,
        click.option("--batch", metavar="1,10%,100%",
                     help="staged rollout: batch sizes (count or % of the selected devices; the last repeats); "
                          "each batch finishes before the next, a batch with no ok device ends the rollout"),
        click.option("--max-failures", metavar="N|P%",
                     help="after this many devices ended failed or partial, start no new device"),
        parallel_option,
        click.option("--on-error", type=click.Choice(["continue", "stop"]), default="continue", show_default=True,
                     help="after a rejected value: send the rest, or skip it"),
        click.option("--write-all", is_flag=True, help="write every parameter, even those already right"),
        click.option("--allow-broadcast", is_flag=True, help="allow unit 0 (broadcast; nothing can be verified)"),
        click.option("--state-dir", default=".deployer", show_default=True, type=click.Path(file_okay=False),
                     help="where snapshots and the audit log go"),
        click.option("--lock-timeout", type=click.FloatRange(min=0), default=0, show_default=True, metavar="S",
                     help="wait up to S seconds for a device another run on this machine is writing"),
    ]
    for opt in reversed(opts):
        f = opt(f)
    return device_options(f)


@cli.command()
@click.argument("source", metavar="RECIPE|PLAN.json", type=click.Path(dir_okay=False))
@apply_options
def apply(source: str, **kw: Any) -> int:
    """Write a recipe (or a saved plan) to a device, read it back, report what it holds."""
    return run_apply(source, **kw)


@cli.command()
@click.argument("snapshot", required=False, type=click.Path(dir_okay=False, exists=True))
@apply_options
@click.option("--force", is_flag=True,
              help="restore the recorded raw registers although the profile changed since the snapshot")
@click.option("--save-report", type=click.Path(dir_okay=False), metavar="FILE",
              help="with --report RUN.json: write this rollback's own report here")
def rollback(snapshot: str | None, **kw: Any) -> int:
    """Restore a snapshot that apply saved, to the device it was taken from.

    \b
    rollback SNAPSHOT            that device, from that snapshot (--report FILE writes this run's report)
    rollback --report RUN.json   every device of an earlier run, each from its own snapshot
                                 (--save-report FILE writes this run's report)
    """
    save = kw.pop("save_report")
    if snapshot is None:
        if not kw["report_path"]:
            raise UsageError("rollback needs a SNAPSHOT, or --report REPORT.json to roll back every device of a run")
        from_report, kw["report_path"] = kw["report_path"], save
        return run_apply(None, from_report=from_report, command="rollback", **kw)
    if save:
        raise UsageError("--save-report goes with rollback --report RUN.json; with a SNAPSHOT use --report FILE")
    return run_apply(snapshot, command="rollback", **kw)


@cli.command()
@click.option("--state-dir", default=".deployer", show_default=True, type=click.Path(file_okay=False),
              help="where snapshots and the audit log are")
@click.option("--json", "as_json", is_flag=True, help="print the unfinished runs as JSON")
def status(state_dir: str, as_json: bool) -> int:
    """Runs that never finished (a crash, kill -9, a laptop asleep): which devices were being written."""
    from .journal import unfinished

    runs, torn = unfinished(state_dir)
    if as_json:
        click.echo(json.dumps({"unfinished": [
            {"run": r.run, "time": r.time, "user": r.user, "pid": r.pid, "running": r.running, "command": r.command,
             "argv": r.argv, "recipe": r.recipe, "devices": r.devices, "interrupted": r.interrupted,
             "finished": r.finished} for r in runs]}, indent=2))
        return EXIT_OK
    out = console()
    if not runs:
        out.print(f"no unfinished runs in {os.path.join(state_dir, 'audit.jsonl')}")
    for r in runs:
        state = "still running" if r.running else "did not finish"
        out.print(f"[bold]{r.command}[/bold] {r.recipe or ''} by {r.user} at {r.time} (run {r.run}, PID {r.pid}): "
                  f"{state}; {_n(len(r.devices), 'device')} selected, {len(r.finished)} finished")
        for d in r.interrupted:
            out.print(f"  interrupted while writing: {d.get('name')} {d.get('url')} unit {d.get('unit')}; "
                      f"snapshot {d.get('snapshot')}")
            out.print(f"    check with: deployer diff RECIPE --device {d.get('url')} --unit {d.get('unit')}; "
                      f"undo with: deployer rollback {d.get('snapshot')}")
        done = {(d.get("name"), d.get("url"), d.get("unit")) for d in (*r.finished, *r.interrupted)}
        never = [d for d in r.devices if (d.get("name"), d.get("url"), d.get("unit")) not in done]
        if never and not r.running:
            out.print(f"  not written (never started or nothing to write): "
                      f"{', '.join(str(d.get('name')) for d in never)}")
    if torn:
        out.print(f"({_n(torn, 'line')} of the log could not be read: cut off by the crash)")
    return EXIT_OK


@cli.command()
@click.argument("recipe", type=click.Path(dir_okay=False))
@device_options
@click.option("--json", "as_json", is_flag=True, help="print the differences as JSON")
@fleet_option
@limit_option
@parallel_option
def diff(recipe: str, device: str | None, unit: int | None, timeout: float | None, retries: int | None,
         as_json: bool, inventory: str | None, limit: str | None, parallel: int) -> int:
    """Drift check: exit 2 when the device (any device of --inventory) differs from the recipe, 0 when it matches."""
    from .api import diff_values
    from .recipe import load_recipe

    rec = load_recipe(recipe)
    if inventory:
        if device:
            raise UsageError("--device and --inventory exclude each other")
        return diff_fleet(rec, _fleet(rec, inventory, limit, timeout, retries, unit), parallel=parallel,
                          as_json=as_json)
    if limit:
        raise UsageError("--limit needs --inventory")
    url, u = _target(rec, device, unit, timeout, retries, required=True)
    assert url is not None
    current = read_device(rec.profile, [d.name for d in rec.desired], url, u)
    if current is None:
        return EXIT_UNREACHABLE
    rows = diff_values(rec, current)
    drift = [r for r in rows if r.device_raw is not None]
    if as_json:
        click.echo(json.dumps({"recipe": recipe, "device": describe(url), "unit": u,
                               "drift": [r.to_json() for r in rows]}, indent=2))
    elif rows:
        show(console(), ["parameter", "recipe", "device value", ""], drift_rows(rows))
        console().print(f"{len(drift)} of {len(rec.desired)} parameters differ from the recipe")
    else:
        console().print(f"no drift: the device holds all {len(rec.desired)} values of the recipe")
    return EXIT_CHANGES if drift else EXIT_OK


def drift_rows(rows: Sequence[Drift], device: str | None = None) -> list[list[Cell]]:
    """parameter, recipe, device value, status (with the device's name first for fleets)."""
    return [[*([device] if device is not None else []), r.name, r.desired, r.device or "-",
             ("drift", "yellow") if r.device_raw is not None else "not readable"] for r in rows]


def diff_fleet(rec: Recipe, jobs: Sequence[Job], *, parallel: int, as_json: bool) -> int:
    """One table for the whole fleet; exit 2 naming every drifted device, 3 if any could not be read."""
    from .api import diff_values, read_jobs

    values = read_fleet(read_jobs(jobs), parallel)
    rows = {j.name: diff_values(j.recipe, v) for j in jobs if not isinstance(v := values[j.name], Exception)}
    drifted = [n for n, r in rows.items() if any(d.device_raw is not None for d in r)]
    down = _unreachable(values)
    if as_json:
        click.echo(json.dumps({"recipe": rec.path, "devices": [
            {"name": j.name, "url": describe(j.url), "unit": j.unit, "drift": [d.to_json() for d in rows[j.name]]}
            if j.name in rows else {"name": j.name, "url": describe(j.url), "unit": j.unit,
                                    "error": str(values[j.name])} for j in jobs],
            "drifted": drifted, "unreachable": down}, indent=2))
    else:
        out = console()
        show(out, ["device", "parameter", "recipe", "device value", ""],
             [row for j in jobs for row in drift_rows(rows.get(j.name, []), j.name)])
        out.print(f"drift on {len(drifted)} of {len(jobs)} devices" + (f": {', '.join(drifted)}" if drifted else "")
                  + (f"; {len(down)} unreachable: {', '.join(down)}" if down else ""))
    if down:
        return EXIT_UNREACHABLE
    return EXIT_CHANGES if drifted else EXIT_OK


@cli.command()
@click.option("--profile", "profile_ref", metavar="ID|FILE",
              help="the device's profile (with --inventory: for devices whose entry names none)")
@click.option("--device", metavar="URL")
@click.option("--unit", type=click.IntRange(1, 247), help="unit id (default 1, or the inventory's)")
@click.option("--timeout", type=click.FloatRange(min=0, min_open=True))
@click.option("--retries", type=click.IntRange(0, 20))
@click.option("-o", "--output", type=click.Path(), help="write the recipe here (default: stdout); "
              "with --inventory a folder: one NAME.yaml per device")
@click.option("--name", help="the recipe's name (default: pulled-PROFILE)")
@fleet_option
@limit_option
@parallel_option
def pull(profile_ref: str | None, device: str | None, unit: int | None, timeout: float | None, retries: int | None,
         output: str | None, name: str | None, inventory: str | None, limit: str | None, parallel: int) -> int:
    """Read every writable parameter of a device into a recipe that applies back as a no-op."""
    from .api import device_url, pull_names, pulled_recipe
    from .profile import resolve_profile

    if inventory:
        if device or name:
            raise UsageError("with --inventory, --device and --name do not apply (one recipe per device)")
        if not output:
            raise UsageError("with --inventory, pass -o DIR: one recipe per device goes there")
        return pull_fleet(inventory, limit, profile_ref, output, timeout=timeout, retries=retries, unit=unit,
                          parallel=parallel)
    if limit:
        raise UsageError("--limit needs --inventory")
    if not profile_ref or not device:
        raise UsageError("pass --profile ID|FILE and --device URL (or --inventory FILE -o DIR)")
    prof = resolve_profile(profile_ref)
    url = device_url(device, timeout=timeout, retries=retries)
    u = unit if unit is not None else 1
    current = read_device(prof, pull_names(prof), url, u)
    if current is None:
        return EXIT_UNREACHABLE
    text = pulled_recipe(prof, current, name=name or f"pulled-{prof.id}", url=describe(url), unit=u,
                         comment=_pulled_from(describe(url), u), relative_to=output)
    _output(text, output, f"{_n(len(current), 'parameter')} written to {output}")
    return EXIT_OK


def _pulled_from(url: str, unit: int) -> str:
    return f"Pulled from {url} unit {unit} at {time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}"


def pull_fleet(inventory: str, limit: str | None, profile_ref: str | None, folder: str, *, timeout: float | None,
               retries: int | None, unit: int | None, parallel: int) -> int:
    """DIR/NAME.yaml per device, each with the device's profile; exit 3 if any device could not be read."""
    from .api import check_writable, device_url, load_inventory, pull_names, pulled_recipe
    from .executor import ReadJob
    from .profile import resolve_profile

    inv = load_inventory(inventory)
    devices = inv.select(limit)
    profiles: dict[str, Profile] = {}
    jobs: list[ReadJob] = []
    errors: list[Diagnostic] = []
    for dev in devices:
        ref = dev.profile or profile_ref
        try:
            if ref is None:
                raise UsageError("no profile: set profile in the inventory or pass --profile")
            if ref not in profiles:
                profiles[ref] = resolve_profile(ref)
            prof = profiles[ref]
            url = device_url(dev.url, timeout=timeout or dev.timeout,
                             retries=retries if retries is not None else dev.retries)
        except UsageError as e:
            errors.append(Diagnostic(inv.path, *dev.where, f"{dev.name}: {e}"))
            continue
        jobs.append(ReadJob(dev.name, prof, tuple(pull_names(prof)), url, unit if unit is not None else dev.unit))
    if errors:
        raise InputError(errors)
    check_writable(folder, f"recipes into {folder}")
    values = read_fleet(jobs, parallel)
    written = 0
    for j in jobs:
        cur = values[j.name]
        if isinstance(cur, Exception):
            continue
        path = os.path.join(folder, f"{_safe(j.name)}.yaml")
        text = pulled_recipe(j.profile, cur, name=f"pulled-{j.name}", url=describe(j.url), unit=j.unit,
                             comment=_pulled_from(describe(j.url), j.unit), relative_to=path)
        with open(path, "w", encoding="utf-8") as f:
            f.write(text)
        written += 1
    down = _unreachable(values)
    click.echo(f"{written} recipes written to {folder}" + (f"; {len(down)} unreachable: {', '.join(down)}"
                                                          if down else ""), err=True)
    return EXIT_UNREACHABLE if down else EXIT_OK


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


@cli.command()
@click.option("--fast", is_flag=True, hidden=True, help="no pauses between steps (tests)")
def demo(fast: bool) -> int:
    """The whole story against a built-in simulated device: validate, plan, apply, verify, drift, rollback."""
    from .demo import run_demo

    return run_demo(fast=fast)



_ARGV: list[str] = []  # the command line, for the audit log
_OWN_PROCESS: list[bool] = []  # main() without argv: this process is the command, not a caller's


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point: map every user error to its exit code, never a traceback."""
    if argv is None:
        _OWN_PROCESS[:] = [True]
    try:
        _main(argv)
    finally:
        if argv is None:  # the process itself (not a test calling in): its objects end with it, so the
            import gc  # interpreter's last collection need not walk them (40 ms after a 200-device fleet)

            gc.freeze()


def _main(argv: Sequence[str] | None) -> None:
    _ARGV[:] = list(argv) if argv is not None else sys.argv[1:]
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
