"""Plan, apply and roll back, as coroutines (``deployer.aio``; ``deployer`` has their blocking twins).

``plan`` makes one device's Plan, or a fleet's (``FleetPlan``); ``apply`` executes a plan exactly (each device
refused before its first write when it no longer holds what its plan was made against), or plans and executes a
recipe in one session per device; ``rollback`` restores snapshots. A run goes through the one machinery every
client uses (``run.request``: the journal, the report file, the locks, interruptions).
"""

from __future__ import annotations

import asyncio
import logging
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any, Literal, overload

from ..calls import checked
from ..errors import UsageError
from ..fleet.inventory import Inventory, fleet_jobs
from ..fleet.plans import FleetPlan
from ..limits import LIMITS
from ..planning.model import Plan, Target
from ..recipe.loader import Recipe
from ..report import DeviceResult, Report
from ..transport.urls import DeviceURL, recorded
from .checks import (
    kind,
    need_batch_by,
    need_choice,
    need_flag,
    need_inventory,
    need_optional_path,
    need_parallel,
    need_path,
    need_recipe,
    need_text,
    need_timing,
    need_unit,
    optional_duration,
    target,
)

if TYPE_CHECKING:
    from ..execute.job import Job
    from ..run.request import PreparedRun, RunRequest

# an inventory as the calls take it: a file, a list of device mappings, or a loaded Inventory
InventoryLike = str | os.PathLike[str] | Inventory | Sequence[Mapping[str, Any]]

log = logging.getLogger("deployer")

# keywords earlier releases took, and what stands for them now
APPLY_HINTS = {
    "options": "ApplyOptions is gone: its fields are apply's keyword arguments (state_dir=..., "
    "write_all=..., on_error=..., allow_broadcast=..., lock_timeout=...)",
    "expected": "apply the Plan itself: deployer.apply(plan)",
}


def _fleet_jobs(
    recipe: Recipe | None,
    inventory: InventoryLike,
    call: str,
    *,
    limit: str | None,
    timeout: float | None,
    retries: int | None,
    unit: int | None,
) -> tuple[Inventory, list[Job]]:
    if limit is not None and not isinstance(limit, str):
        raise UsageError(f"{call} takes limit as a str (names, groups, globs, !x, @REPORT.json), got {kind(limit)}")
    inv = need_inventory(inventory, call)
    jobs = fleet_jobs(inv, recipe, limit, timeout=timeout, retries=retries, unit=unit)
    if not jobs:
        raise UsageError(f"no device selected from {inv.path}")
    return inv, jobs


def _offline_plan(
    recipe: Recipe,
    url: DeviceURL | None,
    unit: int,
    *,
    write_all: bool,
    state_dir: str | None,
    safe_change: bool = False,
) -> Plan:
    """The full write plan, nothing read: over the limits the device taught an earlier apply, as apply uses them."""
    from ..planning.steps import make_plan, pacing_for
    from ..transport.urls import identification

    if url is not None and state_dir is not None:
        from ..state import learned

        recipe, entry = learned.for_recipe(recipe, state_dir, url, unit)
        if entry is not None:
            log.info("%s", learned.note(entry))
    ref = recipe.profile_ref or recipe.profile.id
    return make_plan(
        recipe,
        Target(recorded(url) if url is not None else None, unit, ref),
        None,
        write_all=write_all,
        pacing=pacing_for(url, recipe.profile),
        device_id=None if url is None else identification(url),
        window=safe_change,
    )


@overload
async def plan(
    recipe: Recipe,
    device: str | None = None,
    unit: int | None = None,
    *,
    inventory: None = None,
    limit: None = None,
    timeout: float | None = None,
    retries: int | None = None,
    write_all: bool = False,
    state_dir: str | os.PathLike[str] | None = ".deployer",
    offline: bool = False,
    parallel: int = 8,
    safe_change: bool = False,
) -> Plan: ...


