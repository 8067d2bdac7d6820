"""What deployer's own command line needs of the library beyond the public API (``deployer.api.__all__``).

Not public: nothing here is promised to stay, and there is no ``__all__``. The command line (``deployer/cli``)
reaches into the library through this module, ``deployer.api`` and ``deployer.errors`` only (and the few
modules tests/test_import_graph.py lists), so what it needs is one visible list; a name that Ansible, the site
agent or a user needs belongs in the public API instead.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

from ..calls import in_own_loop
from ..errors import InputError, TransportError, UsageError
from ..fleet.inventory import Inventory, load_inventory
from ..fleet.inventory import fleet_jobs as _fleet_jobs
from ..fleet.plans import fleet_plan_text
from ..planning.model import Cost, Plan, Target
from ..planning.planfile import plan_to_json
from ..planning.steps import make_plan
from ..portable import file_name, user_name
from ..profile import Profile, is_profile_path, load_profile, resolve_profile
from ..profile.codec import format_decimal, layout_name, mask_shift
from ..profile.model import address_text
from ..recipe.loader import Recipe
from ..recipe.loader import load_recipe as _load_recipe
from ..report import DEVICE_STATUSES, Report, report_from_json, report_text, run_info
from ..run.request import PreparedRun, RunRequest
from ..transport.urls import DeviceURL, describe, recorded
from .checks import (
    device_url,
    kind,
    need_inventory,
    need_parallel,
    need_path,
    need_recipe,
    need_timing,
    need_unit,
    target,
)
from .runs import confirm_outcome, resolve_run
from .runs import status as run_status
from .values import (
    defaults_diff,
    diff_values,
    non_default,
    out_of_range,
    pull_names,
    pulled_recipe,
)

if TYPE_CHECKING:  # their modules import pymodbus: loaded when a command needs them
    from ..execute.job import Job
    from ..execute.probe import ProbeResult
    from ..execute.scan import ScanResult
    from ..fleet.rollout import ReadJob
    from ..profile.emit import Draft
    from ..profile.importers.sunspec import DeviceModel as SunSpecModel
    from ..state.learned import Entry as LearnedEntry
    from ..transport.ports import SerialPort

# what the command line takes from here (for the linters and type checkers; it promises nothing to anyone else)
__all__ = [
    "DeviceURL",
    "Job",
    "PreparedRun",
    "ReadJob",
    "RunRequest",
    "address_text",
    "builtin_profiles",
    "check_folder",
    "check_output",
    "confirm_outcome",
    "defaults_diff",
    "describe_url",
    "device_url",
    "diff_values",
    "file_name",
    "fleet_jobs",
    "fleet_plan_text",
    "forget_learned",
    "format_decimal",
    "import_csv",
    "import_sunspec",
    "import_sunspec_chain",
    "import_wb_template",
    "import_xlsx",
    "imported_profile",
    "layout_name",
    "learned_limits",
    "mask_shift",
    "non_default",
    "out_of_range",
    "plan_async",
    "plan_cost",
    "plan_fleet_async",
    "plan_to_json",
    "plan_values",
    "prepare_run",
    "probe",
    "profile_csv",
    "profile_skeleton",
    "pull_async",
    "pull_jobs",
    "pull_names",
    "pulled_recipe",
    "read_fleet_async",
    "read_jobs",
    "register_address",
    "report_from_json",
    "report_text",
    "resolve_run",
    "run_info",
    "run_prepared_async",
    "run_status",
    "scan",
    "serial_ports",
    "snapshot_text",
    "sunspec_models",
    "sunspec_reported",
    "taught_recipe",
    "url_option",
    "user_name",
    "validate_file",
    "write_output",
    "writing_caches",
]

# names served on first use: their modules import pymodbus (an offline plan, validate and --help do not)
_LAZY = {"Job": "deployer.execute.job", "ReadJob": "deployer.fleet.rollout"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'deployer.api.commands' has no attribute {name!r}")


def describe_url(url: DeviceURL) -> str:
    """A device URL as text, without secrets (no key, certificate or CA paths): for reports and logs."""
    return describe(url)


async def plan_async(
    recipe: Recipe,
    device: str | DeviceURL | None = None,
    unit: int | None = None,
    *,
    write_all: bool = False,
    offline: bool = False,
    state_dir: str | None = ".deployer",
    notices: list[str] | None = None,
    window: bool = False,
) -> Plan:
    """The requests apply would send: against what the device holds now, or ``offline`` the full write plan;
    ``window``: a safe change's plan (the health checks read before the change)."""
    need_recipe(recipe, "plan")
    need_unit(unit)
    if offline:
        u = unit if unit is not None else 1
        return make_plan(
            recipe, Target(None, u, recipe.profile_ref or recipe.profile.id), None, write_all=write_all, window=window
        )
    url, u = target(recipe, device, unit)
    from ..execute.read import plan_device

    return await plan_device(recipe, url, u, write_all=write_all, state_dir=state_dir, notices=notices, window=window)


