"""plan: one device or a fleet, as a table, JSON or frames."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, cast

import click

from ..errors import EXIT_CHANGES, EXIT_OK, EXIT_UNREACHABLE, UsageError
from .base import (
    _fleet,
    _n,
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
    recipe_or_inventory,
    safe,
)
from .change import ChangeOptions, change_options, stamped
from .tables import Cell, show

if TYPE_CHECKING:
    from rich.console import Console

    from ..api import Plan, Profile, Recipe, Step
    from ..api.commands import DeviceURL, Job


def _hexwords(regs: Sequence[int] | None) -> str:
    return "-" if regs is None else " ".join([format(w, "04X") for w in regs])


def print_plan(
    plan: Plan, profile: Profile, *, changes_only: bool, out: Console, url: DeviceURL | None = None, steps: bool = True
) -> None:
    """The plan's parameters (``changes_only``: those it writes, current -> desired) and, with ``steps``, every
    step apply takes on the device in order, and what that costs."""
    from ..api.commands import address_text, plan_cost

    step_of: dict[str, list[int]] = {}
    for i, s in enumerate(plan.steps, 1):
        if s.kind == "write":
            for n in s.parameters:
                step_of.setdefault(n, []).append(i)
    headers = ["parameter", "address", "raw", "value", "step"]
    if changes_only:
        headers = ["parameter", "address", "current -> desired", "raw", "action", "step"]
    rows: list[list[Cell]] = []
    for pp in plan.parameters:
        if changes_only and pp.action == "unchanged":
            continue
        addr = address_text(pp.register_type, pp.address)
        at = ",".join(str(i) for i in step_of.get(pp.name, [])) or "-"
        if changes_only:
            p = profile.parameter(pp.name)
            cur = p.format_registers(pp.current_raw) if pp.current_raw is not None else "?"
            rows.append([pp.name, addr, f"{cur} -> {pp.desired}", _hexwords(pp.desired_raw), pp.action, at])
        else:
            rows.append([pp.name, addr, _hexwords(pp.desired_raw), pp.desired, at])
    if rows:
        show(out, headers, rows)
        if not changes_only and any(profile.parameter(pp.name).mask for pp in plan.parameters):
            out.print(
                "bit fields: raw shows their own bits; apply reads each such register right before writing "
                "it (a read-modify-write step) and keeps its other bits as the device holds them"
            )
    elif changes_only:
        out.print("No changes: the device already holds every value of the recipe.")
    if steps:
        print_steps(plan, out)
    cost = plan_cost(plan, profile, url)
    writes = [s for s in plan.steps if s.kind == "write"]
    naive = sum(1 for pp in plan.parameters if pp.action != "unchanged")
    unchanged = sum(1 for pp in plan.parameters if pp.action == "unchanged")
    coils = sum(s.count for s in writes if s.function in (5, 15))
    registers = sum(s.count for s in writes)
    units = (
        f"{_n(cost.bytes, 'character')} on an ASCII line"
        if cost.framing == "ascii"
        else f"{_n(cost.bytes, 'byte')} in Modbus/TCP frames"
        if cost.framing == "tcp"
        else f"{_n(cost.bytes, 'byte')} on an RTU line"
    )
    when = (
        f"about {cost.seconds * 1000:.0f} ms at {cost.line}"
        if cost.framing != "tcp"
        else f"{cost.waits * 1000:.0f} ms of waits"
    )
    waits = (
        f" ({cost.waits * 1000:.0f} ms of it waits and pauses the device needs)"
        if cost.waits and cost.framing != "tcp"
        else ""
    )
    out.print(
        f"{_n(len(writes), 'write request')} "
        f"({_what(registers, coils)}; one request per parameter would take {naive})"
        + (f", {unchanged} unchanged" if unchanged else "")
        + f"; {_n(cost.requests, 'request')} in all ({_n(cost.reads, 'read')}, {_n(cost.writes, 'write')}): "
        + f"{units}, {when}{waits}"
        + (" (broadcast: no answers)" if plan.device.unit == 0 else ""),
        soft_wrap=True,
    )
    if cost.non_volatile_writes:
        out.print(
            f"non-volatile memory: {_n(cost.non_volatile_writes, 'write')} "
            f"(storing {_n(len(cost.stores), 'parameter')})",
            soft_wrap=True,
        )


def _what(registers: int, coils: int) -> str:
    """'5 registers', or '1 register, 4 coils' when coils are written too."""
    if not coils:
        return _n(registers, "register")
    return f"{_n(registers - coils, 'register')}, {_n(coils, 'coil')}"


def step_text(step: Step) -> str:
    """One step in words: 'FC16 at 0x00FF, 2 registers (control_mode, motor_poles); then wait 100 ms'."""
    if step.function == 43:
        what = f"FC43 device identification ({step.note})" if step.note else "FC43 device identification"
    else:
        noun = "coil" if step.function in (1, 5, 15) else "input" if step.function == 2 else "register"
        what = f"FC{step.function:02d} at 0x{step.address:04X}, {_n(step.count, noun)}"
        if step.writes and step.kind != "write":
            what += ": " + ("(secret)" if step.values is None else _hexwords(step.values))
        if step.expect is not None:
            mask = step.expect.mask
            what += (
                f": must hold 0x{step.expect.equals:04X}"
                if mask == 0xFFFF
                else f": bits 0x{mask:04X} must be {step.expect.equals}"
            )
        if step.parameters:
            what += f" ({safe(', '.join(step.parameters))})"
        elif step.note:
            what += f" ({safe(step.note)})"
    if step.kind == "commit":
        what += "; only when every parameter verified"
    if step.kind == "lock":
        what += "; whenever the unlock went out"
    if step.wait:
        what += f"; then wait {step.wait * 1000:.0f} ms"
    return what


def print_steps(plan: Plan, out: Console) -> None:
    if not plan.steps:
        return
    out.print("steps, in the order apply sends them:")
    width = len(str(len(plan.steps)))
    for i, step in enumerate(plan.steps, 1):
        out.print(f"  {i:>{width}}  {step.kind:<17}  {step_text(step)}", markup=False, highlight=False, soft_wrap=True)


def print_frames(plan: Plan, out: Console) -> None:
    from ..planning.frames import shown, step_frames

    unit = plan.device.unit
    for i, step in enumerate(plan.steps, 1):
        out.print(f"step {i} ({step.kind}): {step_text(step)}", markup=False, highlight=False, soft_wrap=True)
        for framing in ("rtu", "ascii", "tcp"):
            q, a = step_frames(step, unit, framing, i)
            out.print(
                f"  {framing:5} query    {shown(step, q, unit, framing, i)}",
                markup=False,
                highlight=False,
                soft_wrap=True,
            )
            if a is None or not step.writes:
                why = (
                    "none (broadcast)"
                    if unit == 0
                    else "the device's identification objects"
                    if a is None
                    else f"{len(a)} {'characters' if framing == 'ascii' else 'bytes'}, carrying the values read"
                )
                out.print(f"  {'':5} response {why}", markup=False, highlight=False, soft_wrap=True)
                continue
            out.print(
                f"  {'':5} response {shown(step, a, unit, framing, i, answer=True)}", markup=False, highlight=False
            )


@click.command()
@click.argument("recipe", required=False, type=click.Path(dir_okay=False))
@device_options
@click.option("--json", "as_json", is_flag=True, help="print the plan as JSON")
@click.option(
    "--out",
    "out_path",
    type=click.Path(dir_okay=False),
    help="write the plan (JSON) for 'apply PLAN.json' (with --inventory: every device's, for 'apply FLEET.json')",
)
@click.option("--detailed-exitcode", is_flag=True, help="exit 2 when something would change, 0 when nothing would")
@click.option("--show-frames", is_flag=True, help="print the exact bytes of each request (RTU, ASCII, TCP)")
@click.option("--write-all", is_flag=True, help="plan every parameter, even those the device already holds")
@click.option(
    "--safe-change",
    is_flag=True,
    help="the plan of a safe change (apply --soak or --confirm-within): it reads the profile's health checks "
    "before writing, and a device already failing one is not written",
)
@click.option(
    "--state-dir",
    default=".deployer",
    show_default=True,
    type=click.Path(file_okay=False),
    help="where apply keeps what devices taught (limits found by their refusals); plan uses it",
)
@fleet_option
@limit_option
@parallel_option
@click.option(
    "--per-device",
    is_flag=True,
    help="with --inventory: each device's own plan table (default: devices with identical changes together)",
)
@agent_option
@change_options
def plan(
    recipe: str | None,
    device: str | None,
    unit: int | None,
    timeout: float | None,
    retries: int | None,
    as_json: bool,
    out_path: str | None,
    detailed_exitcode: bool,
    show_frames: bool,
    write_all: bool,
    safe_change: bool,
    state_dir: str,
    inventory: str | None,
    limit: str | None,
    parallel: int,
    per_device: bool,
    agent_url: str | None,
    change: ChangeOptions,
) -> int:
    """Show the requests that apply would send. Offline, or with --device against what the device holds.

    With --inventory and no RECIPE, each device's recipe from the inventory. With --agent URL: the changes
    of the agent's files that it has not adopted, per device."""
    if agent_url:
        from . import agentclient

        if recipe or device or inventory or out_path or show_frames:
            raise UsageError(
                "with --agent, plan shows the agent's pending changes: no RECIPE, --device, "
                "--inventory, --out or --show-frames"
            )
        return agentclient.plan(agent_url, as_json=as_json, detailed_exitcode=detailed_exitcode)
    from ..api.commands import plan_to_json, plan_values, write_output

    if change.given and not out_path:
        raise UsageError("--reason, --ticket, --sign-key and --signer describe a saved plan: give --out PLAN.json")
    maybe = recipe_or_inventory(recipe, inventory)
    if inventory:
        if device or show_frames:
            raise UsageError("with --inventory, --device and --show-frames do not apply (one plan per device)")
        if out_path:  # before reading the devices
            from ..api.commands import check_output

            check_output(out_path, what="the fleet plan")
        return plan_fleet(
            maybe,
            _fleet(maybe, inventory, limit, timeout, retries, unit),
            parallel=parallel,
            as_json=as_json,
            detailed_exitcode=detailed_exitcode,
            write_all=write_all,
            state_dir=state_dir,
            per_device=per_device,
            window=safe_change,
            inventory=inventory,
            out_path=out_path,
            change=change,
        )
    if limit or per_device:
        raise UsageError(f"{'--limit' if limit else '--per-device'} needs --inventory")
    assert maybe is not None
    rec = maybe
    url, u = _target(rec, device, unit, timeout, retries, required=False)
    if out_path:  # before reading the device
        from ..api.commands import check_output

        check_output(out_path, what="the plan")
    if device is not None:  # the plan's checks run on the device (reads only), the plan made against them
        import asyncio

        from ..api import TransportError
        from ..api.commands import plan_async

        assert url is not None
        notes: list[str] = []
        try:
            p = asyncio.run(
                plan_async(rec, url, u, write_all=write_all, state_dir=state_dir, notices=notes, window=safe_change)
            )
        except TransportError as e:
            echo(f"error: {safe(e)}", err=True)
            return EXIT_UNREACHABLE
        for note in notes:
            echo(f"note: {safe(note)}", err=as_json)
    else:
        if url is not None:
            from ..api.commands import taught_recipe

            rec, taught = taught_recipe(rec, url, u, state_dir=state_dir)
            if taught is not None:
                echo(f"note: {safe(taught)}", err=as_json)
        p = plan_values(rec, None, url, u, write_all=write_all, window=safe_change)
    from ..api.commands import plan_cost

    data = plan_to_json(p, plan_cost(p, rec.profile, url))  # the saved plan says what it costs, as printed
    if out_path:
        from .change import stamped  # change control: who, why, which ticket, from which files; signed

        data = stamped(data, change, rec)
        os.makedirs(os.path.dirname(os.path.abspath(out_path)), exist_ok=True)
        write_output(out_path, json.dumps(data, indent=2) + "\n", what="the plan")
        from ..audit.commands import after_plan

        for what in after_plan(
            data,
            out_path=out_path,
            device=data.get("device", {}).get("url"),
            state_dir=state_dir,
            policy_path=change.policy,
        ):
            echo(f"not recorded: {safe(what)}", err=True)
    if as_json:
        echo(json.dumps(data, indent=2))
    else:
        out = console()
        out.print(f"profile: {safe(rec.profile.id)} ({safe(rec.profile.source or 'built-in')})")
        print_plan(p, rec.profile, changes_only=device is not None, out=out, url=url)
        if show_frames:
            print_frames(p, out)
        if out_path:
            out.print(f"plan written to {safe(out_path)}; run it unchanged with: deployer apply {safe(out_path)}")
    if detailed_exitcode and p.writes:
        return EXIT_CHANGES
    return EXIT_OK


