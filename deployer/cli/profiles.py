"""The ``profiles`` group: list, show, new, import (csv, xlsx, sunspec) and export."""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import click

from ..load.diagnostics import EXIT_OK, EXIT_UNREACHABLE, UsageError
from .base import _n, _output, console, read_device
from .tables import Cell, show


@click.group()
def profiles() -> None:
    """The built-in device profiles, and importing new ones."""


@profiles.command("list")
def profiles_list() -> int:
    """List the built-in profiles."""
    from ..profile import builtin_profile, builtin_profile_ids

    rows: list[list[Cell]] = []
    for pid in builtin_profile_ids():
        prof = builtin_profile(pid)
        first = prof.description.split(". ")[0].rstrip(".")
        rows.append([pid, str(len(prof.parameters)), first])
    show(console(), ["profile", "parameters", "description"], rows)
    return EXIT_OK


def _type_text(p: Any) -> str:
    """'uint32 CDAB', 'bool bit 3', 'uint16 bits 3..5', 'string[8] ascii' (the layout only when not the default)."""
    from ..profile.codec import mask_shift

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

    from ..profile.emit import check

    pid = str(draft.header["profile"])
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", pid):  # the profile schema's pattern
        raise UsageError(f"--id '{pid}': letters, digits, '.', '_' and '-', starting with a letter or digit")

    for w in warnings:
        click.echo(f"warning: {w}", err=True)
    text, prof = check(draft, out or "<stdout>", f"Imported by 'deployer profiles import' from {source}.\n"
                                                "Check it against the manual before the first deployment.")
    _output(text, out, f"{out}: profile {prof.id} with {_n(len(prof.parameters), 'parameter')}")
    return EXIT_OK


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
    from ..profile.importers.spreadsheet import read_csv

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
    from ..profile.importers.spreadsheet import read_xlsx

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
    from ..profile import resolve_profile
    from ..profile.importers.spreadsheet import profile_to_csv

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
    from ..profile import parse_register
    from ..profile.importers.sunspec import read_model

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
    from ..profile.codec import decode
    from ..profile.emit import check
    from ..profile.importers.sunspec import read_model, scale_factor_points
    from ..transport.clients import parse_url

    url = parse_url(device)  # BadURL is a UsageError
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
    from ..profile import resolve_profile
    from ..profile.codec import format_decimal, layout_name
    from ..profile.model import address_text

    prof = resolve_profile(profile)
    out = console()
    out.print(f"[bold]{prof.id}[/bold]: {prof.description}")
    lim = prof.limits
    layout = layout_name(prof.word_order, prof.byte_swap)
    out.print(f"addressing {prof.addressing}, byte order {layout}; up to {lim.write_registers} registers "
              f"per write (FC{lim.write_function:02d}), {lim.read_registers} per read"
              + (f"; {lim.write_coils} coils per write (FC15), {lim.read_coils} per read"
                 if any(p.register_type == "coil" for p in prof.parameters) else ""))
    rows: list[list[Cell]] = []
    for p in prof.parameters:
        rng = "" if p.min is None and p.max is None else (
            f"{'' if p.min is None else format_decimal(p.min)}..{'' if p.max is None else format_decimal(p.max)}")
        if p.values:
            rng = ", ".join(f"{label}={raw}" for label, raw in p.values)
        default = "" if p.default is None else p.default if isinstance(p.default, str) else (
            str(bool(p.default)).lower() if p.type == "bool" else format_decimal(p.default))
        rows.append([p.name, address_text(p.register_type, p.address), _type_text(p), p.unit or "",
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

    from ..load.schema import schema
    from ..profile.skeleton import profile_skeleton

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