def plan_values(
    recipe: Recipe,
    current: Mapping[str, tuple[int, ...]] | None,
    device: DeviceURL | None = None,
    unit: int = 1,
    *,
    write_all: bool = False,
    window: bool = False,
) -> Plan:
    """The plan of ``recipe`` against values already read (``current``: {name: registers}, as ``pull`` and
    ``read_fleet`` give them), or with ``current`` None the full write plan, offline. ``device`` and ``unit``:
    what the plan names as its target (``device`` None: none). Nothing is read or sent; the limits taught
    by devices are the caller's (``taught_recipe``)."""
    from ..planning.steps import pacing_for
    from ..transport.urls import identification

    where = Target(recorded(device) if device is not None else None, unit, recipe.profile_ref or recipe.profile.id)
    return make_plan(
        recipe,
        where,
        current,
        write_all=write_all,
        pacing=pacing_for(device, recipe.profile),
        device_id=None if device is None else identification(device),
        window=window,
    )


def plan_cost(plan: Plan, profile: Profile, device: DeviceURL | None = None) -> Cost:
    """What executing a plan costs the device (``deployer.planning.model.Cost``): requests, bytes and time on its
    line (its URL's serial settings; Modbus/TCP frames on tcp:// and tls://; else RTU at 19200 baud 8E1), the
    waits, and the writes that wear its non-volatile memory."""
    from ..planning.wire import plan_cost as cost

    return cost(plan, profile, device)


def taught_recipe(
    recipe: Recipe, device: str | DeviceURL, unit: int = 1, *, state_dir: str = ".deployer"
) -> tuple[Recipe, str | None]:
    """``recipe`` with the limits ``device`` taught an earlier apply in force, as ``plan`` and ``apply`` use
    them, and the note that says so (None: nothing taught, the recipe unchanged).

    Raises:
        UsageError: a bad URL or unit; a recipe no plan can carry over what the device taught (a parameter longer
            than the writes it takes: the message names the limit as taught, and when). InputError: a learned file
            deployer did not write.
    """
    from ..state import learned

    need_recipe(recipe, "taught_recipe")
    need_unit(unit)
    out, entry = learned.for_recipe(recipe, os.fspath(state_dir), device_url(device), unit)
    return out, None if entry is None else learned.note(entry)


async def pull_async(
    profile: str | Profile, device: str | DeviceURL, unit: int = 1, *, names: Sequence[str] | None = None
) -> dict[str, tuple[int, ...]]:
    """``pull`` for callers with their own event loop."""
    need_unit(unit)
    if not isinstance(profile, (str, Profile)):
        raise UsageError(f"pull takes a profile id, a profile file or a Profile, got {kind(profile)}")
    prof = profile if isinstance(profile, Profile) else resolve_profile(profile)
    if names is not None:
        unknown = [n for n in names if not isinstance(n, str) or prof.get(n) is None]
        if unknown:
            raise UsageError(f"pull: profile {prof.id} has no parameter {', '.join(map(repr, unknown))}")
    from ..execute.read import read_current

    return await read_current(prof, pull_names(prof) if names is None else list(names), device_url(device), unit)


