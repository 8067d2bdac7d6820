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
from rich.console import Console
from rich.table import Table

from .diagnostics import (
    EXIT_CHANGES,
    EXIT_INVALID,
    EXIT_OK,
    EXIT_UNREACHABLE,
    Diagnostic,
    InputError,
    UsageError,
)
from .transport import DeviceURL, TransportError, describe

if TYPE_CHECKING:
    from .planner import Plan
    from .profile import Profile
    from .recipe import Recipe
    from .report import DeviceResult, Report


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
    """Explain a key of a profile, recipe, inventory, plan or report (e.g. max_frame_bytes, profile:scale)."""
    import difflib

    from .docgen import all_keys, find_keys, render_text

    found = find_keys(key)
    if not found:
        names = sorted({k.path for k in all_keys()} | {k.path.rsplit(".", 1)[-1] for k in all_keys()})
        hint = difflib.get_close_matches(key.rpartition(":")[2], names, n=3)
        raise UsageError(f"no key '{key}' in any schema" + (f"; did you mean {', '.join(hint)}?" if hint else
                                                            "; try e.g. 'deployer explain scale'"))
    click.echo("\n\n".join(render_text(k) for k in found))
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


def _target(recipe: Recipe, device: str | None, unit: int | None, timeout: float | None,
            retries: int | None, *, required: bool) -> tuple[DeviceURL | None, int]:
    """The device URL and unit from the options, else the recipe's; parsed before any I/O."""
    from .transport import BadURL, parse_url

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

    try:
        return asyncio.run(read_current(profile, names, url, unit))
    except TransportError as e:
        click.echo(f"error: {e}", err=True)
        return None


def _hexwords(regs: Sequence[int] | None) -> str:
    return "-" if regs is None else " ".join(f"{w:04X}" for w in regs)


def print_plan(plan: Plan, profile: Profile, *, changes_only: bool, out: Console) -> None:
    from .planner import wire_stats

    req_of: dict[str, list[int]] = {}
    for i, w in enumerate(plan.writes, 1):
        for n in w.parameters:
            req_of.setdefault(n, []).append(i)
    table = Table("parameter", "address", "raw", "value", "request", box=None)
    if changes_only:
        table = Table("parameter", "address", "current -> desired", "raw", "action", "request", box=None)
    for pp in plan.parameters:
        if changes_only and pp.action == "unchanged":
            continue
        addr = f"0x{pp.address:04X} ({pp.address})"
        reqs = ",".join(str(i) for i in req_of.get(pp.name, [])) or "-"
        if changes_only:
            p = profile.parameter(pp.name)
            cur = p.format_registers(pp.current_raw) if pp.current_raw is not None else "?"
            table.add_row(pp.name, addr, f"{cur} -> {pp.desired}", _hexwords(pp.desired_raw), pp.action, reqs)
        else:
            table.add_row(pp.name, addr, _hexwords(pp.desired_raw), pp.desired, reqs)
    if table.row_count:
        out.print(table)
    elif changes_only:
        out.print("No changes: the device already holds every value of the recipe.")
    st = wire_stats(plan)
    naive = sum(1 for pp in plan.parameters if pp.action != "unchanged")
    unchanged = sum(1 for pp in plan.parameters if pp.action == "unchanged")
    out.print(
        f"{len(plan.writes)} write request{'s' if len(plan.writes) != 1 else ''} "
        f"({st['registers']} registers; one request per parameter would take {naive})"
        + (f", {unchanged} unchanged" if unchanged else "")
        + f"; {st['rtu_bytes']} bytes on an RTU line, about {float(st['seconds_19200']) * 1000:.0f} ms at 19200 baud")


