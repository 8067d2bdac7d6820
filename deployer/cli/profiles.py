"""The ``profiles`` group: list, show, new, import (csv, xlsx, sunspec) and export."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, Any

import click

from ..errors import EXIT_INVALID, EXIT_OK, EXIT_UNREACHABLE, InputError, TransportError, UsageError
from .base import _n, _output, console, echo, force_option, report_input_error, safe
from .tables import Cell, show

if TYPE_CHECKING:
    from ..api import Profile


@click.group()
def profiles() -> None:
    """The built-in device profiles, and importing new ones."""


@profiles.command("list")
def profiles_list() -> int:
    """List the built-in profiles."""
    from ..api.commands import builtin_profiles

    rows: list[list[Cell]] = []
    for prof in builtin_profiles():
        first = prof.description.split(". ")[0].rstrip(".")
        rows.append([prof.id, str(len(prof.parameters)), first])
    show(console(), ["profile", "parameters", "description"], rows)
    return EXIT_OK


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


_decimal_option = click.option(
    "--decimal-comma/--decimal-point",
    "decimal",
    default=None,
    help="The decimal mark of every number cell. Default: '.', and ',' where it cannot be a thousands "
    "separator (0,5 or 1.000,5); a cell such as 3,000 is then an error at its position.",
)


def _mark(decimal: bool | None) -> str | None:
    return None if decimal is None else "comma" if decimal else "point"


@contextlib.contextmanager
def _import_errors() -> Iterator[None]:
    """An import's bad input: every problem at its position, and no device was ever involved."""
    try:
        yield
    except InputError as e:
        report_input_error(e, "no profile was written")
        raise SystemExit(EXIT_INVALID) from None


def _write_imported(draft: Any, out: str | None, source: str, warnings: Sequence[str] = ()) -> int:
    import re

    from ..api.commands import imported_profile

    pid = str(draft.header["profile"])
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", pid):  # the profile schema's pattern
        raise UsageError(f"--id '{pid}': letters, digits, '.', '_' and '-', starting with a letter or digit")

    for w in warnings:
        echo(safe(w) if ": warning: " in w else f"warning: {safe(w)}", err=True)
    text, prof = imported_profile(
        draft,
        out or "<stdout>",
        f"Imported by 'deployer profiles import' from {source}.\n"
        "Check it against the manual before the first deployment.",
    )
    _output(text, out, f"{out}: profile {prof.id} with {_n(len(prof.parameters), 'parameter')}")
    return EXIT_OK


@profiles_import.command("csv")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--id", "profile_id", required=True, help="Profile id to write (e.g. acme-drive).")
@click.option("-o", "--out", help="Profile file to write (default: stdout).")
@force_option
@click.option(
    "--column",
    "columns",
    multiple=True,
    metavar="OURS=HEADER",
    help="Which header holds a column, e.g. --column address='Reg No'. Repeatable.",
)
@click.option(
    "--addressing",
    type=click.Choice(["address", "register-number", "modicon"]),
    default="address",
    show_default=True,
    help="How the address column counts.",
)
@click.option("--delimiter", help="Cell separator (default: sniffed from , ; or tab).")
@click.option(
    "--byte-order",
    help="Layout of rows without a byte_order cell: ABCD, CDAB, BADC, DCBA (or none, byte, word, word_byte).",
)
@_decimal_option
def profiles_import_csv(
    file: str,
    profile_id: str,
    out: str | None,
    columns: Sequence[str],
    addressing: str,
    delimiter: str | None,
    byte_order: str | None,
    decimal: bool | None,
) -> int:
    """A profile from a CSV register list (columns: name, address, type, unit, scale, min, max, range, access ...)."""
    from ..api.commands import import_csv

    with _import_errors():
        draft, warnings = import_csv(
            file,
            profile_id=profile_id,
            columns=_pairs(columns, "--column"),
            addressing=addressing,
            delimiter=delimiter,
            byte_order=byte_order,
            decimal=_mark(decimal),
        )
        return _write_imported(draft, out, file, warnings)