def fleet_jobs(
    recipe: Recipe | None,
    inventory: str | Inventory,
    *,
    limit: str | None = None,
    timeout: float | None = None,
    retries: int | None = None,
    unit: int | None = None,
) -> list[Job]:
    """One checked job per selected device: ``recipe`` (None: each device's own from the inventory) with
    the device's profile and overrides.

    ``inventory``: a file or an Inventory (``inventory_from``); ``limit``: names, groups, globs, ``!x``,
    ``@REPORT.json`` (as ``--limit``). ``timeout``, ``retries`` and ``unit`` override every device's.

    Raises:
        InputError: an invalid inventory, or devices that cannot have their job (profile, recipe, overrides,
            URL), naming the devices, all at once.
        UsageError: nothing selected, or a ``limit`` word that matches nothing; arguments of the wrong type
            or out of their bounds (``LIMITS``).
    """
    if recipe is not None:
        need_recipe(recipe, "fleet_jobs")
    need_inventory(inventory, "fleet_jobs")
    need_timing(timeout, retries)
    need_unit(unit)
    inv = inventory if isinstance(inventory, Inventory) else load_inventory(inventory)
    jobs = _fleet_jobs(inv, recipe, limit, timeout=timeout, retries=retries, unit=unit)
    if not jobs:
        raise UsageError(f"no device selected from {inv.path}")
    return jobs


def read_jobs(jobs: Sequence[Job]) -> list[ReadJob]:
    """Plan and diff read what each device's recipe names."""
    from ..fleet.rollout import ReadJob

    return [ReadJob(j.name, j.recipe.profile, tuple(d.name for d in j.recipe.desired), j.url, j.unit) for j in jobs]


def pull_jobs(
    inventory: str | Inventory,
    *,
    limit: str | None = None,
    profile: str | Profile | None = None,
    timeout: float | None = None,
    retries: int | None = None,
    unit: int | None = None,
) -> list[ReadJob]:
    """What ``pull --inventory`` reads: one ``ReadJob`` per selected device, of every parameter ``pull_names``
    gives for the device's profile: its own (or its groups'), else its recipe's, as plan, apply and diff use it,
    else ``profile``. ``timeout``, ``retries`` and ``unit`` stand for the inventory's where given. Read them
    with ``read_fleet_async``; nothing is sent here.

    Raises:
        InputError: every device without a profile, with an unknown one or a bad URL (its position in the
            inventory), and every problem of the files it names.
    """
    from .reading import pull_reads

    inv = inventory if isinstance(inventory, Inventory) else load_inventory(inventory)
    return pull_reads(profile, inv, limit=limit, names=None, timeout=timeout, retries=retries, unit=unit)


async def read_fleet_async(
    jobs: Sequence[ReadJob],
    *,
    parallel: int = 8,
    on_done: Callable[[str, str | None], None] | None = None,
) -> dict[str, dict[str, tuple[int, ...]] | TransportError | UsageError]:
    """Current values of many devices: name -> registers by parameter, or the error that stopped the read."""
    from ..fleet.rollout import read_many
    from ..run.runner import ensure_files

    need_parallel(parallel)
    ensure_files(parallel, len(jobs))
    return await read_many(jobs, parallel=parallel, on_done=on_done)


async def plan_fleet_async(
    jobs: Sequence[Job],
    *,
    parallel: int = 8,
    write_all: bool = False,
    on_done: Callable[[str, str | None], None] | None = None,
    state_dir: str | None = ".deployer",
    window: bool = False,
) -> dict[str, Plan | TransportError | UsageError]:
    """``plan_fleet`` for callers with their own event loop; ``on_done(name, error or None)`` per device read."""
    from ..fleet.rollout import plan_many

    need_parallel(parallel)
    return await plan_many(
        jobs, parallel=parallel, write_all=write_all, state_dir=state_dir, on_done=on_done, window=window
    )


