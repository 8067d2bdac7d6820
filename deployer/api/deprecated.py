"""The names ``deployer`` and ``deployer.api`` exported before 0.x's smaller API, for one more release.

Each still works, with a ``DeprecationWarning`` naming what stands for it now (``REMOVED``); CHANGELOG.md lists
them. The functions below are the old ones whose behaviour has no other home (the command line uses none of
them); the rest are served from where they live now. This module goes in the release after next.
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

from ..calls import in_own_loop
from ..errors import TransportError, UsageError
from ..fleet.inventory import Inventory
from ..limits import LIMITS, Bound
from ..recipe.loader import Recipe
from ..report import DeviceResult, Report
from ..transport.urls import DeviceURL
from .checks import duration, kind, need_batch_by, need_inventory, need_parallel, need_path, need_recipe, target
from .commands import fleet_jobs, plan_fleet_async, read_fleet_async, run_prepared_async
from .values import Drift, diff_values

if TYPE_CHECKING:
    from ..execute.job import Job
    from ..execute.session import ApplyOptions
    from ..fleet.rollout import ReadJob
    from ..planning.model import Plan
    from ..run.request import PreparedRun

_ERRORS = "deployer.errors.{name} (the whole error tree is there)"
_CLI = "no replacement in the API: a helper of deployer's command line now (deployer.api.commands, not public)"

# removed name -> (where it lives now, "module:attribute"; what stands for it now)
REMOVED: dict[str, tuple[str, str]] = {
    "AgentError": ("deployer.errors:AgentError", _ERRORS),
    "ApplyOptions": (
        "deployer.execute.session:ApplyOptions",
        "the keyword arguments of deployer.apply (state_dir=, write_all=, on_error=, soak= ...)",
    ),
    "BadURL": ("deployer.errors:BadURL", _ERRORS),
    "Bound": ("deployer.limits:Bound", "the type of deployer.LIMITS's fields (deployer.LIMITS.parallel ...)"),
    "CodecError": ("deployer.errors:CodecError", _ERRORS),
    "Declined": ("deployer.errors:Declined", _ERRORS),
    "DeviceURL": ("deployer.transport.urls:DeviceURL", "a device URL as text (tcp://HOST:PORT ...)"),
    "FleetDevice": ("deployer.fleet.inventory:FleetDevice", "the items of Inventory.devices"),
    "FromDefault": ("deployer.api.values:FromDefault", _CLI),
    "IdentityMismatch": ("deployer.errors:IdentityMismatch", _ERRORS),
    "Job": ("deployer.execute.job:Job", "deployer.plan(recipe, inventory=...), a FleetPlan, for deployer.apply"),
    "Locked": ("deployer.errors:Locked", _ERRORS),
    "ParameterResult": ("deployer.report:ParameterResult", "the items of DeviceResult.parameters"),
    "PreparedRun": ("deployer.run.request:PreparedRun", "deployer.apply and deployer.rollback"),
    "ReadJob": ("deployer.fleet.rollout:ReadJob", "deployer.pull(what, inventory=...)"),
    "RunRequest": ("deployer.run.request:RunRequest", "deployer.apply and deployer.rollback"),
    "RunStatus": ("deployer.api.runs:RunStatus", "what deployer.status returns"),
    "address_text": ("deployer.profile.model:address_text", _CLI),
    "apply_async": ("deployer.api.deprecated:apply_async", "deployer.aio.apply"),
    "apply_fleet": ("deployer.api.deprecated:apply_fleet", "deployer.apply(recipe, inventory=...)"),
    "apply_fleet_async": ("deployer.api.deprecated:apply_fleet_async", "deployer.aio.apply(recipe, inventory=...)"),
    "builtin_profiles": ("deployer.api.commands:builtin_profiles", _CLI),
    "check_folder": ("deployer.api.commands:check_folder", _CLI),
    "check_output": ("deployer.api.commands:check_output", _CLI),
    "confirm_outcome": ("deployer.api.runs:confirm_outcome", "deployer.confirm(run, wait=True)"),
    "defaults_diff": ("deployer.api.values:defaults_diff", _CLI),
    "describe_url": ("deployer.api.commands:describe_url", "Pulled.device and DeviceResult.url (URLs without secrets)"),
    "device_url": ("deployer.api.checks:device_url", "a device URL as text; timeout= and retries= of each call"),
    "diff_async": ("deployer.api.deprecated:diff_async", "deployer.aio.diff"),
    "diff_values": ("deployer.api.values:diff_values", "deployer.diff"),
    "duration": ("deployer.api.checks:duration", 'durations as text ("30s") or seconds, taken by deployer.apply'),
    "file_name": ("deployer.portable:file_name", _CLI),
    "fleet_jobs": ("deployer.api.commands:fleet_jobs", "deployer.plan(recipe, inventory=...)"),
    "forget_learned": ("deployer.api.commands:forget_learned", _CLI + " (deployer learned forget)"),
    "import_csv": ("deployer.api.commands:import_csv", _CLI + " (deployer profiles import csv)"),
    "import_sunspec": ("deployer.api.commands:import_sunspec", _CLI + " (deployer profiles import sunspec)"),
    "import_sunspec_chain": (
        "deployer.api.commands:import_sunspec_chain",
        _CLI + " (deployer profiles import sunspec)",
    ),
    "import_wb_template": (
        "deployer.api.commands:import_wb_template",
        _CLI + " (deployer profiles import wb-template)",
    ),
    "import_xlsx": ("deployer.api.commands:import_xlsx", _CLI + " (deployer profiles import xlsx)"),
    "imported_profile": ("deployer.api.commands:imported_profile", _CLI + " (deployer profiles import)"),
    "inventory_from": ("deployer.api.deprecated:inventory_from", "deployer.load_inventory(devices)"),
    "learned_limits": ("deployer.api.commands:learned_limits", _CLI + " (deployer learned list)"),
    "non_default": ("deployer.api.values:non_default", _CLI + " (deployer pull --non-default)"),
    "out_of_range": ("deployer.api.values:out_of_range", "Pulled.out_of_range()"),
    "plan_async": ("deployer.api.commands:plan_async", "deployer.aio.plan"),
    "plan_cost": ("deployer.api.commands:plan_cost", _CLI + " (deployer plan prints the cost)"),
    "plan_fleet": ("deployer.api.deprecated:plan_fleet", "deployer.plan(recipe, inventory=...)"),
    "plan_fleet_async": ("deployer.api.commands:plan_fleet_async", "deployer.aio.plan(recipe, inventory=...)"),
    "plan_frames": ("deployer.api.deprecated:plan_frames", _CLI + " (deployer plan --show-frames)"),
    "plan_to_json": ("deployer.planning.model:plan_to_json", "Plan.to_json()"),
    "plan_values": ("deployer.api.commands:plan_values", "deployer.plan(recipe, offline=True)"),
    "prepare_run": ("deployer.api.commands:prepare_run", "deployer.apply and deployer.rollback"),
    "probe": ("deployer.api.commands:probe", _CLI + " (deployer probe)"),
    "profile_csv": ("deployer.api.commands:profile_csv", _CLI + " (deployer profiles export csv)"),
    "profile_skeleton": ("deployer.api.commands:profile_skeleton", _CLI + " (deployer profiles new)"),
    "profile_table": (
        "deployer.cli.profiles:profile_table",
        "no replacement in the API: the command line's own now (deployer profiles show)",
    ),
    "pull_async": ("deployer.api.commands:pull_async", "deployer.aio.pull"),
    "pull_jobs": ("deployer.api.commands:pull_jobs", "deployer.pull(what, inventory=...)"),
    "pull_names": ("deployer.api.values:pull_names", "deployer.pull (it reads those)"),
    "pulled_recipe": ("deployer.api.values:pulled_recipe", "Pulled.recipe_text() (deployer.pull's result)"),
    "read_fleet": ("deployer.api.deprecated:read_fleet", "deployer.pull(what, inventory=...)"),
    "read_fleet_async": ("deployer.api.commands:read_fleet_async", "deployer.aio.pull(what, inventory=...)"),
    "read_jobs": ("deployer.api.commands:read_jobs", "deployer.pull(recipe, inventory=...)"),
    "read_report": ("deployer.api.loading:load_report", "deployer.load_report"),
    "register_address": ("deployer.api.commands:register_address", _CLI),
    "report_from_json": ("deployer.report:report_from_json", "deployer.load_report (a report file)"),
    "report_text": ("deployer.report:report_text", "Report.to_json()"),
    "resolve_run": ("deployer.api.runs:resolve_run", _CLI + " (deployer status --resolve)"),
    "run_fleet": (
        "deployer.api.deprecated:run_fleet",
        "deployer.apply(fleet_plan) or deployer.apply(recipe, inventory=...)",
    ),
    "run_fleet_async": ("deployer.api.deprecated:run_fleet_async", "deployer.aio.apply"),
    "run_info": ("deployer.report:run_info", "Report.run"),
    "run_prepared": ("deployer.api.deprecated:run_prepared", "deployer.apply and deployer.rollback"),
    "run_prepared_async": ("deployer.api.commands:run_prepared_async", "deployer.aio.apply and deployer.aio.rollback"),
    "run_status": ("deployer.api.runs:status", "deployer.status"),
    "safe_options": (
        "deployer.api.deprecated:safe_options",
        "deployer.apply(..., soak=, health_interval=, confirm_within=)",
    ),
    "scan": ("deployer.api.commands:scan", _CLI + " (deployer scan)"),
    "serial_ports": ("deployer.api.commands:serial_ports", _CLI + " (deployer scan --list-ports)"),
    "snapshot_text": ("deployer.api.commands:snapshot_text", _CLI),
    "sunspec_models": ("deployer.api.commands:sunspec_models", _CLI + " (deployer profiles import sunspec)"),
    "sunspec_reported": ("deployer.api.commands:sunspec_reported", _CLI + " (deployer profiles import sunspec)"),
    "taught_recipe": ("deployer.api.commands:taught_recipe", "deployer.plan (it plans over what devices taught)"),
    "url_option": ("deployer.api.commands:url_option", _CLI + " (deployer explain)"),
    "user_name": ("deployer.portable:user_name", _CLI),
    "validate_file": ("deployer.api.commands:validate_file", _CLI + " (deployer validate)"),
    "write_output": ("deployer.api.commands:write_output", _CLI),
    "writing_caches": ("deployer.api.commands:writing_caches", _CLI),
}


def replacement(name: str) -> str:
    """What stands for removed name ``name`` now."""
    return REMOVED[name][1].format(name=name)


def removed(name: str, *, stacklevel: int = 3) -> Any:
    """The object removed name ``name`` stands for, with a DeprecationWarning naming its replacement (pointing at
    the caller's line: ``stacklevel`` counts this function and the module ``__getattr__`` calling it)."""
    where, _ = REMOVED[name]
    text = replacement(name)
    warnings.warn(
        f"deployer.{name} is deprecated and goes in the next release; "
        + (text if text.startswith("no replacement") else f"use {text}"),
        DeprecationWarning,
        stacklevel=stacklevel,
    )
    module, _, attr = where.partition(":")
    return getattr(importlib.import_module(module), attr)


def _need_options(options: object, call: str) -> ApplyOptions:
    """``options`` (None: the defaults) checked against the bounds, before anything is sent."""
    from ..execute.session import ApplyOptions

    if options is None:
        return ApplyOptions()
    if not isinstance(options, ApplyOptions):
        raise UsageError(f"{call} takes options=ApplyOptions(...), got {kind(options)}")
    if options.on_error not in ("continue", "stop"):
        raise UsageError(f"on_error must be 'continue' or 'stop', got {kind(options.on_error)}")
    need_path(options.state_dir, call, "options.state_dir")
    for key in ("soak", "confirm_within", "health_interval", "lock_timeout"):
        value = getattr(options, key)
        if value is not None:
            bound: Bound = getattr(LIMITS, key)
            bound.check(value, key)
    return options


def safe_options(
    options: ApplyOptions | None,
    *,
    soak: float | str | None = None,
    health_interval: float | str | None = None,
    confirm_within: float | str | None = None,
) -> ApplyOptions:
    """``options`` with a soak and a confirmation window (durations as "30s" or seconds).

    A confirmation needs a run id to be named by: one is made when ``options`` has none.

    Raises:
        UsageError: a duration that is not one (e.g. "soon"), or out of its bounds (``LIMITS``).
    """
    from dataclasses import replace

    from ..state.journal import new_run_id

    opts = _need_options(options, "safe_options")
    changes: dict[str, Any] = {}
    for key, value in (("soak", soak), ("health_interval", health_interval), ("confirm_within", confirm_within)):
        if value is not None:
            changes[key] = duration(value, key)
    opts = _need_options(replace(opts, **changes), "safe_options")
    if opts.confirm_within is not None and opts.run_id is None:
        opts = replace(opts, run_id=new_run_id())
    return opts


async def apply_async(
    recipe: Recipe,
    device: str | DeviceURL | None = None,
    unit: int | None = None,
    *,
    options: ApplyOptions | None = None,
    name: str | None = None,
    soak: float | str | None = None,
    health_interval: float | str | None = None,
    confirm_within: float | str | None = None,
    on_confirm_wait: Callable[[str, float], None] | None = None,
    report_path: str | None = None,
) -> Report:
    """Apply to one device; the report says per parameter what it holds now (never raises for a device fault).

    A safe change: ``soak`` ("30s", or seconds) watches the profile's health checks after the write and
    rolls the device back when one fails; ``confirm_within`` holds the profile's commit until ``confirm``
    is called (from another thread, task or process with the same state directory), else rolls back.
    ``on_confirm_wait(run, deadline)`` is told the run id to confirm once it waits. The run is journaled in
    ``options.state_dir`` (``deployer status`` sees it); ``report_path``: the report file, written before
    the first request and at the end. Raises RunInterrupted (with its ``report``) when cancelled mid-run.
    """
    need_recipe(recipe, "apply")
    url, u = target(recipe, device, unit)
    if report_path is not None:
        need_path(report_path, "apply", "report_path")
    opts = safe_options(options, soak=soak, health_interval=health_interval, confirm_within=confirm_within)
    from ..execute.job import Job
    from ..run.runner import run_async

    return await run_async(
        [Job(name or recipe.name, recipe, url, u)],
        label=recipe.path or recipe.name,
        parallel=1,
        options=opts,
        report_path=report_path,
        on_confirm_wait=on_confirm_wait,
    )


async def diff_async(recipe: Recipe, device: str | DeviceURL | None = None, unit: int | None = None) -> list[Drift]:
    """``diff`` for callers with their own event loop."""
    need_recipe(recipe, "diff")
    url, u = target(recipe, device, unit)
    from ..execute.read import read_current

    return diff_values(recipe, await read_current(recipe.profile, [d.name for d in recipe.desired], url, u))


async def apply_fleet_async(
    recipe: Recipe | None,
    inventory: str | Inventory,
    *,
    limit: str | None = None,
    parallel: int = 8,
    batch: str | None = None,
    max_failures: str | None = None,
    options: ApplyOptions | None = None,
    report_path: str | None = None,
    on_start: Callable[[Job], None] | None = None,
    on_done: Callable[[DeviceResult], None] | None = None,
    batch_by: str = "profile",
) -> Report:
    """Apply to the devices of an inventory (``limit`` selects): staged, with a failure budget, see ``run_fleet``.

    ``recipe`` None: each device gets the recipe the inventory gives it."""
    return await run_fleet_async(
        fleet_jobs(recipe, inventory, limit=limit),
        recipe_name=None if recipe is None else recipe.path or recipe.name,
        parallel=parallel,
        batch=batch,
        max_failures=max_failures,
        options=options,
        report_path=report_path,
        on_start=on_start,
        on_done=on_done,
        batch_by=batch_by,
    )


async def run_fleet_async(
    jobs: Sequence[Job],
    *,
    recipe_name: str | None = None,
    parallel: int = 8,
    batch: str | None = None,
    max_failures: str | None = None,
    options: ApplyOptions | None = None,
    report_path: str | None = None,
    on_start: Callable[[Job], None] | None = None,
    on_done: Callable[[DeviceResult], None] | None = None,
    via: str = "api",
    signals: bool = False,
    batch_by: str = "profile",
    **safe: Any,
) -> Report:
    """Apply jobs as one journaled fleet run (``run.runner.run_async``): ``batch`` ("1,10%,100%") stages it,
    ``max_failures`` ("2", "5%") caps it. Each batch takes its count or share of every profile of the line (one
    device of each profile first), or of every group with ``batch_by="group"`` (a device counts in the first
    group it lists); any device of the first batch that does not end ok ends the rollout.

    ``report_path``: written before the first device starts (every device ``skipped``, "not
    finished") and rewritten as devices finish, so after a crash ``limit="@REPORT"`` retries
    exactly what did not end ok, and ``rollback --from-report`` restores what it wrote. ``via``: who runs it
    (for the journal); ``signals``: SIGINT and SIGTERM interrupt it (own process, main thread). ``safe``:
    ``rollback_on_failure``, ``between_batches`` and ``on_confirm_wait`` of ``fleet.rollout.apply_many`` (the
    soak itself is in ``options``).
    """
    need_parallel(parallel)
    batch_by = need_batch_by(batch_by)
    options = _need_options(options, "run_fleet")
    if report_path is not None:
        need_path(report_path, "run_fleet", "report_path")
    from ..run.runner import run_async

    return await run_async(
        jobs,
        label=recipe_name,
        parallel=parallel,
        batch=batch,
        max_failures=max_failures,
        options=options,
        report_path=report_path,
        on_start=on_start,
        on_done=on_done,
        via=via,
        signals=signals,
        batch_by=batch_by,
        **safe,
    )


def apply_fleet(recipe: Recipe | None, inventory: str | Inventory, **kw: Any) -> Report:
    """Apply to the devices of an inventory; ``kw`` as for ``apply_fleet_async`` (``recipe`` None: each device's
    own from the inventory).

    Raises:
        InputError: an invalid inventory, or a device's profile or overrides (all devices checked first).
        UsageError: nothing selected, a bad ``limit``/``batch``/``max_failures``, a report file that cannot
            be written, too few open files for ``parallel``.
        StalePlan: a saved plan (``options.expected``) no longer matches its device.
    """
    if recipe is not None:
        need_recipe(recipe, "apply_fleet")
    need_inventory(inventory, "apply_fleet")
    return in_own_loop(
        lambda: apply_fleet_async(recipe, inventory, **kw), "deployer.apply_fleet", "deployer.apply_fleet_async"
    )


def run_fleet(jobs: Sequence[Job], **kw: Any) -> Report:
    """Apply jobs (from ``fleet``, or made by hand) as one fleet run; ``kw`` as for ``run_fleet_async``.

    Raises:
        UsageError: a bad ``batch``/``max_failures``, a report file that cannot be written, too few open files.
        StalePlan: a saved plan (``options.expected``) no longer matches its device.
    """
    return in_own_loop(lambda: run_fleet_async(jobs, **kw), "deployer.run_fleet", "deployer.run_fleet_async")


def read_fleet(
    jobs: Sequence[ReadJob], *, parallel: int = 8
) -> dict[str, dict[str, tuple[int, ...]] | TransportError | UsageError]:
    """Current values of many devices, ``parallel`` at a time (one per bus): name -> registers by
    parameter, or the error that stopped that device's read (never raised for one device).

    Raises:
        UsageError: too few open files for ``parallel``.
    """
    return in_own_loop(
        lambda: read_fleet_async(jobs, parallel=parallel), "deployer.read_fleet", "deployer.read_fleet_async"
    )


def plan_fleet(
    jobs: Sequence[Job], *, parallel: int = 8, write_all: bool = False, state_dir: str | None = ".deployer"
) -> dict[str, Plan | TransportError | UsageError]:
    """Check mode for many devices: read each, plan against what it holds, write nothing; with the limits
    each device taught an earlier apply in force (kept in ``state_dir``; None: the profiles' alone).

    Returns name -> its Plan (``plan.writes`` empty: nothing to change), or the error that stopped
    its read (never raised for one device), in the order of ``jobs``.

    Raises:
        UsageError: too few open files for ``parallel``.
    """
    return in_own_loop(
        lambda: plan_fleet_async(jobs, parallel=parallel, write_all=write_all, state_dir=state_dir),
        "deployer.plan_fleet",
        "deployer.plan_fleet_async",
    )


def inventory_from(devices: Iterable[Mapping[str, Any]], *, name: str = "<devices>") -> Inventory:
    """An inventory from a list of devices given in code (Ansible host vars, a database), checked as a file is.

    Each device: ``name`` and ``url`` (required), ``unit`` (1), ``profile`` (a built-in id or a path),
    ``groups``, ``timeout``, ``retries`` and ``parameters`` (values over the recipe's), as in an
    inventory file. ``name`` is what messages call the list.

    Raises:
        InputError: a device that is not valid (all of them at once, positions in the list).
    """
    from ..fleet.inventory import inventory_from as _inventory_from

    return _inventory_from(devices, name)


def run_prepared(prepared: PreparedRun, **kw: Any) -> Report:
    """Run a prepared request as one journaled run and return its report.

    ``kw``: ``confirm(plan, device)`` (an async question before each device's write), ``command_line`` and
    ``argv`` (what started it), ``via``, ``signals`` (SIGINT/SIGTERM interrupt it), ``on_start``, ``on_done``,
    and the rollout's ``between_batches``, ``on_confirm_wait``, ``on_soak``, ``on_changed``.

    Raises:
        UsageError: options the run itself refuses (too few open files, a report file that cannot be written).
        StalePlan: a saved plan no longer matches its device. Declined: ``confirm`` answered no.
        RunInterrupted: the run was interrupted (``.report`` says what every device holds).
    """
    return in_own_loop(
        lambda: run_prepared_async(prepared, **kw), "deployer.run_prepared", "deployer.run_prepared_async"
    )


def plan_frames(plan: Plan, framing: str) -> list[tuple[bytes, bytes | None]]:
    """Each step of a plan as the exact bytes on the wire, ``framing`` ``rtu``, ``ascii`` or ``tcp`` (transaction
    ids 1, 2, ... on TCP): (the query, the device's normal answer; None for a broadcast, and for the answer to a
    Function 43 request, whose texts are the device's). A secret's words are sent as zeros here: show them only
    through ``deployer.planning.frames.shown``, which masks them.

    Raises:
        UsageError: an unknown framing.
    """
    from typing import cast

    from ..planning.frames import Framing, step_frames

    if framing not in ("rtu", "ascii", "tcp"):
        raise UsageError(f"plan_frames: framing is rtu, ascii or tcp, not {framing!r}")
    how = cast(Framing, framing)
    return [step_frames(s, plan.device.unit, how, i) for i, s in enumerate(plan.steps, 1)]