def print_frames(plan: Plan, out: Console) -> None:
    from .frames import Framing, request_frame, response_frame

    unit = plan.device.unit
    for i, w in enumerate(plan.writes, 1):
        names = ", ".join(w.parameters)
        out.print(f"request {i}: FC{w.function:02d} at 0x{w.address:04X}, {w.count} registers ({names})")
        framing: Framing
        for framing in ("rtu", "ascii", "tcp"):
            q = request_frame(w, unit, framing, transaction_id=i)
            a = response_frame(w, unit, framing, transaction_id=i)
            out.print(f"  {framing:5} query    {_show(q, framing)}")
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
def plan(recipe: str, device: str | None, unit: int | None, timeout: float | None, retries: int | None,
         as_json: bool, out_path: str | None, detailed_exitcode: bool, show_frames: bool, write_all: bool) -> int:
    """Show the requests that apply would send. Offline, or with --device against what the device holds."""
    from .planner import Target, make_plan, plan_to_json
    from .recipe import load_recipe
    from .report import write_json

    rec = load_recipe(recipe)
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
        print_plan(p, rec.profile, changes_only=current is not None, out=out)
        if show_frames:
            print_frames(p, out)
        if out_path:
            out.print(f"plan written to {out_path}; run it unchanged with: deployer apply {out_path}")
    if detailed_exitcode and p.writes:
        return EXIT_CHANGES
    return EXIT_OK


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
def simulate(profile: str, listen: str, units: tuple[int, ...], init_recipe: str | None, latency_ms: float,
             baud: int | None, drop_every: int, busy_first: int, fail_registers: tuple[str, ...],
             disconnect_after: int, state_path: str | None, log_path: str | None, loose_limits: bool) -> int:
    """Serve a simulated device for PROFILE (a built-in id or a file) until Ctrl-C."""
    from .profile import resolve_profile
    from .recipe import load_recipe
    from .simulator import Faults, Simulator, init_from_recipe, parse_listen, serve

    prof = resolve_profile(profile)
    try:
        parse_listen(listen)
    except ValueError as e:
        raise UsageError(str(e)) from None
    init = init_from_recipe(load_recipe(init_recipe)) if init_recipe else None
    faults = Faults(latency_ms=latency_ms, baud=baud, drop_every=drop_every, busy_first=busy_first,
                    fail_registers=frozenset(_register(r) for r in fail_registers),
                    disconnect_after=disconnect_after)
    sim = Simulator(prof, listen=listen, units=units or (1,), init=init, faults=faults, log_path=log_path,
                    state_path=state_path, strict_limits=not loose_limits)

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


def print_report(report: Report, out: Console) -> None:
    for d in report.devices:
        style = _STATUS_STYLE.get(d.status, "")
        out.print(f"[bold]{d.name}[/bold] {d.url} unit {d.unit} ({d.profile}): [{style}]{d.status}[/{style}]"
                  + (f" - {d.error}" if d.error else ""))
        rows = sorted(d.parameters, key=lambda p: (_STATUS_ORDER.get(p.status, 9), p.address))
        if d.status != "unreachable" and rows:
            table = Table("parameter", "before", "desired", "after", "status", "", box=None)
            for p in rows:
                st = _STATUS_STYLE.get(p.status, "")
                table.add_row(p.name, p.before or "-", p.desired, p.after or "-", f"[{st}]{p.status}[/{st}]",
                              p.error or "")
            out.print(table)
        if d.status == "sent":
            out.print("broadcast sent: every request went out; no device answers a broadcast, so nothing was "
                      "read back or verified")
        if d.snapshot:
            out.print(f"snapshot: {d.snapshot}  (undo with: deployer rollback {d.snapshot})")
        out.print(f"{d.write_requests} write and {d.read_requests} read requests")
    s = report.to_json()["summary"]
    if len(report.devices) > 1:
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