def prepare_run(request: RunRequest) -> PreparedRun:
    """Check an apply or rollback request and build its jobs, nothing sent: the command line's ``apply`` and
    ``rollback`` are this, a confirmation, and ``run_prepared``.

    Raises:
        UsageError: a bad combination of options (``--limit`` without an inventory ...), a number out of its
            bounds (``LIMITS``), no device, a snapshot given as a recipe, a soak without health checks.
        InputError: an invalid recipe, plan, inventory or snapshot.
    """
    from ..run.request import prepare

    if not isinstance(request, RunRequest):
        raise UsageError(f"prepare_run takes a RunRequest, got {kind(request)}")
    return prepare(request)


async def run_prepared_async(prepared: PreparedRun, **kw: Any) -> Report:
    """``run_prepared`` for callers with their own event loop."""
    from ..run.request import execute

    if not isinstance(prepared, PreparedRun):
        raise UsageError(f"run_prepared takes a PreparedRun (deployer.prepare_run(request)), got {kind(prepared)}")
    return await execute(prepared, **kw)


def writing_caches() -> contextlib.AbstractContextManager[None]:
    """A block within which deployer keeps its disk caches (pint's parsed units in ``~/.cache``) up to date,
    as the command line does for each command; outside one, deployer only reads them and leaves no files."""
    from ..state.caches import writing

    return writing()


def probe(
    profile: str | Profile, device: str | DeviceURL, unit: int = 1, *, expect: Mapping[str, str] | None = None
) -> ProbeResult:
    """Check a profile against a live device, read-only (``deployer probe``): its identity, every readable
    parameter, and for ``expect`` (name -> a value known to be held, in the parameter's unit) the byte/word
    layout or scale that gives it. Returns a result with ``identity``, ``values``, ``findings`` and
    ``changes`` (suggested profile changes; empty when the profile fits).

    Raises:
        UsageError: a bad URL, unit or profile, an ``expect`` name the profile does not have.
        TransportError: the device cannot be read.
    """
    from ..execute.probe import probe as _probe

    need_unit(unit)
    prof = profile if isinstance(profile, Profile) else load_profile(profile)
    wanted = dict(expect or {})
    for name in wanted:
        if prof.get(name) is None:
            raise UsageError(f"probe: profile {prof.id} has no parameter {name!r}")
    url = device_url(device)
    return in_own_loop(lambda: _probe(prof, url, unit, wanted), "probe")


def scan(device: str | DeviceURL, units: Iterable[int], *, register: int = 0) -> ScanResult:
    """Ask each unit id of ``units`` on a bus (the URL's timeout per unit, no retries), read-only
    (``deployer scan``): a result with ``units`` (each ``unit``, ``answer``, ``identity``), ``asked``,
    ``seconds`` and ``url``; ``.inventory_text(url, when)`` is an inventory fragment of the units found.

    Raises:
        UsageError: a bad URL. TransportError: the bus cannot be opened.
    """
    from ..execute.scan import scan as _scan

    url = device_url(device)
    ids = list(units)
    return in_own_loop(lambda: _scan(url, ids, register=register), "scan")


def serial_ports() -> list[SerialPort]:
    """This system's serial ports as pyserial finds them, sorted by name (COM2 before COM10): each with its
    ``device`` (COM3, /dev/ttyUSB0), the ``url`` that names it (``rtu://COM3``), the adapter's ``description``
    and ``hwid`` (USB VID:PID and serial number), and ``to_json()``. Nothing is opened."""
    from ..transport.ports import serial_ports as _serial_ports

    return _serial_ports()


def learned_limits(state_dir: str = ".deployer") -> tuple[str, list[LearnedEntry]]:
    """What devices taught by their refusals (``deployer learned list``): the file's path, and its entries
    (each ``profile``, ``device``, ``limits``, ``seen``, ``when``, ``describe_limits()``, ``to_json()``).

    Raises:
        InputError: a learned file deployer did not write (with its position and how to clear it).
    """
    from ..state import learned

    need_path(state_dir, "learned_limits", "state_dir")
    return learned.path_of(os.fspath(state_dir)), learned.load(os.fspath(state_dir))


