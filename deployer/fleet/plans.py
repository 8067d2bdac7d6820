"""A fleet's plan: each device's plan (or why it has none), with how each device is reached, for ``apply``."""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from ..calls import checked
from ..errors import DeployerError, UsageError
from ..planning.model import Plan, Target
from ..transport.urls import describe

if TYPE_CHECKING:  # its module imports the transports (pymodbus): an offline plan does not need them
    from ..errors import Diagnostic
    from ..execute.job import Job
    from ..load.yamlsrc import Path_
    from ..profile import Profile
    from ..recipe.loader import Recipe

    ErrorAt = Callable[[Path_, str], Diagnostic]  # a problem said at a position of one device's plan

FLEET_SCHEMA = "deployer.fleetplan/1"


class FleetPlan:
    """Every selected device's plan, in the inventory's order, or the error that stopped its plan (a device
    that could not be read: ``TransportError``; a device no plan can be made for: ``UsageError``).

    ``fleet[name]`` is the device's Plan (or raises its error), ``fleet.plans`` the plans made, ``fleet.errors``
    the others, ``fleet.changes`` whether executing it writes anything. ``apply(fleet)`` executes exactly these
    plans (each device refused before its first write when it no longer holds what its plan was made against),
    with each device's URL, unit and group as the inventory gave them (``batch_by="group"``); a device without a
    plan refuses the whole apply: plan again, or apply ``fleet.without_errors()``.
    """

    def __init__(
        self, jobs: Sequence[Job], results: Mapping[str, Plan | DeployerError], *, recipe: str | None, inventory: str
    ) -> None:
        self._jobs = {j.name: j for j in jobs}
        self._results = {j.name: results[j.name] for j in jobs}
        self.recipe = recipe  # what was planned (a recipe's path or name; None: each device's own from the inventory)
        self.inventory = inventory  # the inventory's path (or the name of a list of devices)

    def __repr__(self) -> str:
        return f"FleetPlan(devices={len(self._results)}, planned={len(self.plans)}, errors={len(self.errors)})"

    def __len__(self) -> int:
        return len(self._results)

    def __iter__(self) -> Iterator[str]:
        """The devices' names, in the inventory's order."""
        return iter(self._results)

    def __contains__(self, name: object) -> bool:
        return name in self._results

    def __getitem__(self, name: str) -> Plan:
        """The device's plan; its error when it has none (KeyError: no such device in the plan)."""
        got = self._results[name]
        if isinstance(got, DeployerError):
            raise got
        return got

    @property
    def plans(self) -> dict[str, Plan]:
        """The devices that have a plan: name -> Plan."""
        return {n: p for n, p in self._results.items() if isinstance(p, Plan)}

    @property
    def errors(self) -> dict[str, DeployerError]:
        """The devices that have none: name -> why (``TransportError``: it could not be read)."""
        return {n: e for n, e in self._results.items() if isinstance(e, DeployerError)}

    @property
    def changes(self) -> bool:
        """Whether executing the plans writes anything on any device."""
        return any(p.changes for p in self.plans.values())

    def profile(self, name: str) -> Profile:
        """The profile device ``name`` is planned with (its own from the inventory, else the recipe's)."""
        return self._jobs[name].recipe.profile

    def device(self, name: str) -> tuple[str, int]:
        """Device ``name``'s URL (without secrets) and unit."""
        job = self._jobs[name]
        return describe(job.url), job.unit

    @classmethod
    @checked("deployer.FleetPlan.load")
    def load(cls, path: str | os.PathLike[str]) -> FleetPlan:
        """A saved fleet plan file (``plan --inventory --out``, or ``to_json()`` written to a file), each device's
        plan checked as ``deployer.load_plan`` checks one: ``apply`` executes it unchanged. Raises InputError with
        every problem at its position, UsageError when ``path`` is not a path."""
        if not isinstance(path, (str, os.PathLike)):
            raise UsageError(f"deployer.FleetPlan.load() takes the fleet plan file's path, got {type(path).__name__}")
        return load_fleet_plan(os.fspath(path))

    def without_errors(self) -> FleetPlan:
        """This plan without the devices that have none."""
        return FleetPlan(
            [j for n, j in self._jobs.items() if n in self.plans],
            self._results,
            recipe=self.recipe,
            inventory=self.inventory,
        )

    def to_json(self, plans: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """A saved fleet plan (docs/reference/fleetplan.md), as ``deployer plan --inventory --json`` prints it and
        ``--out`` writes it: the recipe and inventory, and per device its group and its plan (a saved plan's JSON),
        or the name of an earlier device whose plan it is but for the device (``plan_of``: a fleet's devices mostly
        hold the same values, and a file of every plan in full held 600 devices of 100 parameters), or its error.
        ``plans``: each device's plan JSON where the caller made it (with its cost)."""
        first: dict[str, str] = {}  # a plan's JSON without its device -> the device that has it in full
        devices: list[dict[str, Any]] = []
        for n, r in self._results.items():
            entry: dict[str, Any] = {"name": n, "group": self._jobs[n].group}
            if not isinstance(r, Plan):
                entry["error"] = str(r)
            else:
                doc = plans[n] if plans is not None and n in plans else r.to_json()
                key = json.dumps({k: v for k, v in doc.items() if k != "device"}, sort_keys=True)
                if key in first:
                    entry["plan_of"], entry["device"] = first[key], doc["device"]
                else:
                    first[key] = n
                    entry["plan"] = doc
            devices.append(entry)
        return {"schema": FLEET_SCHEMA, "recipe": self.recipe, "inventory": self.inventory, "devices": devices}


def fleet_plan_text(doc: Mapping[str, Any]) -> str:
    """A fleet plan document as its file's text; UsageError when ``apply`` could not read it back (the input limits
    every file is read within), saying how large it would be and how to plan the fleet in parts."""
    from ..load.yamlsrc import MAX_FILE_BYTES, MAX_NODES

    def values(x: Any) -> int:  # as the loader counts them: every value, keys not
        if isinstance(x, dict):
            return 1 + sum(values(v) for v in x.values())
        if isinstance(x, list):
            return 1 + sum(values(v) for v in x)
        return 1

    text = json.dumps(doc, indent=2) + "\n"
    size, count = len(text.encode()), values(doc)
    if size > MAX_FILE_BYTES or count > MAX_NODES:
        raise UsageError(
            f"no fleet plan written: it would be {size / 1e6:.1f} MB and {count:,} values, more than a file may hold "
            f"({MAX_FILE_BYTES >> 20} MiB, {MAX_NODES:,} values: docs/input-limits.md); plan the fleet in parts, a "
            "group or a range of names at a time (--limit)"
        )
    return text


def executable_jobs(fleet: FleetPlan) -> list[Job]:
    """What ``apply(fleet)`` runs: each device's job, its plan to be executed unchanged. UsageError when a device
    has no plan."""
    missing = fleet.errors
    if missing:
        shown = "; ".join(f"{n}: {e}" for n, e in list(missing.items())[:5])
        more = f" (and {len(missing) - 5} more)" if len(missing) > 5 else ""
        raise UsageError(
            f"the fleet plan has no plan for {len(missing)} device{'s' if len(missing) != 1 else ''} "
            f"({shown}{more}): plan again, or apply the plan's without_errors()"
        )
    plans = fleet.plans
    return [replace(j, plan=plans[n]) for n, j in fleet._jobs.items()]


def is_fleet_plan_file(path: str) -> bool:
    """A saved fleet plan (``plan --inventory --out``), by its first bytes: it writes its schema first."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    return head.lstrip().startswith(b"{") and b'"deployer.fleetplan/' in head


def read_fleet_plan(path: str) -> tuple[dict[str, Any], list[tuple[str, str | None, Plan, ErrorAt, str]]]:
    """A saved fleet plan file's document, and each device's name, group and plan, checked as a saved plan is
    (``plan_from_json``: its format and consistency, every problem at its position in the file), all problems at
    once (InputError), with what says a problem at a position of the plan and the device whose entry writes it in
    full (itself, or the one its ``plan_of`` names). A device saved without a plan (an edited file: ``plan --out``
    writes none) is one: a saved fleet plan runs every device it names."""
    from ..errors import InputError
    from ..load import yamlsrc
    from ..planning.planfile import plan_from_json

    data, src = yamlsrc.load(path)
    if not isinstance(data, dict) or data.get("schema") != FLEET_SCHEMA:
        raise InputError([src.error(("schema",), f"not a saved fleet plan ({FLEET_SCHEMA})")])
    devices = data.get("devices")
    if not isinstance(devices, list) or not devices:
        raise InputError([src.error(("devices",), "a saved fleet plan lists its devices, each with its plan")])
    # each device's positions, its plan's paths made relative to the plan (one pass over the file's positions)
    subs: dict[int, yamlsrc.Source] = {i: yamlsrc.Source(path) for i in range(len(devices))}
    for table, member in ((src.values, "values"), (src.keys, "keys")):
        for at, pos in table.items():
            if len(at) >= 3 and at[0] == "devices" and at[2] == "plan" and isinstance(at[1], int) and at[1] in subs:
                getattr(subs[at[1]], member)[at[3:]] = pos
    errors: list[Diagnostic] = []
    out: list[tuple[str, str | None, Plan, ErrorAt, str]] = []
    full: dict[str, tuple[Plan, ErrorAt]] = {}  # the devices whose plan is written in full
    seen: set[str] = set()
    for i, entry in enumerate(devices):
        name: Any = entry.get("name") if isinstance(entry, dict) else None
        if not isinstance(name, str) or not name or name in seen:
            errors.append(src.error(("devices", i), "each device has a name of its own"))
            continue
        seen.add(name)
        group = entry.get("group")
        group = group if isinstance(group, str) else None
        if "plan_of" in entry and "plan" in entry:  # a reviewer would read one plan and apply run the other
            errors.append(src.error(("devices", i, "plan_of"), f"{name}: a plan and a plan_of: give one of them"))
            continue
        if "plan_of" in entry:  # an earlier device's plan, for this device
            of, dev = entry.get("plan_of"), entry.get("device")
            if not isinstance(of, str) or of not in full:
                errors.append(src.error(("devices", i, "plan_of"), f"{name}: plan_of names no earlier device's plan"))
                continue
            plan, said = full[of]
            unit = dev.get("unit") if isinstance(dev, dict) else None
            if type(unit) is not int or not isinstance(dev, dict) or not isinstance(dev.get("url"), str):  # not True
                errors.append(src.error(("devices", i, "device"), f"{name}: its device's url and unit are needed"))
                continue
            if not 0 <= unit <= 247:  # as a plan's own device (the plan schema)
                errors.append(src.error(("devices", i, "device", "unit"), f"{name}: unit {unit} is outside 0..247"))
                continue
            if dev.get("profile") != plan.device.profile:
                errors.append(src.error(("devices", i, "device"), f"{name}: not the profile of {of}'s plan"))
                continue
            shared = replace(plan, device=Target(dev["url"], dev["unit"], plan.device.profile))
            out.append((name, group, shared, said, str(of)))
            continue
        if "plan" not in entry:
            why = f" ({entry['error']})" if isinstance(entry.get("error"), str) else ""
            errors.append(src.error(("devices", i), f"{name} has no plan{why}: plan the fleet again"))
            continue
        try:
            plan = plan_from_json(entry["plan"], path, src=subs[i])
        except InputError as e:
            errors.extend(e.diagnostics)
            continue
        full[name] = plan, subs[i].error
        out.append((name, group, plan, subs[i].error, name))
    if errors:
        raise InputError(errors)
    return data, out


def load_fleet_plan(path: str, *, timeout: float | None = None, retries: int | None = None) -> FleetPlan:
    """A saved fleet plan file, to run (``read_fleet_plan``): each device's plan checked against its profile as
    ``apply PLAN.json`` checks one, all problems at once (InputError). ``timeout``/``retries``: override each device
    URL's, as for a fleet."""
    from ..errors import InputError
    from ..execute.job import Job
    from ..planning.planfile import plan_recipe
    from ..recipe.model import DeviceSpec
    from ..transport.urls import overridden, parse_url

    data, plans = read_fleet_plan(path)
    errors: list[Diagnostic] = []
    jobs: list[Job] = []
    recipes: dict[str, Recipe] = {}  # each plan's recipe, checked against its profile once, by its device in full
    for name, group, plan, at, base in plans:
        try:
            rec = recipes.get(base)
            if rec is None:
                rec = recipes[base] = plan_recipe(plan, path, at)
            elif base != name:  # a shared plan: its recipe, for this device
                rec = replace(rec, device=DeviceSpec(plan.device.url, plan.device.unit))
            if plan.device.url is None:
                raise InputError([at(("device", "url"), f"{name}: the plan names no device URL")])
            url = overridden(parse_url(plan.device.url), timeout, retries)  # given now, over the plan's own
        except InputError as e:
            errors.extend(e.diagnostics)
            continue
        except UsageError as e:  # a URL that does not parse
            errors.append(at(("device", "url"), f"{name}: {e}"))
            continue
        jobs.append(Job(name, rec, url, plan.device.unit, group=group))
    if errors:
        raise InputError(errors)
    recipe = data.get("recipe")
    return FleetPlan(
        jobs,
        {name: plan for name, _, plan, _, _ in plans},
        recipe=recipe if isinstance(recipe, str) else None,
        inventory=str(data.get("inventory") or path),
    )
