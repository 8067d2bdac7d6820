"""Loading what deployer works from: recipes, inventories, saved plans and reports, checked as the command line
checks them (every problem at once, with its position), and recipes made from values given in code."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

from ..calls import checked
from ..errors import Diagnostic, InputError, UsageError
from ..fleet.inventory import Inventory, inventory_from
from ..fleet.inventory import load_inventory as _load_inventory
from ..fleet.plans import is_fleet_plan_file
from ..load.yamlsrc import Source
from ..planning.model import Plan
from ..profile import Profile, load_profile, resolve_profile
from ..recipe.loader import Entry, Recipe, with_overrides
from ..recipe.loader import load_recipe as _load_recipe
from ..report import Report
from .checks import kind, need_flag, need_path, need_recipe


@checked("deployer.load_recipe")
def load_recipe(path: str | os.PathLike[str], *, force: bool = False) -> Recipe:
    """A recipe file, validated against its profile (``extends`` merged, values in engineering units checked
    and encoded). A snapshot (what ``apply`` saved before writing) loads too, checked against the digest its
    journal recorded; ``force`` loads one that was edited since.

    Raises:
        InputError: every problem of the recipe (and its profile), with its position.
        UsageError: ``path`` is not a path.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise UsageError(f"load_recipe takes a path (str or os.PathLike), got {kind(path)}")
    return _load_recipe(path, force=need_flag(force, "force"))


@checked("deployer.load_inventory")
def load_inventory(
    source: str | os.PathLike[str] | Sequence[Mapping[str, Any]], *, name: str = "<devices>"
) -> Inventory:
    """An inventory: a file, or a list of devices given in code (Ansible host vars, a database), checked as a
    file is.

    Each device of a list: ``name`` and ``url`` (required), ``unit`` (1), ``profile`` (a built-in id or a
    path), ``groups``, ``timeout``, ``retries``, ``recipe`` and ``parameters`` (values over the recipe's), as
    in an inventory file; ``name`` is what messages call the list.

    Raises:
        InputError: an invalid inventory (every problem, with its position: in the list, the device's index).
        UsageError: ``source`` is neither a path nor a list of mappings.
    """
    if isinstance(source, (str, os.PathLike)):
        return _load_inventory(source)
    if isinstance(source, (str, bytes, Mapping)) or not isinstance(source, Sequence):
        raise UsageError(f"load_inventory takes an inventory file or a list of devices (mappings), got {kind(source)}")
    devices: list[Mapping[str, Any]] = []
    for i, device in enumerate(source):
        if not isinstance(device, Mapping):
            raise UsageError(
                f"load_inventory: device {i + 1} of the list is not a mapping (name, url ...), got {kind(device)}"
            )
        devices.append(device)
    if not isinstance(name, str):
        raise UsageError(f"load_inventory takes name as a str, got {kind(name)}")
    return inventory_from(devices, name)


@checked("deployer.load_plan")
def load_plan(path: str | os.PathLike[str]) -> Plan:
    """A saved plan (``deployer plan --out``, or ``Plan.to_json()`` written to a file), checked: against the plan
    schema, for consistency (a hand-edited plan cannot write a register no parameter names), and against its
    profile (the same profile text it was made with). ``apply`` executes it unchanged.

    Raises:
        InputError: every problem, with its position; a plan of an older format with the command that remakes it.
        UsageError: ``path`` is not a path.
    """
    from ..planning.planfile import load_plan as _load_plan

    where = need_path(path, "load_plan", "the plan file")
    if is_fleet_plan_file(where):  # every device's plan: a FleetPlan, which apply executes as a fleet
        raise InputError(
            [Diagnostic(where, 1, 1, "a saved fleet plan, not one device's: load it with deployer.FleetPlan.load()")]
        )
    return _load_plan(where)[1]


@checked("deployer.load_report")
def load_report(path: str | os.PathLike[str], profiles: Sequence[str | Profile] = ()) -> Report:
    """An earlier run's report file (``report_path``, ``--report``, a fleet's live report, one a crash left
    unfinished) as a Report. A report is data: no file it names is opened. Values read in engineering units as
    the report describes its profiles, or with ``profiles`` given here (ids, files or Profiles), else as register
    words.

    Raises:
        InputError: not a deployer report, or not a valid one (with its position).
        UsageError: the file cannot be read; an unknown profile.
    """
    from ..report import read_report, report_from_json

    where = need_path(path, "load_report", "the report file")
    if isinstance(profiles, (str, Profile)) or not isinstance(profiles, Sequence):
        raise UsageError(f"load_report takes profiles as a list (ids, files or Profiles), got {kind(profiles)}")
    try:
        doc = read_report(where)
    except OSError as e:
        raise UsageError(f"cannot read {where}: {e.strerror or e}") from None
    return report_from_json(doc, [p if isinstance(p, Profile) else load_profile(p) for p in profiles])


@checked("deployer.recipe_from")
def recipe_from(
    profile: str | Profile, parameters: Mapping[str, Any], *, name: str = "inline", base: Recipe | None = None
) -> Recipe:
    """A recipe from values given in code (``{"F07": "10 s"}``), on its own or over ``base``'s values.

    ``profile``: a Profile, a built-in id or a profile file (ignored when ``base`` is given).

    Raises:
        InputError: a value that is not valid for its parameter (all of them at once).
        UsageError: an unknown built-in profile id; arguments of the wrong type.
    """
    if not isinstance(parameters, Mapping):
        raise UsageError(f"recipe_from takes the parameters as a mapping (name -> value), got {kind(parameters)}")
    if not isinstance(profile, (str, Profile)):
        raise UsageError(f"recipe_from takes a profile id, a profile file or a Profile, got {kind(profile)}")
    if base is not None:
        need_recipe(base, "recipe_from(base=...)")
    for key in parameters:
        if not isinstance(key, str):
            raise UsageError(f"recipe_from takes parameter names as str keys, got {kind(key)}")
    src = Source(f"<{name}>")
    entries = [Entry(k, v, src, ("parameters", k)) for k, v in parameters.items()]
    if base is None:
        prof = profile if isinstance(profile, Profile) else resolve_profile(profile)
        ref = prof.source or prof.id
        base = Recipe(name, None, prof, (), profile_ref=ref)
    return with_overrides(base, entries)