def forget_learned(
    state_dir: str = ".deployer", *, profile: str | None = None, device: str | DeviceURL | None = None, unit: int = 1
) -> list[LearnedEntry]:
    """Forget what devices taught (``deployer learned forget``): of ``profile`` (a built-in id or a file), of
    ``device`` (a URL, with ``unit``), or everything when neither is given. Returns the entries forgotten.

    Raises:
        UsageError: a bad URL or unit.
    """
    from ..state import learned

    need_path(state_dir, "forget_learned", "state_dir")
    need_unit(unit)
    ref = None
    if profile is not None:
        ref = os.path.abspath(profile) if is_profile_path(profile) else profile  # as profile_ref names it
    key = None if device is None else learned.device_id(device_url(device), unit)
    return learned.forget(os.fspath(state_dir), profile=ref, device=key)


def _filekind(data: object) -> str | None:
    if not isinstance(data, dict):
        return None
    from ..load.schema import document_of

    told = document_of(data)
    if told is not None:
        return told  # before "recipe": a plan and a report name their recipe
    if "recipe" in data:
        return "recipe"
    if "devices" in data:
        return "inventory"
    if "users" in data:
        return "users"  # the agent's users file (deployer agent --users)
    params = data.get("parameters")
    declares = isinstance(params, dict) and any(isinstance(v, dict) and "register" in v for v in params.values())
    if "profile" in data and (declares or data.keys() & {"tables", "addressing", "limits", "identity", "commit"}):
        return "profile"
    if "profile" in data or "extends" in data:
        return "recipe"  # a recipe without its 'recipe' key: let the schema say so
    return None


def _count(count: int, noun: str) -> str:
    return f"{count} {noun}{'' if count == 1 else 's'}"


def validate_file(path: str | os.PathLike[str]) -> str:
    """Check one file of any kind (a profile, recipe, inventory, users file, saved plan or report, told by its keys) as
    ``deployer validate`` does, nothing sent; returns a one-line summary ("recipe line3: 4 parameters for
    profile example-inverter"). An inventory is checked as ``plan`` and ``apply`` would check it: each
    device's profile, URL, and its recipe with its overrides.

    Raises:
        InputError: the file is not valid, or not a deployer file (with positions).
        UsageError: ``path`` is not a path.
    """
    from ..load import yamlsrc
    from ..planning.planfile import plan_from_json
    from ..profile import load_profile_file

    need_path(path, "validate_file", "the file")
    where = os.fspath(path)
    data, src = yamlsrc.load(where, hand_over=True)  # the loader below takes it over: parsed once
    try:
        kind = _filekind(data)
        if kind == "profile":
            prof = load_profile_file(where)
            return f"profile {prof.id}: {_count(len(prof.parameters), 'parameter')}"
        if kind == "recipe":
            rec = _load_recipe(where)
            return f"recipe {rec.name}: {_count(len(rec.desired), 'parameter')} for profile {rec.profile.id}"
        if kind == "inventory":
            inv = load_inventory(where)
            # what plan and apply would check before sending anything: each device's profile, URL, and its
            # recipe (from the inventory) with its overrides; devices without one get theirs on the command line
            jobs = _fleet_jobs(inv, None, None, require_recipe=False)
            recipes = {j.recipe.path for j in jobs}
            return f"inventory: {_count(len(inv.devices), 'device')}" + (
                f", {_count(len(recipes), 'recipe')}" if recipes else ""
            )
        if kind == "users":
            from ..agent.users import parse as parse_users

            people = parse_users(data, src)
            return f"users: {_count(len(people), 'user')}, {sum(not u.disabled for u in people.values())} enabled"
        if kind == "plan":
            saved = plan_from_json(data, where, src=src)
            return f"plan: {_count(len(saved.writes), 'write request')} for profile {saved.device.profile}"
        if kind == "fleetplan":  # checked as a saved plan is: the profiles are checked when it runs
            from ..fleet.plans import read_fleet_plan

            _, plans = read_fleet_plan(where)  # takes the document over: every device's plan at its positions
            writes = sum(len(p.writes) for _, _, p, _, _ in plans)
            return f"fleet plan: {_count(len(plans), 'device')}, {_count(writes, 'write request')}"
        if kind == "report":
            from .loading import load_report

            summary = load_report(where).summary()
            said = ", ".join(f"{summary[s]} {s}" for s in DEVICE_STATUSES if summary[s])
            return f"report: {_count(summary['devices'], 'device')}" + (f", {said}" if said else "")
        what = (
            "cannot tell what this file is"
            if isinstance(data, dict)
            else f"expected a mapping, got {'a list' if isinstance(data, list) else 'a single value'}"
        )
        raise InputError(
            [
                src.error(
                    (),
                    f"{what}: a profile has 'profile' and 'parameters', a recipe has "
                    "'recipe', an inventory has 'devices', the agent's users file has 'users', a saved plan or a "
                    "report its 'schema'",
                )
            ]
        )
    finally:
        yamlsrc.forget(where)


