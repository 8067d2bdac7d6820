"""simulate, and demo (the whole story against a built-in simulated device)."""

from __future__ import annotations

import asyncio

import click

from ..errors import EXIT_INVALID, EXIT_OK, UsageError
from .base import echo, safe


def _register(text: str) -> int:
    from ..testing.simulator import parse_address

    try:
        return parse_address(text)
    except ValueError:
        raise click.BadParameter(f"not a register address: {text!r} (e.g. 4354, 0x1102, 1102h)") from None


@click.command()
@click.argument("profile")
@click.option(
    "--listen",
    default="tcp://127.0.0.1:5020",
    show_default=True,
    metavar="URL",
    help="tcp://HOST:PORT, rtu+tcp://HOST:PORT, rtu:///dev/X?baudrate=B, ascii:///dev/X",
)
@click.option("--unit", "units", type=click.IntRange(1, 247), multiple=True, help="unit id(s) served (default 1)")
@click.option("--init", "init_recipe", type=click.Path(dir_okay=False), help="start with a recipe's values")
@click.option(
    "--set",
    "set_registers",
    multiple=True,
    metavar="[TABLE:]ADDR=RAW",
    help="start a register (protocol address) with a raw value, read-only ones too, e.g. a status word "
    "saying 'running': --set 0x10=8; another table with a prefix: --set coil:19=1, discrete:196=1, "
    "input:8=215. Repeatable.",
)
@click.option("--latency-ms", type=click.FloatRange(min=0), default=0, help="delay every answer")
@click.option("--baud", type=click.IntRange(min=50), help="delay answers by their line time at this baud rate (8E1)")
@click.option("--drop-every", type=click.IntRange(min=0), default=0, help="never answer every Nth request")
@click.option("--busy-first", type=click.IntRange(min=0), default=0, help="answer the first N writes with 06 (busy)")
@click.option(
    "--fail-register",
    "fail_registers",
    multiple=True,
    metavar="ADDR",
    help="writes reaching this wire address answer 04 (repeatable; 4354, 0x1102 or 1102h)",
)
@click.option(
    "--fault",
    "fault_rules",
    multiple=True,
    metavar="RULE",
    help="after a write, set a register when a condition on a parameter holds, e.g. "
    "'F07 < 2 s: 48=7' (the drive trips on a short acceleration time; wire address=raw). Repeatable.",
)
@click.option("--disconnect-after", type=click.IntRange(min=0), default=0, help="drop the connection every N requests")
@click.option("--state", "state_path", type=click.Path(dir_okay=False), help="dump registers as JSON on exit/SIGUSR1")
@click.option("--log", "log_path", type=click.Path(dir_okay=False), help="one JSON line per request")
@click.option("--loose-limits", is_flag=True, help="accept requests beyond the profile's limits")
@click.option("--gap-reads", is_flag=True, help="answer reads of undeclared registers between declared ones (zeros)")
@click.option(
    "--max-write-registers",
    type=click.IntRange(1, 123),
    default=None,
    metavar="N",
    help="quirk: FC16 writes of more than N registers answer 03 and write nothing, whatever the profile says",
)
@click.option(
    "--all-or-nothing",
    is_flag=True,
    help="quirk: one bad value refuses the whole write (03) and nothing of it is written",
)
@click.option("--fc06-only", is_flag=True, help="quirk: Function 16 answers 01 (illegal function); only FC06 writes")
@click.option(
    "--pause-after-connect",
    metavar="DURATION",
    default="0",
    help="quirk: requests sooner after a connection opens are not answered (250ms, 1s)",
)
@click.option(
    "--pause-between-requests",
    metavar="DURATION",
    default="0",
    help="quirk: requests sooner after the previous answer are not answered (250ms, 1s)",
)
@click.option(
    "--max-connections",
    type=click.IntRange(min=0),
    default=0,
    metavar="N",
    help="quirk: serve N TCP connections at once, close any more as they open (a gateway's limit); 0: any",
)
@click.option(
    "--silent-function",
    "silent",
    type=click.IntRange(1, 127),
    multiple=True,
    metavar="FC",
    help="quirk: requests of this function code are never answered (a device that lacks Function 43 and "
    "stays silent: --silent-function 43). Repeatable.",
)
@click.option(
    "--nonvolatile",
    is_flag=True,
    help="keep RAM and non-volatile memory apart: writes reach RAM, the profile's commit stores them, and "
    "a power cycle (SIGUSR2) brings back what was stored",
)
@click.option(
    "--identity",
    "identity",
    multiple=True,
    metavar="OBJECT=TEXT",
    help="Function 43 objects to answer (vendor, product_code, revision, ... or an id 0..255), e.g. "
    "--identity vendor=ACME; default: the profile's identity objects, else the device answers 01. "
    "Repeatable.",
)
def simulate(
    profile: str,
    listen: str,
    units: tuple[int, ...],
    init_recipe: str | None,
    set_registers: tuple[str, ...],
    latency_ms: float,
    baud: int | None,
    drop_every: int,
    busy_first: int,
    fail_registers: tuple[str, ...],
    disconnect_after: int,
    state_path: str | None,
    log_path: str | None,
    loose_limits: bool,
    gap_reads: bool,
    max_write_registers: int | None,
    all_or_nothing: bool,
    fc06_only: bool,
    pause_after_connect: str,
    pause_between_requests: str,
    identity: tuple[str, ...],
    fault_rules: tuple[str, ...] = (),
    max_connections: int = 0,
    silent: tuple[int, ...] = (),
    nonvolatile: bool = False,
) -> int:
    """Serve a simulated device for PROFILE (a built-in id or a file) until Ctrl-C."""
    from ..api import load_profile, load_recipe
    from ..load.durations import parse_duration
    from ..testing.simulator import (
        Faults,
        Quirks,
        Simulator,
        init_from_recipe,
        parse_fault_rule,
        parse_identity,
        parse_listen,
        parse_set,
        serve,
    )

    prof = load_profile(profile)
    try:
        parse_listen(listen)
    except ValueError as e:
        raise UsageError(str(e)) from None
    init = init_from_recipe(load_recipe(init_recipe)) if init_recipe else {}
    for item in set_registers:
        try:
            key, value = parse_set(item)
        except ValueError as e:
            raise UsageError(str(e)) from None
        init[key] = value
    try:
        rules = tuple(parse_fault_rule(r, prof) for r in fault_rules)
    except ValueError as e:
        raise UsageError(f"--fault {e}") from None
    faults = Faults(
        latency_ms=latency_ms,
        baud=baud,
        drop_every=drop_every,
        busy_first=busy_first,
        fail_registers=frozenset(_register(r) for r in fail_registers),
        disconnect_after=disconnect_after,
        rules=rules,
    )
    pauses = []
    for option, text in (
        ("--pause-after-connect", pause_after_connect),
        ("--pause-between-requests", pause_between_requests),
    ):
        try:
            pauses.append(parse_duration(text) * 1000)
        except ValueError as e:
            raise UsageError(f"{option}: {e}") from None
    try:
        objects = parse_identity(identity)
    except ValueError as e:
        raise UsageError(str(e)) from None
    quirks = Quirks(
        max_write_registers=max_write_registers or 0,
        all_or_nothing=all_or_nothing,
        fc06_only=fc06_only,
        pause_after_connect_ms=pauses[0],
        request_gap_ms=pauses[1],
        max_connections=max_connections,
        identity=objects,
        silent_functions=frozenset(silent),
    )
    try:
        sim = Simulator(
            prof,
            listen=listen,
            units=units or (1,),
            init=init,
            faults=faults,
            log_path=log_path,
            state_path=state_path,
            strict_limits=not loose_limits,
            gap_reads=gap_reads,
            quirks=quirks,
            nonvolatile=nonvolatile,
        )
    except ValueError as e:  # a --set register the profile does not declare
        raise UsageError(str(e)) from None

    def ready(s: Simulator) -> None:
        which = ", ".join(str(u) for u in s.units)
        echo(
            f"simulating {safe(prof.id)} unit{'s' if len(s.units) > 1 else ''} {which} on {safe(s.url)} "
            "(Ctrl-C to stop" + ("; SIGUSR2: a power cycle" if s.nonvolatile else "") + ")",
            err=True,
        )

    try:
        asyncio.run(serve(sim, on_ready=ready))
    except (OSError, RuntimeError) as e:
        echo(f"error: cannot listen on {safe(listen)}: {safe(e)}", err=True)
        return EXIT_INVALID
    return EXIT_OK


@click.command()
@click.option("--fast", is_flag=True, hidden=True, help="no pauses between steps (tests)")
@click.option(
    "--keep",
    "keep",
    metavar="DIR",
    default=None,
    help="write the demo's files (recipes, state folder, audit log) into DIR and keep them; "
    "by default they go in a temporary folder removed at the end",
)
def demo(fast: bool, keep: str | None) -> int:
    """The whole story against a built-in simulated device: validate, plan, apply, verify, drift, rollback."""
    from .demo import run_demo

    return run_demo(fast=fast, keep=keep)