def run_apply(source: str, *, device: str | None, unit: int | None, timeout: float | None, retries: int | None,
              yes: bool, report_path: str | None, as_json: bool, inventory: str | None, limit: str | None,
              parallel: int, on_error: str, write_all: bool, allow_broadcast: bool, state_dir: str,
              command: str = "apply") -> int:
    """apply / rollback: everything validated, then confirmed, then sent."""
    from .executor import ApplyOptions, Job, apply_many
    from .fleet import fleet_jobs, load_inventory
    from .planner import load_plan
    from .recipe import load_recipe
    from .report import audit, write_json

    expected: Plan | None = None
    if _is_plan_file(source):
        if inventory or write_all:
            raise UsageError("a saved plan runs unchanged: --inventory and --write-all do not apply to it")
        rec, expected = load_plan(source)
    else:
        rec = load_recipe(source)
    jobs: list[Job] = []
    if inventory:
        if device:
            raise UsageError("--device and --inventory exclude each other")
        jobs = fleet_jobs(load_inventory(inventory), rec, limit, timeout=timeout, retries=retries, unit=unit)
        if not jobs:
            raise UsageError(f"--limit {limit!r} matches no device in {inventory}")
    else:
        one, u = _target(rec, device, unit, timeout, retries, required=True)
        assert one is not None
        jobs.append(Job(rec.name, rec, one, u))
    for j in jobs:
        if j.unit == 0 and not allow_broadcast:
            raise UsageError(f"{j.name}: unit 0 is broadcast (no device answers, nothing can be verified); "
                             "pass --allow-broadcast to send it anyway")

    out = console()
    err = Console(stderr=True, highlight=False)
    confirm = None
    if not yes:
        if not sys.stdin.isatty():
            raise UsageError("refusing to write without confirmation: stdin is not a terminal; pass --yes")
        lock = asyncio.Lock()
        profiles = {j.name: j.recipe.profile for j in jobs}

        async def confirm(p: Plan, res: DeviceResult) -> bool:
            async with lock:  # one question at a time, even for fleets
                err.print(f"[bold]{res.name}[/bold] {res.url} unit {res.unit}:")
                print_plan(p, profiles[res.name], changes_only=True, out=err)
                return await asyncio.to_thread(click.confirm, "Write these values?", default=False, err=True)

    options = ApplyOptions(on_error=on_error, write_all=write_all,  # type: ignore[arg-type]
                           allow_broadcast=allow_broadcast, state_dir=state_dir, expected=expected, confirm=confirm)
    def done(r: DeviceResult) -> None:  # fleets: a line per device as it finishes
        style = _STATUS_STYLE.get(r.status, "")
        err.print(f"{r.name}: [{style}]{r.status}[/{style}] ({r.write_requests} writes)"
                  + (f" - {r.error}" if r.error else ""))

    report = asyncio.run(apply_many(jobs, parallel=parallel, options=options, recipe_name=source,
                                    on_done=done if len(jobs) > 1 else None))
    data = report.to_json()
    if report_path:
        write_json(data, report_path)
    audit(state_dir, report, command=command, argv=_ARGV)
    if as_json:
        click.echo(json.dumps(data, indent=2))
    else:
        print_report(report, out)
    return report.exit_code