def snapshot_text(
    profile: str | Profile,
    values: Mapping[str, tuple[int, ...]],
    *,
    name: str,
    url: str,
    unit: int = 1,
    applied: str,
    path: str,
    taken: float | None = None,
) -> str:
    """A snapshot's text as ``apply`` writes it before its first write (a recipe that ``rollback`` restores
    bit for bit): what device ``name`` at ``url`` unit ``unit`` held (``values``: {parameter: registers}) at
    ``taken`` (seconds since the epoch; None: now) before ``applied`` (a recipe's path or name), saved as
    ``path`` (its comment says how to restore it).

    Raises:
        UsageError: an unknown profile or parameter.
    """
    import time

    from ..state.snapshot import snapshot_text as _snapshot_text

    prof = profile if isinstance(profile, Profile) else load_profile(profile)
    unknown = [n for n in values if prof.get(n) is None]
    if unknown:
        raise UsageError(f"snapshot_text: profile {prof.id} has no parameter {', '.join(map(repr, unknown))}")
    when = time.gmtime(time.time() if taken is None else taken)
    return _snapshot_text(
        prof, values, name=name, url=url, unit=unit, taken=when, applied=applied, label=applied, path=path
    )


def url_option(name: str) -> tuple[list[str], str | None, str | None]:
    """A device URL option (``baudrate``, ``timeout``): the schemes that take it (none: no such option), its
    default and what it allows, as ``deployer explain`` shows them (docs/urls.md says what each means)."""
    from ..transport.urls import option_facts

    return option_facts(name)


def builtin_profiles() -> list[Profile]:
    """Every built-in profile (``deployer profiles list``), by id."""
    from ..profile import builtin_profile, builtin_profile_ids

    return [builtin_profile(pid) for pid in builtin_profile_ids()]


def profile_csv(profile: str | Profile) -> tuple[str, list[str]]:
    """A profile as a CSV register list (``profiles export csv``; ``profiles import csv`` reads it back: wire
    addresses, tables as rows), and what a register list cannot say about it (each lost on a round trip).

    Raises:
        UsageError: an unknown profile.
        InputError: a profile file that is not valid.
    """
    from ..profile.importers.spreadsheet import not_exported, profile_to_csv

    prof = profile if isinstance(profile, Profile) else load_profile(profile)
    return profile_to_csv(prof), not_exported(prof)


def profile_skeleton(profile_id: str, path: str = "FILE") -> str:
    """A commented profile skeleton for ``profile_id`` (``profiles new``), to fill in from the device's manual;
    ``path``: where it will be, for the command its comments suggest. Checking the id is the caller's (the
    profile schema's ``profile`` pattern)."""
    from ..profile.skeleton import profile_skeleton as _skeleton

    return _skeleton(profile_id, path)


def import_csv(
    path: str,
    *,
    profile_id: str,
    columns: Mapping[str, str] | None = None,
    addressing: str = "address",
    delimiter: str | None = None,
    byte_order: str | None = None,
    decimal: str | None = None,
) -> tuple[Draft, list[str]]:
    """A vendor's CSV register list (``profiles import csv``) as a draft profile, and warnings; make the profile
    with ``imported_profile``. ``columns``: our column -> its header; ``addressing``: ``address``,
    ``register-number`` or ``modicon``; ``decimal``: ``comma`` or ``point`` (None: told cell by cell).

    Raises:
        InputError: every bad cell at once, at its position.
        UsageError: the file cannot be read.
    """
    from ..profile.importers.spreadsheet import read_csv

    return read_csv(
        path,
        profile_id=profile_id,
        columns=columns,
        addressing=addressing,
        delimiter=delimiter,
        byte_order=byte_order,
        decimal=decimal,
    )