@overload
async def plan(
    recipe: Recipe | None = None,
    device: None = None,
    unit: int | None = None,
    *,
    inventory: InventoryLike,
    limit: str | None = None,
    timeout: float | None = None,
    retries: int | None = None,
    write_all: bool = False,
    state_dir: str | os.PathLike[str] | None = ".deployer",
    offline: bool = False,
    parallel: int = 8,
    safe_change: bool = False,
) -> FleetPlan: ...


@checked("deployer.aio.plan")
async def plan(
    recipe: Recipe | None = None,
    device: str | None = None,
    unit: int | None = None,
    *,
    inventory: InventoryLike | None = None,
    limit: str | None = None,
    timeout: float | None = None,
    retries: int | None = None,
    write_all: bool = False,
    state_dir: str | os.PathLike[str] | None = ".deployer",
    offline: bool = False,
    parallel: int = 8,
    safe_change: bool = False,
) -> Plan | FleetPlan:
    """Every step ``apply`` would take, as data: one device's ``Plan``, or with ``inventory`` a ``FleetPlan``
    (each selected device's plan, or why it has none). Nothing is written.

    The device is read (its identity, what it holds: reads only) and the plan made against what it holds;
    ``offline``: nothing is read, the full write plan. ``device`` and ``unit`` default to the recipe's;
    ``inventory`` (a file, a list of device mappings or an Inventory) and ``limit`` (names, groups, globs,
    ``!x``, ``@REPORT.json``) select devices, ``parallel`` at a time (one per bus), each with its own recipe
    from the inventory when ``recipe`` is None. ``timeout`` and ``retries`` stand where URLs set none.
    ``write_all``: plan every parameter, even those a device already holds; ``safe_change``: the plan of a safe
    change (``apply`` with ``soak`` or ``confirm_within``), which reads the health checks before writing. The
    limits a device taught an earlier apply (kept in ``state_dir``; None: the profiles' alone) are in force, as
    they are for ``apply``.

    Raises:
        UsageError: no device (none given and none in the recipe), a bad URL, unit 0 (broadcast) read;
            arguments of the wrong type or out of their bounds.
        InputError: an invalid inventory, or a device's profile or overrides (every problem at once).
        TransportError: the one device cannot be read (also when its identity does not match). A device of
            an inventory that cannot be read is in the FleetPlan's ``errors``, not raised.
    """
    need_unit(unit)
    need_timing(timeout, retries)
    write_all, offline = need_flag(write_all, "write_all"), need_flag(offline, "offline")
    safe_change = need_flag(safe_change, "safe_change")
    state = need_optional_path(state_dir, "plan", "state_dir")
    if inventory is None:
        if limit is not None:
            raise UsageError("limit selects devices of an inventory: pass inventory too")
        rec = need_recipe(recipe, "plan")
        if offline:
            text = device if device is not None else (rec.device.url if rec.device else None)
            url = None
            if text is not None:
                from .checks import device_url

                url = device_url(text, timeout=timeout, retries=retries)
            u = unit if unit is not None else (rec.device.unit if rec.device and rec.device.unit is not None else 1)
            return _offline_plan(rec, url, u, write_all=write_all, state_dir=state, safe_change=safe_change)
        url, u = target(rec, device, unit, timeout=timeout, retries=retries)
        from ..execute.read import plan_device

        notices: list[str] = []
        made = await plan_device(rec, url, u, write_all=write_all, state_dir=state, notices=notices, window=safe_change)
        for note in notices:
            log.info("%s", note)
        return made
    if device is not None:
        raise UsageError("device and inventory exclude each other")
    parallel = need_parallel(parallel)
    chosen = None if recipe is None else need_recipe(recipe, "plan")
    inv, jobs = _fleet_jobs(chosen, inventory, "plan", limit=limit, timeout=timeout, retries=retries, unit=unit)
    label = None if chosen is None else chosen.path or chosen.name
    if offline:
        return FleetPlan(
            jobs,
            {
                j.name: _offline_plan(
                    j.recipe, j.url, j.unit, write_all=write_all, state_dir=state, safe_change=safe_change
                )
                for j in jobs
            },
            recipe=label,
            inventory=inv.path,
        )
    from ..fleet.rollout import plan_many
    from ..run.runner import ensure_files

    ensure_files(parallel, len(jobs))
    if state is not None:  # what devices taught changes the plans: a damaged file is refused before any read
        from ..state import learned

        learned.load(state)
    made_many = await plan_many(jobs, parallel=parallel, write_all=write_all, state_dir=state, window=safe_change)
    return FleetPlan(jobs, dict(made_many), recipe=label, inventory=inv.path)