def _fleet_cost(jobs: Sequence[Job], plans: Mapping[str, Plan]) -> str:
    """What the fleet's apply would send, as a device's plan states its cost: the recipes' write requests, every
    request (each device's checks and read-back too), and the writes that wear non-volatile memory (commits)."""
    from ..api.commands import plan_cost

    costs = [plan_cost(plans[j.name], j.recipe.profile, j.url) for j in jobs if j.name in plans]
    stored = sum(c.non_volatile_writes for c in costs)
    return (
        f"{_n(sum(len(p.writes) for p in plans.values()), 'write request')}; "
        f"{_n(sum(c.requests for c in costs), 'request')} in all"
        + (f", {_n(stored, 'write')} to non-volatile memory" if stored else "")
    )


def plan_fleet(
    rec: Recipe | None,
    jobs: Sequence[Job],
    *,
    parallel: int,
    as_json: bool,
    detailed_exitcode: bool,
    write_all: bool,
    per_device: bool = False,
    state_dir: str = ".deployer",
    window: bool = False,
    inventory: str | None = None,
    out_path: str | None = None,
    change: ChangeOptions | None = None,
) -> int:
    """A plan per device against what it holds, devices with identical changes together (``per_device``:
    each device's table); exit 3 if any device could not be read, else as plan. ``out_path``: the saved fleet plan
    written there (refused, nothing written, when a device has no plan)."""
    from ..api import FleetPlan
    from ..api.commands import plan_cost, plan_to_json
    from .progress import plan_fleet as planned_fleet  # rich: only fleets pay for importing it

    values = planned_fleet(jobs, parallel, write_all=write_all, state_dir=state_dir, window=window)
    plans = {n: p for n, p in values.items() if not isinstance(p, Exception)}
    changing = [n for n, p in plans.items() if p.writes]
    data: dict[str, Any] | None = None
    if as_json or out_path:  # the saved fleet plan: each device's plan as a saved plan says it, with its cost
        fleet = FleetPlan(
            jobs,
            cast(Mapping[str, Any], values),
            recipe=rec.path if rec else None,
            inventory=os.path.abspath(inventory) if inventory else "",  # its policy governs apply FLEET.json too
        )
        data = fleet.to_json(
            {j.name: plan_to_json(p, plan_cost(p, j.recipe.profile, j.url)) for j in jobs if (p := plans.get(j.name))}
        )
    if out_path:
        assert data is not None
        if len(plans) < len(jobs):
            down = [n for n in values if n not in plans]
            raise UsageError(
                f"no fleet plan written: {_n(len(down), 'device')} could not be planned "
                f"({'; '.join(f'{safe(n)}: {safe(str(values[n]))}' for n in down[:5])}"
                f"{' ...' if len(down) > 5 else ''}); a saved fleet plan runs every device it names: bring them "
                "back, or leave them out with --limit"
            )
        data = _save_fleet_plan(data, out_path, jobs, change, state_dir)
    if as_json:
        echo(json.dumps(data, indent=2))
    elif per_device:
        out = console()
        for j in jobs:
            if j.name in plans and plans[j.name].writes:
                from .text import styled

                out.print(styled((j.name, "bold"), f" {describe(j.url)} unit {j.unit}:"))
                print_plan(plans[j.name], j.recipe.profile, changes_only=True, out=out)
        down = _unreachable(values)
        out.print(
            f"{len(changing)} of {_n(len(jobs), 'device')} would change ({_fleet_cost(jobs, plans)})"
            + (f": {', '.join(safe(n) for n in changing)}" if changing else "")
            + (f"; {len(down)} unreachable: {', '.join(safe(n) for n in down)}" if down else "")
        )
    else:
        from .summary import plan_changes, print_groups

        out = console()
        print_groups(
            out,
            {j.name: plan_changes(plans[j.name], j.recipe.profile) for j in jobs if j.name in plans},
            _unreachable(values),
            same="as desired",
        )
        out.print(
            f"{len(changing)} of {_n(len(jobs), 'device')} would change ({_fleet_cost(jobs, plans)}); "
            "--per-device shows each device's plan"
        )
    if out_path and not as_json:
        console().print(
            f"fleet plan written to {safe(out_path)} ({_n(len(jobs), 'device')}); run it unchanged with: "
            f"deployer apply {safe(out_path)}"
        )
    if _unreachable(values):
        return EXIT_UNREACHABLE
    return EXIT_CHANGES if detailed_exitcode and changing else EXIT_OK


def _save_fleet_plan(
    data: dict[str, Any], out_path: str, jobs: Sequence[Job], change: ChangeOptions | None, state_dir: str
) -> dict[str, Any]:
    """``plan --inventory --out``: the fleet plan with its change (who, why, from which recipes and profiles),
    signed with ``--sign-key``, and the audit trail's record of it; the document written."""
    from ..api.commands import fleet_plan_text, write_output
    from ..audit.commands import after_plan

    change = change or ChangeOptions()
    files: list[tuple[str, str | None]] = []
    for j in jobs:
        files += [("recipe", j.recipe.path), ("profile", j.recipe.profile.source)]
    doc = stamped(data, change, None, files)
    text = fleet_plan_text(doc)  # refused when apply could not read it back
    os.makedirs(os.path.dirname(os.path.abspath(out_path)), exist_ok=True)
    write_output(out_path, text, what="the fleet plan")
    for what in after_plan(doc, out_path=out_path, device=None, state_dir=state_dir, policy_path=change.policy):
        echo(f"not recorded: {safe(what)}", err=True)
    return doc