@profiles_import.command("xlsx")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--id", "profile_id", required=True, help="Profile id to write (e.g. acme-drive).")
@click.option("--sheet", help="Worksheet to read (default: the first).")
@click.option("-o", "--out", help="Profile file to write (default: stdout).")
@force_option
@click.option(
    "--column",
    "columns",
    multiple=True,
    metavar="OURS=HEADER",
    help="Which header holds a column, e.g. --column address='Reg No'. Repeatable.",
)
@click.option(
    "--addressing",
    type=click.Choice(["address", "register-number", "modicon"]),
    default="address",
    show_default=True,
    help="How the address column counts.",
)
@click.option(
    "--byte-order",
    help="Layout of rows without a byte_order cell: ABCD, CDAB, BADC, DCBA (or none, byte, word, word_byte).",
)
@_decimal_option
def profiles_import_xlsx(
    file: str,
    profile_id: str,
    sheet: str | None,
    out: str | None,
    columns: Sequence[str],
    addressing: str,
    byte_order: str | None,
    decimal: bool | None,
) -> int:
    """A profile from an Excel register list (the same columns as csv; needs openpyxl)."""
    from ..api.commands import import_xlsx

    with _import_errors():
        draft, warnings = import_xlsx(
            file,
            profile_id=profile_id,
            sheet=sheet,
            columns=_pairs(columns, "--column"),
            addressing=addressing,
            byte_order=byte_order,
            decimal=_mark(decimal),
        )
        return _write_imported(draft, out, file, warnings)