def _request(
    command: Literal["apply", "rollback"],
    *,
    parallel: object,
    batch: object,
    batch_by: object,
    max_failures: object,
    on_error: object,
    write_all: object,
    allow_broadcast: object,
    state_dir: object,
    lock_timeout: object,
    soak: object,
    health_interval: object,
    confirm_within: object,
    rollback_on_failure: object,
    report_path: object,
    workers: object,
    call: str,
    allow_unhealthy: object = False,
    **source: Any,
) -> RunRequest:
    """The run's options checked (types, bounds) and said as the one request every client makes."""
    from ..run.request import RunRequest

    return RunRequest(
        command=command,
        parallel=need_parallel(parallel),
        batch=need_text(batch, "batch"),
        max_failures=need_text(max_failures, "max_failures"),
        batch_by=need_batch_by(batch_by),
        on_error="stop" if need_choice(on_error, "on_error", ("continue", "stop")) == "stop" else "continue",
        write_all=need_flag(write_all, "write_all"),
        allow_broadcast=need_flag(allow_broadcast, "allow_broadcast"),
        state_dir=need_path(state_dir, call, "state_dir"),
        lock_timeout=optional_duration(lock_timeout, "lock_timeout") or 0.0,
        soak=optional_duration(soak, "soak"),
        health_interval=optional_duration(health_interval, "health_interval") or 1.0,
        confirm_within=optional_duration(confirm_within, "confirm_within"),
        allow_unhealthy=need_flag(allow_unhealthy, "allow_unhealthy"),
        rollback_on_failure=need_flag(rollback_on_failure, "rollback_on_failure"),
        report_path=need_optional_path(report_path, call, "report_path"),
        workers=None if workers is None else int(LIMITS.workers.check(workers, "workers")),
        **source,
    )


def _apply_jobs(
    what: Recipe | Plan | FleetPlan | None,
    device: str | None,
    unit: int | None,
    *,
    inventory: InventoryLike | None,
    limit: str | None,
    timeout: float | None,
    retries: int | None,
    write_all: bool,
    name: str | None,
) -> tuple[list[Job], str | None, bool]:
    """The jobs ``apply`` runs: (jobs, what is applied (the report's recipe), whether it is a fleet)."""
    from ..execute.job import Job

    if isinstance(what, FleetPlan):
        given = [
            k
            for k, v in (
                ("device", device),
                ("unit", unit),
                ("inventory", inventory),
                ("limit", limit),
                ("timeout", timeout),
                ("retries", retries),
                ("name", name),
            )
            if v is not None
        ]
        if given or write_all:
            raise UsageError(
                f"a FleetPlan runs unchanged, on the devices it was made for: "
                f"{', '.join([*given, *(['write_all'] if write_all else [])])} do not apply to it"
            )
        from ..fleet.plans import executable_jobs

        return executable_jobs(what), what.recipe, True
    if isinstance(what, Plan):
        if inventory is not None or limit is not None or write_all:
            raise UsageError(
                "a Plan is one device's and runs unchanged: inventory, limit and write_all do not apply "
                "to it (plan the inventory for a FleetPlan)"
            )
        from ..planning.planfile import plan_recipe

        rec = plan_recipe(what)
        url, u = target(rec, device, unit, timeout=timeout, retries=retries)
        if device is None:  # the plan's URL: a timeout given now goes over its own
            from ..transport.urls import overridden

            url = overridden(url, timeout, retries)
        return [Job(name or rec.name, rec, url, u, plan=what)], what.recipe or rec.name, False
    if what is not None:
        need_recipe(what, "apply")
    elif inventory is None:
        raise UsageError(
            "apply takes a Plan, a FleetPlan or a Recipe (None: each device's own recipe from the "
            "inventory, with inventory=...), got NoneType None"
        )
    label = None if what is None else what.path or what.name
    if inventory is not None:
        if device is not None or name is not None:
            raise UsageError(f"{'device' if device is not None else 'name'} and inventory exclude each other")
        need_unit(unit)
        return (
            _fleet_jobs(what, inventory, "apply", limit=limit, timeout=timeout, retries=retries, unit=unit)[1],
            label,
            True,
        )
    if limit is not None:
        raise UsageError("limit selects devices of an inventory: pass inventory too")
    assert what is not None
    url, u = target(what, device, unit, timeout=timeout, retries=retries)
    return [Job(name or what.name, what, url, u)], label, False