def apply_options(f: Callable[..., Any]) -> Callable[..., Any]:
    opts = [
        click.option("--yes", "-y", is_flag=True, help="do not ask for confirmation"),
        click.option("--report", "report_path", type=click.Path(dir_okay=False), help="write the report JSON here"),
        click.option("--json", "as_json", is_flag=True, help="print the report JSON"),
        click.option("--inventory", type=click.Path(dir_okay=False), help="apply to the devices of an inventory"),
        click.option("--limit", metavar="GROUP|NAME", help="only these inventory devices or groups (comma-separated)"),
        click.option("--parallel", type=click.IntRange(1, 1000), default=8, show_default=True,
                     help="devices at once (devices on one bus always go one at a time)"),
        click.option("--on-error", type=click.Choice(["continue", "stop"]), default="continue", show_default=True,
                     help="after a rejected value: send the rest, or skip it"),
        click.option("--write-all", is_flag=True, help="write every parameter, even those already right"),
        click.option("--allow-broadcast", is_flag=True, help="allow unit 0 (broadcast; nothing can be verified)"),
        click.option("--state-dir", default=".deployer", show_default=True, type=click.Path(file_okay=False),
                     help="where snapshots and the audit log go"),
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
@click.argument("snapshot", type=click.Path(dir_okay=False, exists=True))
@apply_options
def rollback(snapshot: str, **kw: Any) -> int:
    """Restore a snapshot that apply saved (a snapshot is itself a recipe)."""
    return run_apply(snapshot, command="rollback", **kw)


@cli.command()
@click.argument("recipe", type=click.Path(dir_okay=False))
@device_options
@click.option("--json", "as_json", is_flag=True, help="print the differences as JSON")
def diff(recipe: str, device: str | None, unit: int | None, timeout: float | None, retries: int | None,
         as_json: bool) -> int:
    """Drift check: exit 2 when the device differs from the recipe, 0 when it matches."""
    from .recipe import load_recipe

    rec = load_recipe(recipe)
    url, u = _target(rec, device, unit, timeout, retries, required=True)
    assert url is not None
    current = read_device(rec.profile, [d.name for d in rec.desired], url, u)
    if current is None:
        return EXIT_UNREACHABLE
    rows: list[dict[str, Any]] = []
    for d in rec.desired:
        cur = current.get(d.name)
        if cur is None:
            rows.append({"name": d.name, "desired": d.text, "device": None, "status": "not readable"})
        elif cur != d.registers:
            rows.append({"name": d.name, "desired": d.text, "device": d.parameter.format_registers(cur),
                         "device_raw": list(cur), "desired_raw": list(d.registers), "status": "drift"})
    drift = [r for r in rows if r["status"] == "drift"]
    if as_json:
        click.echo(json.dumps({"recipe": recipe, "device": describe(url), "unit": u, "drift": rows}, indent=2))
    elif rows:
        table = Table("parameter", "recipe", "device", "", box=None)
        for r in rows:
            table.add_row(str(r["name"]), str(r["desired"]), str(r["device"] or "-"), str(r["status"]))
        console().print(table)
        console().print(f"{len(drift)} of {len(rec.desired)} parameters differ from the recipe")
    else:
        console().print(f"no drift: the device holds all {len(rec.desired)} values of the recipe")
    return EXIT_CHANGES if drift else EXIT_OK


@cli.command()
@click.option("--profile", "profile_ref", required=True, metavar="ID|FILE", help="the device's profile")
@click.option("--device", required=True, metavar="URL")
@click.option("--unit", type=click.IntRange(1, 247), default=1, show_default=True)
@click.option("--timeout", type=click.FloatRange(min=0, min_open=True))
@click.option("--retries", type=click.IntRange(0, 20))
@click.option("-o", "--output", type=click.Path(dir_okay=False), help="write the recipe here (default: stdout)")
@click.option("--name", help="the recipe's name (default: pulled-PROFILE)")
def pull(profile_ref: str, device: str, unit: int, timeout: float | None, retries: int | None,
         output: str | None, name: str | None) -> int:
    """Read every writable parameter of a device into a recipe that applies back as a no-op."""
    from .profile import resolve_profile
    from .recipe import DeviceSpec, recipe_text
    from .transport import BadURL, parse_url

    prof = resolve_profile(profile_ref)
    try:
        url = parse_url(device, timeout=timeout, retries=retries)
    except BadURL as e:
        raise UsageError(str(e)) from None
    names = [p.name for p in prof.parameters if p.readable and p.writable]
    current = read_device(prof, names, url, unit)
    if current is None:
        return EXIT_UNREACHABLE
    ref = prof.source if prof.source and output is None else (
        os.path.relpath(prof.source, os.path.dirname(os.path.abspath(output))) if prof.source and output else prof.id)
    text = recipe_text(ref, {prof.parameter(n): v for n, v in current.items()}, name=name or f"pulled-{prof.id}",
                       device=DeviceSpec(describe(url), unit),
                       comment=f"Pulled from {describe(url)} unit {unit} at "
                               f"{time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}")
    if output:
        with open(output, "w", encoding="utf-8") as f:
            f.write(text)
        click.echo(f"{len(current)} parameters written to {output}", err=True)
    else:
        click.echo(text, nl=False)
    return EXIT_OK


@cli.command()
@click.option("--fast", is_flag=True, hidden=True, help="no pauses between steps (tests)")
def demo(fast: bool) -> int:
    """The whole story against a built-in simulated device: validate, plan, apply, verify, drift, rollback."""
    from .demo import run_demo

    return run_demo(fast=fast)



_ARGV: list[str] = []  # the command line, for the audit log


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point: map every user error to its exit code, never a traceback."""
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