def import_xlsx(
    path: str,
    *,
    profile_id: str,
    sheet: str | None = None,
    columns: Mapping[str, str] | None = None,
    addressing: str = "address",
    byte_order: str | None = None,
    decimal: str | None = None,
) -> tuple[Draft, list[str]]:
    """A register list in an Excel workbook (``profiles import xlsx``; needs openpyxl), as ``import_csv`` reads
    a CSV file; ``sheet``: the worksheet (None: the first).

    Raises:
        InputError: every bad cell at once, at FILE[SHEET]:ROW:COLUMN.
        UsageError: the file cannot be read, or openpyxl is not installed.
    """
    from ..profile.importers.spreadsheet import read_xlsx

    return read_xlsx(
        path,
        profile_id=profile_id,
        sheet=sheet,
        columns=columns,
        addressing=addressing,
        byte_order=byte_order,
        decimal=decimal,
    )


def import_wb_template(path: str, *, profile_id: str | None = None, channels: bool = True) -> tuple[Draft, list[str]]:
    """A wb-mqtt-serial device template (``profiles import wb-template``) as a draft profile, and warnings (the
    last one counting the entries left out, when some were): its parameters become settings, its channels
    read-only values (``channels`` False: left out). ``profile_id`` None: the template's device_type.

    Raises:
        InputError: not such a template, or invalid (at its position).
    """
    from ..profile.importers.wbtemplate import read_wb_template

    imported = read_wb_template(path, profile_id=profile_id, channels=channels)
    warnings = imported.warnings
    if imported.left_out:
        n = imported.left_out
        warnings = [
            *warnings,
            f"{path}: {n} {'entry' if n == 1 else 'entries'} of the template left out (see the warnings above)",
        ]
    return imported.draft, warnings


def imported_profile(draft: Draft, path: str, comment: str = "") -> tuple[str, Profile]:
    """The profile an importer's draft makes: its text (``comment`` on top) and the Profile it loads as, checked
    to read back as imported; ``path``: where it will be written (the positions of its problems).

    Raises:
        InputError: the draft's problems, pointing at the source's rows.
    """
    from ..profile.emit import check

    return check(draft, path, comment)


def register_address(text: str) -> int:
    """A register address as profiles write it: 4354, 0x1102 or 1102h (a protocol address); ValueError if it is
    not one."""
    from ..profile import parse_register

    return parse_register(text)


def import_sunspec(
    model: str,
    *,
    at: int = 40002,
    scale_factors: Mapping[str, int] | None = None,
    counts: Mapping[str, int] | None = None,
    profile_id: str | None = None,
    point_values: Mapping[str, int] | None = None,
    length: int | None = None,
) -> tuple[Draft, list[str]]:
    """A SunSpec model (its number, name or a model JSON file; pysunspec2's definitions) as a draft profile with
    its ID register at protocol address ``at``, and warnings (``profiles import sunspec``). ``scale_factors``
    and ``counts``: what the device reports (by point and group name); ``point_values`` and ``length``: its
    count points and L as ``sunspec_reported`` and ``sunspec_models`` read them.

    Raises:
        UsageError: an unknown model, or pysunspec2 is not installed.
        InputError: a model file that is not valid.
    """
    from ..profile.importers.sunspec import read_model

    return read_model(
        model,
        at=at,
        scale_factors=scale_factors,
        counts=counts,
        profile_id=profile_id,
        point_values=point_values,
        length=length,
    )


