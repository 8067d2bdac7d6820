"""Commands for devices that do not follow the book: what they taught (learned), scan, probe."""

from __future__ import annotations

import json

import click

from ..errors import EXIT_OK, UsageError
from .base import TIMEOUT, console, echo, safe
from .tables import show

_STATE = click.option(
    "--state-dir",
    default=".deployer",
    show_default=True,
    type=click.Path(file_okay=False),
    help="the state directory apply keeps what devices taught in",
)


@click.group()
def learned() -> None:
    """Limits devices taught by their refusals (STATE/learned.json): list or forget them."""


@learned.command("list")
@_STATE
@click.option("--json", "as_json", is_flag=True, help="print the entries as JSON")
def learned_list(state_dir: str, as_json: bool) -> int:
    """What each device taught: profile, device, limits, what was seen, when."""
    from ..api.commands import learned_limits

    path, entries = learned_limits(state_dir)
    if as_json:
        echo(json.dumps([e.to_json() for e in entries], indent=2))
        return EXIT_OK
    out = console()
    if not entries:
        out.print(f"nothing learned in {safe(path)}")
        return EXIT_OK
    show(
        out,
        ["profile", "device", "limits", "seen", "when"],
        [[e.profile, e.device, e.describe_limits(), e.seen, e.when] for e in entries],
    )
    return EXIT_OK


@learned.command("forget")
@_STATE
@click.option("--profile", "profile", metavar="PROFILE", help="only this profile (a built-in id or a file)")
@click.option("--device", "device", metavar="URL", help="only this device (with --unit)")
@click.option("--unit", type=click.IntRange(1, 247), default=1, show_default=True, help="the device's unit id")
@click.option("--all", "everything", is_flag=True, help="forget everything learned")
def learned_forget(state_dir: str, profile: str | None, device: str | None, unit: int, everything: bool) -> int:
    """Forget what devices taught: the next plan and apply use the profile's own limits again."""
    from ..api.commands import forget_learned
    from ..errors import BadURL

    if not (profile or device or everything):
        raise UsageError("say what to forget: --profile PROFILE, --device URL [--unit N], or --all")
    try:
        gone = forget_learned(state_dir, profile=profile or None, device=device or None, unit=unit)
    except BadURL as e:
        raise UsageError(str(e)) from None
    out = console()
    for entry in gone:
        if not entry.limits:  # forget --all of a file deployer did not write
            out.print(f"cleared {safe(entry.device)}: it was not a learned file deployer wrote")
            continue
        out.print(f"forgot {entry.describe_limits()} of {safe(entry.device)} ({safe(entry.profile)})")
    if not gone:
        out.print("nothing matched: nothing was forgotten")
    return EXIT_OK


def _unit_ids(specs: tuple[str, ...]) -> list[int]:
    """``--unit 1-247``, ``--unit 5 --unit 9``, ``--unit 1,3,10-12``: unit ids in the order given, each once."""
    out: list[int] = []
    for spec in specs or ("1-247",):
        for part in spec.split(","):
            lo, dash, hi = part.strip().partition("-")
            try:
                first, last = int(lo), int(hi if dash else lo)
            except ValueError:
                raise UsageError(f"--unit {spec}: expected a unit id or a range, e.g. 5 or 1-247") from None
            if not 1 <= first <= last <= 247:
                raise UsageError(f"--unit {spec}: unit ids are 1..247, a range low-high")
            out += [u for u in range(first, last + 1) if u not in out]
    return out


@click.command()
@click.argument("url", required=False)
@click.option(
    "--list-ports",
    is_flag=True,
    help="list this system's serial ports (COM3, /dev/ttyUSB0) with their adapters instead of scanning",
)
@click.option(
    "--unit",
    "units",
    multiple=True,
    metavar="IDS",
    help="unit ids to ask: 7, 1-32, 1,3,10-12 (repeatable; default 1-247)",
)
@click.option(
    "--timeout",
    type=click.FloatRange(min=0.001, max=60),
    default=0.2,
    show_default=True,
    help="seconds to wait for each unit (a silent unit costs this once)",
)
@click.option(
    "--register",
    type=click.IntRange(0, 65535),
    default=0,
    show_default=True,
    help="the holding register each unit is asked for (any answer, an exception too, counts)",
)
@click.option(
    "-o",
    "--output",
    "output",
    type=click.Path(dir_okay=False),
    help="write an inventory fragment of the units that answered",
)
@click.option("--json", "as_json", is_flag=True, help="print the result as JSON")
def scan(
    url: str | None,
    list_ports: bool,
    units: tuple[str, ...],
    timeout: float,
    register: int,
    output: str | None,
    as_json: bool,
) -> int:
    """Which unit ids answer on URL (a serial bus or a gateway), with their identity (Function 43).

    Read-only. Each unit costs one FC03 request without retry (at most --timeout when silent), then a
    Function 43 request for those that answered. Exit 0 when some unit answered, 3 when none did.
    With --list-ports (no URL): the serial ports this system has (exit 0, or 3 when it has none).
    """
    if list_ports:
        if url is not None:
            raise UsageError("--list-ports lists this system's serial ports: give it without a URL")
        return _list_ports(as_json)
    if url is None:
        raise UsageError("scan needs a URL (rtu://COM3, rtu:///dev/ttyUSB0, rtu+tcp://GATEWAY:PORT), or --list-ports")
    from ..api.commands import device_url as parse_url
    from ..api.commands import scan as run_scan
    from ..errors import EXIT_UNREACHABLE, BadURL, TransportError

    ids = _unit_ids(units)
    try:
        device_url = parse_url(url, timeout=timeout)
    except BadURL as e:
        raise UsageError(str(e)) from None
    err = console(stderr=True)
    err.print(
        f"asking {len(ids)} unit id{'s' if len(ids) != 1 else ''} on {safe(url)} "
        f"(at most {len(ids) * device_url.timeout:.1f} s)"
    )
    try:
        result = run_scan(device_url, ids, register=register)
    except TransportError as e:
        echo(f"error: {safe(e)}", err=True)
        return EXIT_UNREACHABLE
    if output:
        from ..api.commands import write_output as write_atomic

        write_atomic(output, result.inventory_text(url))
    if as_json:
        echo(
            json.dumps(
                {
                    "url": result.url,
                    "asked": result.asked,
                    "seconds": round(result.seconds, 3),
                    "units": [{"unit": u.unit, "answer": u.answer, "identity": u.identity} for u in result.units],
                },
                indent=2,
            )
        )
    else:
        out = console()
        if result.units:
            show(
                out,
                ["unit", "answer", "vendor", "product code", "revision"],
                [
                    [
                        str(u.unit),
                        u.answer,
                        *((u.identity or {}).get(k, "-") for k in ("vendor", "product_code", "revision")),
                    ]
                    for u in result.units
                ],
            )
        out.print(
            f"{len(result.units)} of {result.asked} unit ids answered on {safe(result.url)} "
            f"in {result.seconds:.1f} s" + (f"; inventory written to {safe(output)}" if output else "")
        )
    return EXIT_OK if result.units else EXIT_UNREACHABLE