def _refuse_broadcast(jobs: Sequence[Job], allow: bool) -> None:
    for j in jobs:
        if j.unit == 0 and not allow:
            raise UsageError(
                f"{j.name}: unit 0 is broadcast (no device answers, nothing can be verified); pass "
                "allow_broadcast=True to send it anyway"
            )


async def _execute(
    prepared: PreparedRun,
    *,
    caller: str | None,
    signals: bool,
    on_start: Callable[[str], None] | None,
    on_done: Callable[[DeviceResult], None] | None,
    **hooks: Any,
) -> Report:
    from ..run.request import execute

    if caller is not None and not isinstance(caller, str):
        raise UsageError(f"caller takes a str, got {kind(caller)}")
    for what, hook in (("on_start", on_start), ("on_done", on_done), *hooks.items()):
        if hook is not None and not callable(hook):
            raise UsageError(f"{what} takes a function, got {kind(hook)}")
    via = caller.split()[0] if caller and caller.split() else "api"
    return await execute(
        prepared,
        command_line=caller,
        via=via,
        signals=need_flag(signals, "signals"),
        on_start=None if on_start is None else (lambda j: on_start(j.name)),
        on_done=on_done,
        **{k: v for k, v in hooks.items() if v is not None},
    )


@checked("deployer.aio.apply", hints=APPLY_HINTS)
async def apply(
    what: Recipe | Plan | FleetPlan | None,
    device: str | None = None,
    unit: int | None = None,
    *,
    inventory: InventoryLike | None = None,
    limit: str | None = None,
    name: str | None = None,
    timeout: float | None = None,
    retries: int | None = None,
    write_all: bool = False,
    on_error: Literal["continue", "stop"] = "continue",
    allow_broadcast: bool = False,
    parallel: int = 8,
    batch: str | None = None,
    batch_by: Literal["profile", "group"] = "profile",
    max_failures: str | None = None,
    rollback_on_failure: bool = False,
    soak: float | str | None = None,
    health_interval: float | str = 1.0,
    confirm_within: float | str | None = None,
    allow_unhealthy: bool = False,
    on_confirm_wait: Callable[[str, float], None] | None = None,
    report_path: str | os.PathLike[str] | None = None,
    state_dir: str | os.PathLike[str] = ".deployer",
    lock_timeout: float | str = 0.0,
    workers: int | None = 0,
    on_start: Callable[[str], None] | None = None,
    on_done: Callable[[DeviceResult], None] | None = None,
    signals: bool = False,
    caller: str | None = None,
) -> Report:
    """Execute a plan, or plan and execute a recipe, as one journaled run; its Report (never raises for a
    device's fault: that is the device's status in the report, and ``report.exit_code`` says it as the command
    line would).

    ``what``: a ``Plan`` (one device) or a ``FleetPlan``, executed exactly, each device refused before its
    first write when it no longer holds what the plan was made against (``StalePlan``); or a ``Recipe``, planned
    against what each device holds and executed in the same session (``device``/``unit``, else the recipe's
    device; or ``inventory`` and ``limit`` as for ``plan``; None with an inventory: each device's own recipe).
    ``name``: one device's name in the report (default: the recipe's).

    How it writes: ``write_all`` (every parameter, even unchanged ones), ``on_error`` ("continue": the
    parameters after a refused one go out in a new request; "stop": skipped), ``allow_broadcast`` (unit 0).
    A fleet: ``parallel`` devices at once (one per bus), ``batch`` ("1,10%,100%": each batch a share of every
    profile, or of every inventory group with ``batch_by="group"``; a first batch that fails ends the rollout),
    ``max_failures`` ("2", "5%"), ``rollback_on_failure``, ``workers`` (worker processes for a big fleet;
    None: chosen by its size). A safe change: ``soak`` ("30s") watches the profiles' health checks after the
    write every ``health_interval`` and rolls a device back when one fails; ``confirm_within`` holds the commit
    until ``confirm`` is called (from another thread, task or process with the same ``state_dir``), else rolls
    back; ``on_confirm_wait(run, deadline)`` is told the run id once it waits. A safe change's plan reads the
    health checks before the change and does not write a device already failing one, unless
    ``allow_unhealthy``. Durations are seconds or text.

    The run is journaled in ``state_dir`` (``status`` sees it); ``report_path``: the report file, written
    before the first request and as devices finish (``rollback`` of it restores what the run wrote);
    ``lock_timeout``: the wait for a device another run holds. ``on_start(name)`` and ``on_done(result)`` are
    called per device; ``signals``: SIGINT and SIGTERM interrupt the run (own process, main thread);
    ``caller``: who runs it, for the report and the journal ("ansible deployer.modbus.apply"; its first word is
    what ``deployer status`` shows).

    Raises:
        UsageError: no device, a bad URL, a broadcast without ``allow_broadcast``, nothing selected, arguments of
            the wrong type or out of their bounds, a report file that cannot be written, a soak on a profile
            without health checks; nothing was sent.
        InputError: an invalid inventory, or a device's profile, recipe or overrides (all at once).
        StalePlan: a device no longer holds what its plan was made against (nothing was written anywhere;
            ``.report``: the refused run's report, the device ``skipped`` with the values it was found holding).
        RunInterrupted: the run was interrupted (``.report`` says what every device holds).
    """
    from ..run.request import PreparedRun

    need_unit(unit)
    need_timing(timeout, retries)
    if name is not None and not isinstance(name, str):
        raise UsageError(f"apply takes name as a str, got {kind(name)}")
    request = _request(
        "apply",
        parallel=parallel,
        batch=batch,
        batch_by=batch_by,
        max_failures=max_failures,
        on_error=on_error,
        write_all=write_all,
        allow_broadcast=allow_broadcast,
        state_dir=state_dir,
        lock_timeout=lock_timeout,
        soak=soak,
        health_interval=health_interval,
        confirm_within=confirm_within,
        rollback_on_failure=rollback_on_failure,
        report_path=report_path,
        workers=workers,
        call="apply",
        allow_unhealthy=allow_unhealthy,
    )
    if isinstance(what, FleetPlan) and request.workers not in (0, None):
        raise UsageError(
            "a FleetPlan runs in this process (its plans are not handed to worker processes): leave workers at 0"
        )
    if isinstance(what, FleetPlan):
        request = replace(request, workers=0)
    jobs, label, _ = _apply_jobs(
        what,
        device,
        unit,
        inventory=inventory,
        limit=limit,
        timeout=timeout,
        retries=retries,
        write_all=request.write_all,
        name=name,
    )
    _refuse_broadcast(jobs, request.allow_broadcast)
    return await _execute(
        PreparedRun(request, jobs, label),
        caller=caller,
        signals=signals,
        on_start=on_start,
        on_done=on_done,
        on_confirm_wait=on_confirm_wait,
    )


