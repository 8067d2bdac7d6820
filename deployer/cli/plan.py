"""plan: one device or a fleet, as a table, JSON or frames."""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import TYPE_CHECKING

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
    read_device,
    recipe_or_inventory,
    safe,
)
from .tables import Cell, show

if TYPE_CHECKING:
    from rich.console import Console

    from ..api import DeviceURL, Job, Plan, Profile, Recipe


def _hexwords(regs: Sequence[int] | None) -> str:
    return "-" if regs is None else " ".join([format(w, "04X") for w in regs])


def print_plan(plan: Plan, profile: Profile, *, changes_only: bool, out: Console,
               url: DeviceURL | None = None) -> None:
    from ..api import address_text, plan_cost

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
        addr = address_text(pp.register_type, pp.address)
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
    cost = plan_cost(plan, profile, url)
    naive = sum(1 for pp in plan.parameters if pp.action != "unchanged")
    unchanged = sum(1 for pp in plan.parameters if pp.action == "unchanged")
    framing, chars, seconds, line = cost["framing"], cost["characters"], cost["seconds"], cost["line"]
    paused = f" (pauses the device needs included: {cost['pauses'] * 1000:.0f} ms)" if cost["pauses"] else ""
    units = (f"{_n(chars, 'character')} on an ASCII line" if framing == "ascii"
             else f"{_n(chars, 'byte')} on an RTU line")
    out.print(
        f"{_n(len(plan.writes), 'write request')} "
        f"({_what(cost['registers'], cost['coils'])}; one request per parameter would take {naive})"
        + (f", {unchanged} unchanged" if unchanged else "")
        + f"; {units}, about {seconds * 1000:.0f} ms at {line}{paused}"
        + (" (broadcast: no answers)" if plan.device.unit == 0 else ""))


def _what(registers: int, coils: int) -> str:
    """'5 registers', or '1 register, 4 coils' when coils are written too."""
    if not coils:
        return _n(registers, "register")
    return f"{_n(registers - coils, 'register')}, {_n(coils, 'coil')}"


def print_frames(plan: Plan, out: Console) -> None:
    from ..api import plan_frames

    frames = {framing: plan_frames(plan, framing) for framing in ("rtu", "ascii", "tcp")}
    for i, w in enumerate(plan.writes, 1):
        names = ", ".join(w.parameters)
        what = _n(w.count, "coil") if w.function in (5, 15) else _n(w.count, "register")
        out.print(f"request {i}: FC{w.function:02d} at 0x{w.address:04X}, {what} ({safe(names)})")
        for framing, sent in frames.items():
            q, a = sent[i - 1]
            out.print(f"  {framing:5} query    {_show(q, framing)}")
            if a is None:  # broadcast: no device answers
                out.print(f"  {'':5} response none (broadcast)")
                continue
            out.print(f"  {'':5} response {_show(a, framing)}")


def _show(frame: bytes, framing: str) -> str:
    return frame.decode("ascii").strip() if framing == "ascii" else frame.hex(" ").upper()


@click.command()
@click.argument("recipe", required=False, type=click.Path(dir_okay=False))
@device_options
@click.option("--json", "as_json", is_flag=True, help="print the plan as JSON")
@click.option("--out", "out_path", type=click.Path(dir_okay=False), help="write the plan (JSON) for 'apply PLAN.json'")
@click.option("--detailed-exitcode", is_flag=True, help="exit 2 when something would change, 0 when nothing would")
@click.option("--show-frames", is_flag=True, help="print the exact bytes of each request (RTU, ASCII, TCP)")
@click.option("--write-all", is_flag=True, help="plan every parameter, even those the device already holds")
@click.option("--state-dir", default=".deployer", show_default=True, type=click.Path(file_okay=False),
              help="where apply keeps what devices taught (limits found by their refusals); plan uses it")
@fleet_option
@limit_option
@parallel_option
@click.option("--per-device", is_flag=True,
              help="with --inventory: each device's own plan table (default: devices with identical changes together)")