def _list_ports(as_json: bool) -> int:
    from ..api.commands import serial_ports
    from ..errors import EXIT_UNREACHABLE

    ports = serial_ports()
    if as_json:
        echo(json.dumps([p.to_json() for p in ports], indent=2))
    elif ports:
        show(
            console(),
            ["port", "URL", "description", "hardware id"],
            [[p.device, p.url, p.description, p.hwid] for p in ports],
        )
    else:
        echo("no serial ports found (a USB adapter that is plugged in but not listed needs its driver)", err=True)
    return EXIT_OK if ports else EXIT_UNREACHABLE


@click.command()
@click.argument("profile")
@click.option("--device", "device", metavar="URL", required=True, help="the live device to check the profile against")
@click.option("--unit", type=click.IntRange(1, 247), default=1, show_default=True, help="its unit id")
@click.option(
    "--expect",
    "expect",
    multiple=True,
    metavar="NAME=VALUE",
    help="a value you know the device holds (e.g. read on its panel), in the parameter's unit: "
    "finds the byte/word layout or scale that gives it. Repeatable.",
)
@click.option("--timeout", type=TIMEOUT, help="seconds per attempt")
@click.option("--json", "as_json", is_flag=True, help="print the findings as JSON")
def probe(profile: str, device: str, unit: int, expect: tuple[str, ...], timeout: float | None, as_json: bool) -> int:
    """Check PROFILE against a live device, read-only, and suggest profile changes.

    Reads the identity (registers and Function 43), every readable parameter (registers answering
    02, values outside their declared range) and, for --expect NAME=VALUE, which byte/word layout or
    scale gives that value. Exit 0 when the profile fits, 2 when changes are suggested, 3 when the
    device does not answer. Nothing is written.
    """
    from ..api import load_profile
    from ..api.commands import device_url as parse_url
    from ..api.commands import probe as run_probe
    from ..errors import EXIT_CHANGES, EXIT_UNREACHABLE, BadURL, TransportError

    prof = load_profile(profile)
    wanted: dict[str, str] = {}
    for item in expect:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise UsageError(f"--expect {item}: expected NAME=VALUE, e.g. --expect F07='10 s'")
        if prof.get(name.strip()) is None:
            raise UsageError(f"--expect {item}: profile {prof.id} has no parameter {name.strip()!r}")
        wanted[name.strip()] = value
    try:
        url = parse_url(device, timeout=timeout)
    except BadURL as e:
        raise UsageError(str(e)) from None
    try:
        result = run_probe(prof, url, unit, expect=wanted)
    except TransportError as e:
        echo(f"error: {safe(e)}", err=True)
        return EXIT_UNREACHABLE
    changes = result.changes
    if as_json:
        echo(
            json.dumps(
                {
                    "profile": prof.id,
                    "identity": result.identity,
                    "values": result.values,
                    "findings": [{"parameter": f.name, "seen": f.what, "change": f.change} for f in result.findings],
                    "changes": changes,
                },
                indent=2,
            )
        )
    else:
        out = console()
        ident = ", ".join(f"{safe(k)} {safe(repr(v))}" for k, v in (result.identity or {}).items())
        out.print(
            f"profile {safe(prof.id)} against {safe(device)} unit {unit}: identity "
            f"{ident or 'none (no Function 43)'}; "
            f"{len(result.values)} of {sum(1 for p in prof.parameters if p.readable)} readable parameters read"
        )
        for f in result.findings:
            out.print(f"  {safe(f.what)}")
        if changes:
            out.print("suggested profile changes:")
            for c in changes:
                out.print(f"  - {safe(c)}")
        else:
            out.print("the profile fits what the device answers")
    return EXIT_CHANGES if changes else EXIT_OK