def _rollback_source(source: object) -> dict[str, Any]:
    """A snapshot file, or report files (told by their content): the request's ``source`` or ``from_reports``."""
    paths = [source] if isinstance(source, (str, os.PathLike)) else source
    if isinstance(paths, (bytes, Mapping)) or not isinstance(paths, Sequence) or not paths:
        raise UsageError(f"rollback takes a snapshot file, a report file or a list of report files, got {kind(source)}")
    files = [need_path(p, "rollback", "a snapshot or report file") for p in paths]
    reports = [f for f in files if _is_report(f)]
    if len(files) == 1 and not reports:
        return {"source": files[0]}
    if len(reports) != len(files):
        raise UsageError(
            f"rollback takes one snapshot, or report files: {', '.join(set(files) - set(reports))} is no report"
        )
    return {"from_reports": tuple(files)}


def _is_report(path: str) -> bool:
    """A report (JSON) rather than a snapshot (a recipe deployer wrote as YAML): by its name, else its first byte."""
    if path.endswith(".json"):
        return True
    try:
        with open(path, "rb") as f:
            return f.read(256).lstrip()[:1] == b"{"
    except OSError:
        return False


@checked("deployer.aio.rollback")
async def rollback(
    source: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    device: str | None = None,
    unit: int | None = None,
    *,
    limit: str | None = None,
    timeout: float | None = None,
    retries: int | None = None,
    to_other_device: bool = False,
    even_if_changed: bool = False,
    accept_edited_snapshot: bool = False,
    parallel: int = 8,
    report_path: str | os.PathLike[str] | None = None,
    state_dir: str | os.PathLike[str] = ".deployer",
    lock_timeout: float | str = 0.0,
    on_start: Callable[[str], None] | None = None,
    on_done: Callable[[DeviceResult], None] | None = None,
    signals: bool = False,
    caller: str | None = None,
) -> Report:
    """Restore what devices held before an apply, as one journaled run; its Report.

    ``source``: a snapshot file (what ``apply`` saved before its first write: ``DeviceResult.snapshot``),
    restored to the device it was taken from (``device``/``unit`` another one, only with ``to_other_device``);
    or an earlier run's report file (``report_path``), or several (a rollout and its retries): every device
    those runs may have written, each from its own snapshot (``limit`` selects among them). A device that no
    longer holds what the run left there refuses the rollback, unless ``even_if_changed``. A snapshot edited
    since it was saved is refused unless ``accept_edited_snapshot``. The other keywords as for ``apply``.

    Raises:
        UsageError: no snapshot known for a device that may have been written, a changed device, another device
            without ``to_other_device``, arguments of the wrong type; nothing was sent.
        InputError: an invalid snapshot or report file.
        RunInterrupted: the run was interrupted (``.report`` says what every device holds).
    """
    from ..run.request import prepare

    need_unit(unit)
    need_timing(timeout, retries)
    whence = _rollback_source(source)
    if "from_reports" in whence and (device is not None or unit is not None):
        raise UsageError(
            "the devices of a report are restored each from its own snapshot, to the device it was "
            "taken from: device and unit do not apply"
        )
    request = _request(
        "rollback",
        parallel=parallel,
        batch=None,
        batch_by="profile",
        max_failures=None,
        on_error="continue",
        write_all=False,
        allow_broadcast=False,
        state_dir=state_dir,
        lock_timeout=lock_timeout,
        soak=None,
        health_interval=1.0,
        confirm_within=None,
        rollback_on_failure=False,
        report_path=report_path,
        workers=0,
        call="rollback",
        device=need_text(device, "device"),
        unit=unit,
        timeout=timeout,
        retries=retries,
        limit=need_text(limit, "limit"),
        accept_edited_snapshot=need_flag(accept_edited_snapshot, "accept_edited_snapshot"),
        even_if_changed=need_flag(even_if_changed, "even_if_changed"),
        all_or_nothing=True,
        **whence,
    )
    if limit is not None and not request.from_reports:
        raise UsageError("limit selects among the devices of report files: a snapshot is one device's")
    # in a thread of its own: a rollback of a run reads its devices first (are they as the run left them?), with an
    # event loop of its own
    prepared = await asyncio.to_thread(prepare, request)
    if prepared.moved is not None and not need_flag(to_other_device, "to_other_device"):
        raise UsageError(
            f"{prepared.moved}: restoring a snapshot to another device needs to_other_device=True; nothing was sent"
        )
    for note in prepared.notices:
        log.info("%s", note)
    return await _execute(prepared, caller=caller, signals=signals, on_start=on_start, on_done=on_done)