@agent_option
def plan(recipe: str | None, device: str | None, unit: int | None, timeout: float | None, retries: int | None,
         as_json: bool, out_path: str | None, detailed_exitcode: bool, show_frames: bool, write_all: bool,
         state_dir: str, inventory: str | None, limit: str | None, parallel: int, per_device: bool,
         agent_url: str | None) -> int:
    """Show the requests that apply would send. Offline, or with --device against what the device holds.

    With --inventory and no RECIPE, each device's recipe from the inventory. With --agent URL: the changes
    of the agent's files that it has not adopted, per device."""
    if agent_url:
        from . import agentclient

        if recipe or device or inventory or out_path or show_frames:
            raise UsageError("with --agent, plan shows the agent's pending changes: no RECIPE, --device, "
                             "--inventory, --out or --show-frames")
        return agentclient.plan(agent_url, as_json=as_json, detailed_exitcode=detailed_exitcode)
    import os

    from ..api import plan_to_json, plan_values, write_output

    maybe = recipe_or_inventory(recipe, inventory)
    if inventory:
        if device or out_path or show_frames:
            raise UsageError("with --inventory, --device, --out and --show-frames do not apply (one plan per device)")
        return plan_fleet(maybe, _fleet(maybe, inventory, limit, timeout, retries, unit), parallel=parallel,
                          as_json=as_json, detailed_exitcode=detailed_exitcode, write_all=write_all,
                          state_dir=state_dir, per_device=per_device)
    if limit or per_device:
        raise UsageError(f"{'--limit' if limit else '--per-device'} needs --inventory")
    assert maybe is not None
    rec = maybe
    url, u = _target(rec, device, unit, timeout, retries, required=False)
    if out_path:  # before reading the device
        from ..api import check_output

        check_output(out_path, what="the plan")
    if url is not None:
        from ..api import taught_recipe

        rec, note = taught_recipe(rec, url, u, state_dir=state_dir)
        if note is not None:
            echo(f"note: {safe(note)}", err=as_json)
    current = None
    if device is not None:
        assert url is not None
        current = read_device(rec.profile, [d.name for d in rec.desired], url, u)
        if current is None:
            return EXIT_UNREACHABLE
    p = plan_values(rec, current, url, u, write_all=write_all)
    data = plan_to_json(p)
    if out_path:
        os.makedirs(os.path.dirname(os.path.abspath(out_path)), exist_ok=True)
        write_output(out_path, json.dumps(data, indent=2) + "\n", what="the plan")
    if as_json:
        echo(json.dumps(data, indent=2))
    else:
        out = console()
        out.print(f"profile: {safe(rec.profile.id)} ({safe(rec.profile.source or 'built-in')})")
        print_plan(p, rec.profile, changes_only=current is not None, out=out, url=url)
        if show_frames:
            print_frames(p, out)
        if out_path:
            out.print(f"plan written to {safe(out_path)}; run it unchanged with: deployer apply {safe(out_path)}")
    if detailed_exitcode and p.writes:
        return EXIT_CHANGES
    return EXIT_OK


def plan_fleet(rec: Recipe | None, jobs: Sequence[Job], *, parallel: int, as_json: bool, detailed_exitcode: bool,
               write_all: bool, per_device: bool = False, state_dir: str = ".deployer") -> int:
    """A plan per device against what it holds, devices with identical changes together (``per_device``:
    each device's table); exit 3 if any device could not be read, else as plan."""
    from dataclasses import replace

    from ..api import plan_to_json, plan_values, read_jobs, taught_recipe

    taught_jobs = []
    for j in jobs:
        r, note = taught_recipe(j.recipe, j.url, j.unit, state_dir=state_dir)
        if note is not None:
            echo(f"note: {safe(j.name)}: {safe(note)}", err=as_json)
            j = replace(j, recipe=r)
        taught_jobs.append(j)
    jobs = taught_jobs

    from .progress import read_fleet  # rich: only fleets pay for importing it

    values = read_fleet(read_jobs(jobs), parallel)
    plans = {}
    for j in jobs:
        cur = values[j.name]
        if not isinstance(cur, Exception):
            plans[j.name] = plan_values(j.recipe, cur, j.url, j.unit, write_all=write_all)
    changing = [n for n, p in plans.items() if p.writes]
    if as_json:
        echo(json.dumps({"recipe": rec.path if rec else None, "devices": [
            {"name": j.name, "plan": plan_to_json(plans[j.name])} if j.name in plans
            else {"name": j.name, "error": str(values[j.name])} for j in jobs]}, indent=2))
    elif per_device:
        out = console()
        for j in jobs:
            if j.name in plans and plans[j.name].writes:
                from .text import styled

                out.print(styled((j.name, "bold"), f" {describe(j.url)} unit {j.unit}:"))
                print_plan(plans[j.name], j.recipe.profile, changes_only=True, out=out)
        down = _unreachable(values)
        out.print(f"{len(changing)} of {_n(len(jobs), 'device')} would change"
                  + (f": {', '.join(safe(n) for n in changing)}" if changing else "")
                  + (f"; {len(down)} unreachable: {', '.join(safe(n) for n in down)}" if down else ""))
    else:
        from .summary import plan_changes, print_groups

        out = console()
        print_groups(out, {j.name: plan_changes(plans[j.name], j.recipe.profile) for j in jobs if j.name in plans},
                     _unreachable(values), same="as desired")
        writes = sum(len(p.writes) for p in plans.values())
        out.print(f"{len(changing)} of {_n(len(jobs), 'device')} would change ({_n(writes, 'write request')}); "
                  "--per-device shows each device's plan")
    if _unreachable(values):
        return EXIT_UNREACHABLE
    return EXIT_CHANGES if detailed_exitcode and changing else EXIT_OK