def sunspec_models(
    device: str | DeviceURL, unit: int = 1, *, at: int = 40002, model: str | None = None, search: bool = False
) -> list[SunSpecModel]:
    """Read a SunSpec device's models, read-only: ``model`` at ``at`` (its ID checked), or with ``model`` None
    the whole chain from the 'SunS' marker two registers before ``at`` to the end marker (``search``: also
    where devices put it, 0 and 50000). Each with its ID, address, length L and registers.

    Raises:
        TransportError: the device cannot be read, or has no such registers (the message says where to look).
        UsageError: a bad URL, or what was read is not SunSpec.
    """
    from ..errors import ExceptionResponse
    from ..execute.connect import opened
    from ..profile.importers import sunspec

    need_unit(unit)
    url = device_url(device)

    async def run() -> list[SunSpecModel]:
        transport = opened(url, None)
        await transport.connect()

        async def read(address: int, count: int) -> list[int]:
            out: list[int] = []
            for a in range(address, address + count, 125):
                n = min(125, address + count - a)
                try:
                    out += await transport.read_holding_registers(a, n, unit)
                except ExceptionResponse as e:
                    said = f"{describe(url)} unit {unit}: reading {n} registers at {a} answered {e}"
                    if e.code == 2:
                        raise sunspec.NotThere(
                            f"{said}: check --at (SunSpec devices put 'SunS' at 40000, 0 or "
                            "50000, the first model's ID 2 registers after it)"
                        ) from None
                    raise TransportError(said) from None
            return out

        try:
            if model is None:
                return await sunspec.device_chain(read, at, search=search)
            return [await sunspec.device_model(read, model, at)]
        finally:
            await transport.close()

    try:
        return asyncio.run(run())
    except sunspec.NotThere as e:  # no such registers: the device is there, the model is not where asked
        raise TransportError(str(e)) from None


def sunspec_reported(model: str, found: SunSpecModel) -> tuple[dict[str, int], dict[str, int], list[str]]:
    """The scale factors and count points a device reports in its model ``found`` (``sunspec_models``), by point
    name, and warnings (a scale factor not implemented or out of range: the points it scales import raw)."""
    from ..profile.importers.sunspec import reported

    return reported(model, found)


def import_sunspec_chain(
    models: list[SunSpecModel],
    *,
    scale_factors: Mapping[str, int] | None = None,
    counts: Mapping[str, int] | None = None,
    profile_id: str | None = None,
    source: str = "the device",
) -> tuple[Draft, list[str]]:
    """One draft profile of a device's whole model chain (``sunspec_models`` without a model): each model's
    points named MODEL.POINT (common.Mn, inverter.W), its scale factors and counts as the device reports them
    (``scale_factors`` and ``counts`` given here win), the markers and model IDs as its identity.

    Raises:
        UsageError: a model pysunspec2 does not know, or pysunspec2 is not installed.
    """
    from ..profile.importers.sunspec import chain_draft

    return chain_draft(models, scale_factors=scale_factors, counts=counts, profile_id=profile_id, source=source)


def check_folder(folder: str | os.PathLike[str], *, what: str) -> None:
    """Create ``folder`` if need be and make sure a file can be written there (``what``: what goes there, for
    the message), before any device is read.

    Raises:
        UsageError: it cannot be created or written, and why.
    """
    from ..run.runner import check_writable

    check_writable(os.fspath(folder), what)


def check_output(path: str | os.PathLike[str], *, replace: bool = True, what: str = "") -> None:
    """Whether deployer may write an output file at ``path``, said before any work: only new paths and
    regular files (a link, FIFO, device node, socket or folder is refused, never opened); an existing file
    only with ``replace``. ``what`` names the file in the message ("the report").

    Raises:
        UsageError: the path is refused (``OutputRefused``).
    """
    from ..state.durable import check_output as _check

    _check(os.fspath(path), replace=replace, what=what)


def write_output(path: str | os.PathLike[str], text: str | bytes, *, replace: bool = True, what: str = "") -> None:
    """Write an output file (a report, plan, page, recipe or profile) as deployer writes its own: whole or
    not at all, and durable (``check_output``'s rule, a temporary file, fsync, rename, the folder fsync'ed).

    Raises:
        UsageError: the path is refused, or the disk refuses (full, read-only).
    """
    from ..state.durable import write_atomic

    write_atomic(os.fspath(path), text, replace=replace, what=what)