@profiles_import.command("wb-template")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--id", "profile_id", help="Profile id to write (default: the template's device_type).")
@click.option("-o", "--out", help="Profile file to write (default: stdout).")
@force_option
@click.option(
    "--no-channels",
    is_flag=True,
    help="Leave out the polled channels (read-only values); keep the parameters (settings) only.",
)
def profiles_import_wb_template(file: str, profile_id: str | None, out: str | None, no_channels: bool) -> int:
    """A profile from a wb-mqtt-serial device template (JSON with // comments): parameters become settings,
    channels read-only values.

    wb-mqtt-serial's templates are under the MIT-WB licence, which allows their use on Wiren Board
    controllers only: check that it allows yours before importing one (docs/importers.md)."""
    from ..api.commands import import_wb_template

    draft, warnings = import_wb_template(file, profile_id=profile_id, channels=not no_channels)
    return _write_imported(draft, out, file, warnings)


@profiles.group("export")
def profiles_export() -> None:
    """Write a profile in another format."""


@profiles_export.command("csv")
@click.argument("profile")
@click.option("-o", "--out", help="CSV file to write (default: stdout).")
@force_option
def profiles_export_csv(profile: str, out: str | None) -> int:
    """A profile as a CSV register list ('profiles import csv' reads it back; wire addresses, tables as rows)."""
    from ..api import load_profile
    from ..api.commands import profile_csv

    prof = load_profile(profile)
    text, lost = profile_csv(prof)
    for what in lost:
        echo(
            f"warning: {safe(prof.source or prof.id)}: {safe(what)}: not in a register list; importing the list "
            "will not bring it back",
            err=True,
        )
    _output(text, out, f"{out}: {_n(len(prof.parameters), 'register row')} of profile {prof.id}")
    return EXIT_OK


@profiles_import.command("sunspec")
@click.argument("model", required=False)
@click.option(
    "--at",
    "at",
    help="Protocol address of the model's ID register (default 40002: the first model "
    "after 'SunS'; with --device and no MODEL and no --at, 'SunS' is looked for at 40000, 0 and 50000).",
)
@click.option(
    "--sf",
    "sfs",
    multiple=True,
    metavar="NAME=N",
    help="A scale factor the device reports, e.g. --sf WMax_SF=0 (-10 to 10). Repeatable.",
)
@click.option(
    "--count",
    "counts",
    multiple=True,
    metavar="GROUP=N",
    help="Repetitions of a group whose count the device reports, e.g. --count curve=4. Repeatable.",
)
@click.option(
    "--device",
    metavar="URL",
    help="Read the scale factors and group counts from this device (the "
    "model at --at); without MODEL, read the device's whole model chain from 'SunS' (see --at) into one "
    "profile. --sf and --count win over what it says.",
)
@click.option("--unit", type=click.IntRange(1, 247), default=1, show_default=True, help="unit id of --device")
@click.option("--id", "profile_id", help="Profile id (default: sunspec-MODEL-NAME, or sunspec-device).")
@click.option("-o", "--out", help="Profile file to write (default: stdout).")
@force_option
def profiles_import_sunspec(
    model: str | None,
    at: str,
    sfs: Sequence[str],
    counts: Sequence[str],
    device: str | None,
    unit: int,
    profile_id: str | None,
    out: str | None,
) -> int:
    """A profile from a SunSpec model (number, name or model JSON) using pysunspec2's definitions, or from a
    device's whole model chain (--device without MODEL)."""
    from ..api.commands import import_sunspec, import_sunspec_chain, sunspec_reported
    from ..api.commands import register_address as parse_register

    factors = {k: _whole(v, f"--sf {k}") for k, v in _pairs(sfs, "--sf").items()}
    repeats = {k: _whole(v, f"--count {k}") for k, v in _pairs(counts, "--count").items()}
    for k, n in factors.items():
        if not -10 <= n <= 10:  # the SunSpec specification's scale factors (sunssf)
            raise UsageError(f"--sf {k}={n}: a SunSpec scale factor is -10 to 10")
    for k, n in repeats.items():
        if not 1 <= n <= 65535:
            raise UsageError(f"--count {k}={n}: a group repeats 1 to 65535 times")
    try:
        address = parse_register(at or "40002")
    except ValueError:
        address = -1
    if not 2 <= address <= 0xFFFF:
        raise UsageError(f"--at {_clip(at or '')}: not a register address (40002, 0x9C42 or 9C42h)")
    if model is None and device is None:
        raise UsageError(
            "give a MODEL (121, settings or a model JSON file), or --device URL to read the device's models"
        )
    with _import_errors():
        if device is not None:
            got = _from_device(device, unit, address, model, search=at is None)
            if got is None:
                return EXIT_UNREACHABLE
            if model is None:
                chain = ", ".join(f"{m.model_id} at {m.at} (L={m.length})" for m in got[0])
                echo(f"models on {safe(device)}: {safe(chain or 'none')}", err=True)
                draft, warnings = import_sunspec_chain(
                    got[0], scale_factors=factors, counts=repeats, profile_id=profile_id, source=device
                )
                return _write_imported(draft, out, f"the SunSpec device {device}", warnings)
            (dm,) = got[0]
            found, points, warnings = sunspec_reported(model, dm)
            echo(
                f"scale factors from {safe(device)}: " + ", ".join(f"{safe(n)}={v}" for n, v in found.items()), err=True
            )
            draft, more = import_sunspec(
                model,
                at=address,
                scale_factors={**found, **factors},
                counts=repeats,
                point_values=points,
                length=dm.length,
                profile_id=profile_id,
            )
            return _write_imported(draft, out, f"SunSpec model {model}", [*warnings, *more])
        draft, warnings = import_sunspec(
            model or "", at=address, scale_factors=factors, counts=repeats, profile_id=profile_id
        )
        return _write_imported(draft, out, f"SunSpec model {model}", warnings)


def _clip(text: str, limit: int = 60) -> str:
    from ..load.messages import clip

    return clip(text, limit)


def _whole(text: str, what: str) -> int:
    import re

    if not re.fullmatch(r"[-+]?[0-9]{1,18}", text.strip()):
        raise UsageError(f"{_clip(what)}={_clip(text)}: a whole number")
    return int(text)


def _from_device(
    device: str, unit: int, at: int, model: str | None, *, search: bool = False
) -> tuple[list[Any]] | None:
    """The device's model at ``at`` (MODEL given) or its whole chain; None (after saying why) when unreachable."""
    from ..api.commands import sunspec_models

    try:
        return (sunspec_models(device, unit, at=at, model=model, search=search),)
    except TransportError as e:
        echo(f"error: {safe(e)}", err=True)
        return None


@profiles.command("show")
@click.argument("profile")
def profiles_show(profile: str) -> int:
    """Show a profile's parameters in engineering units (a built-in id or a file)."""
    from ..api import load_profile

    prof = load_profile(profile)
    out = console()
    from .text import styled

    out.print(styled((prof.id, "bold"), f": {prof.description}"))
    lim = prof.limits
    layout, table = profile_table(prof)
    out.print(
        f"addressing {prof.addressing}, byte order {layout}; up to {_n(lim.write_registers, 'register')} "
        f"per write (FC{lim.write_function:02d}), {lim.read_registers} per read"
        + (
            f"; {lim.write_coils} coils per write (FC15), {lim.read_coils} per read"
            if any(p.register_type == "coil" for p in prof.parameters)
            else ""
        )
    )
    rows: list[list[Cell]] = [list(row) for row in table]
    heads = ["parameter", "address", "type", "unit", "resolution", "range", "access", "default", "description"]
    if any(p.manual for p in prof.parameters):  # beside the key: the parameter as the manual names it
        heads.insert(1, "manual")
        for row, p in zip(rows, prof.parameters, strict=True):
            row.insert(1, p.manual)
    show(out, heads, rows)
    return EXIT_OK


@profiles.command("new")
@click.argument("output", type=click.Path(dir_okay=False))
@click.option("--id", "profile_id", help="the profile's id (default: the file name without .yaml)")
@click.option("--force", is_flag=True, help="overwrite an existing file")
def profiles_new(output: str, profile_id: str | None, force: bool) -> int:
    """Write a commented profile skeleton to OUTPUT, ready to fill in from the device's manual."""
    import re

    from ..api.commands import profile_skeleton
    from ..api.commands import write_output as write_atomic
    from ..load.schema import schema

    pid = profile_id or os.path.splitext(os.path.basename(output))[0]
    pattern = schema("profile")["properties"]["profile"]["pattern"]
    if not re.match(pattern, pid):
        raise UsageError(f"'{pid}' is not a profile id (letters, digits, '.', '_', '-'); pass --id ID")
    text = profile_skeleton(pid, output)
    write_atomic(output, text, replace=force)
    echo(f"wrote {safe(output)}: fill it in from the manual, then run: deployer validate {safe(output)}", err=True)
    return EXIT_OK


def profile_table(profile: str | Profile) -> tuple[str, list[list[str]]]:
    """A profile as ``profiles show`` lists it: the name of its byte order (ABCD, CDAB ...) and one row of text
    per parameter: name, address (as plans write it), type ('uint32 CDAB', 'bool bit 3', 'uint16 bits 3..5',
    'string[8] ascii'), unit, resolution, range (or its labels), access, default and description.

    Raises:
        UsageError: an unknown profile.
        InputError: a profile file that is not valid.
    """
    from ..api import Profile, load_profile
    from ..api.commands import address_text, format_decimal, layout_name, mask_shift

    prof = profile if isinstance(profile, Profile) else load_profile(profile)

    def type_text(p: Any) -> str:  # the layout only when not the default
        if p.is_string:
            return f"string[{p.count}] {p.encoding}" + (" BA" if p.byte_swap else "")
        if p.mask:
            shift, width = mask_shift(p.mask)
            return f"{p.type} bit {shift}" if width == 1 else f"{p.type} bits {shift}..{shift + width - 1}"
        return str(p.type) if p.layout in ("AB", "ABCD", "ABCDEFGH") else f"{p.type} {p.layout}"

    rows: list[list[str]] = []
    for p in prof.parameters:
        rng = (
            ""
            if p.min is None and p.max is None
            else (f"{'' if p.min is None else format_decimal(p.min)}..{'' if p.max is None else format_decimal(p.max)}")
        )
        if p.values:
            rng = ", ".join(f"{label}={raw}" for label, raw in p.values)
        default = (
            ""
            if p.default is None
            else p.default
            if isinstance(p.default, str)
            else (str(bool(p.default)).lower() if p.type == "bool" else format_decimal(p.default))
        )
        rows.append(
            [
                p.name,
                address_text(p.register_type, p.address),
                type_text(p),
                p.unit or "",
                "" if p.is_string or p.type == "bool" else format_decimal(p.scale),
                rng,
                p.access,
                default,
                p.description,
            ]
        )
    return layout_name(prof.word_order, prof.byte_swap), rows
