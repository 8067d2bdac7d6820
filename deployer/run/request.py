"""What a run is asked to do (``RunRequest``), checked and turned into jobs (``prepare``), then run (``execute``).

The command line's ``apply`` and ``rollback``, the Ansible modules and the site agent describe a run the
same way: a recipe, a saved plan or a snapshot (or an earlier run's report), the devices, and the run's
options. ``prepare`` refuses every bad combination before anything is sent and builds one job per
device; ``execute`` runs them (``run.runner.run_async``). What only an interactive client does (asking
before a write, showing progress) comes in as callbacks.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Literal

from ..errors import UsageError
from ..fleet.plans import is_fleet_plan_file
from ..limits import LIMITS

if TYPE_CHECKING:
    from ..execute.job import Job
    from ..execute.session import Confirm
    from ..recipe.loader import Recipe
    from ..report import DeviceResult, Report


@dataclass(frozen=True)
class RunRequest:
    """An apply or a rollback as a client asks for it: what, where, and how.

    ``source``: a recipe file, a saved plan (``PLAN.json``), or for ``command="rollback"`` a snapshot; None
    with ``inventory``: each device's own recipe from the inventory. ``from_reports``: a rollback of every
    device those runs may have written (a device changed since is refused by name, the others restored;
    ``all_or_nothing``: one changed device refuses them all). ``device``/``unit`` (one device), or
    ``inventory`` and ``limit`` (a fleet); ``timeout``/``retries`` override every device's. ``batch`` (a
    share of every profile, or of every group: ``batch_by``), ``max_failures``, ``pause`` and ``ask``
    stage a fleet run; ``soak``, ``health_interval`` and ``confirm_within`` make it a safe change, which does
    not write a device already failing a health check unless ``allow_unhealthy``.
    ``workers``: worker processes running the devices of a plain fleet run (0: none; None: one per CPU
    for a fleet of 100 devices or more where they are forked, Linux, else 1,000, ``fleet.workers``). Numbers
    are in seconds, within ``deployer.LIMITS``.
    """

    source: str | None = None
    command: Literal["apply", "rollback"] = "apply"
    device: str | None = None
    unit: int | None = None
    timeout: float | None = None
    retries: int | None = None
    inventory: str | None = None
    limit: str | None = None
    from_reports: tuple[str, ...] = ()
    force: bool = False
    accept_edited_snapshot: bool = False
    even_if_changed: bool = False
    all_or_nothing: bool = False
    parallel: int = 8
    batch: str | None = None
    max_failures: str | None = None
    batch_by: str = "profile"
    on_error: Literal["continue", "stop"] = "continue"
    write_all: bool = False
    allow_broadcast: bool = False
    state_dir: str = ".deployer"
    lock_timeout: float = 0.0
    soak: float | None = None
    health_interval: float = 1.0
    confirm_within: float | None = None
    allow_unhealthy: bool = False  # a soak or confirmation writes a device whose health checks fail already
    rollback_on_failure: bool = False
    pause: float | None = None
    ask: bool = False
    report_path: str | None = None
    html_path: str | None = None
    workers: int | None = 0
    policy: str | None = None  # the site's change-control policy (an inventory), else DEPLOYER_POLICY's

    @functools.cached_property  # asked several times a run; a saved fleet plan is told by reading its file
    def fleet(self) -> bool:
        """An inventory's devices, every device of earlier runs, or a saved fleet plan's: reported as a fleet."""
        return bool(
            self.inventory
            or self.from_reports
            or (self.command == "apply" and self.source is not None and is_fleet_plan_file(self.source))
        )


@dataclass(frozen=True)
class PreparedRun:
    """A checked request and its jobs, nothing sent yet.

    ``label``: what is applied (the report's ``recipe``); ``moved``: set when a snapshot is to be restored to
    another device than the one it was taken from (the client must have the user's consent first); ``notices``:
    what the preparation has to say (an old snapshot without a digest ...); ``refused``: devices a rollback
    leaves alone, each with why (``jobs`` may then be empty).
    """

    request: RunRequest
    jobs: list[Job]
    label: str | None
    moved: str | None = None
    notices: list[str] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)
    change: dict[str, Any] | None = None  # a saved plan's change control, checked (digest, author, signatures)
    # the inventory whose change_control: governs the run besides --policy: the request's, or the one a saved fleet
    # plan was made from (so that planning it first is no way around that inventory's policy)
    inventory: str | None = None


def is_plan_file(path: str) -> bool:
    """A saved plan (``plan --out``), by its name or its first bytes."""
    if path.endswith(".json"):
        return True
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    return head.lstrip().startswith(b"{") and b"deployer.plan/" in head


def _check_numbers(r: RunRequest) -> None:
    LIMITS.parallel.check(r.parallel, "parallel")
    for key in ("timeout", "retries", "soak", "confirm_within", "pause"):
        if getattr(r, key) is not None:
            getattr(LIMITS, key).check(getattr(r, key), key)
    LIMITS.health_interval.check(r.health_interval, "health_interval")
    LIMITS.lock_timeout.check(r.lock_timeout, "lock_timeout")
    if r.workers is not None:
        LIMITS.workers.check(r.workers, "workers")


def _check_combinations(r: RunRequest) -> None:
    if not r.fleet and (r.batch or r.max_failures or r.limit):
        raise UsageError("--limit, --batch and --max-failures need --inventory")
    if r.allow_unhealthy and r.soak is None and r.confirm_within is None:
        raise UsageError(
            "--allow-unhealthy goes with --soak or --confirm-within (only a safe change reads the "
            "health checks before it writes)"
        )
    if (r.pause is not None or r.ask) and not r.batch:
        raise UsageError("--pause and --ask go between batches: give --batch too")
    if r.from_reports and (r.inventory or r.device or r.unit is not None):
        raise UsageError(
            "rollback --from-report restores each device from its own snapshot, to the device it "
            "was taken from: --inventory, --device and --unit do not apply"
        )
    if r.source is None and not r.from_reports and not r.inventory:
        raise UsageError(
            f"pass {'SNAPSHOT' if r.command == 'rollback' else 'RECIPE'}, or --inventory FILE "
            "whose devices name their recipes"
        )
    if r.inventory and r.device:
        raise UsageError("--device and --inventory exclude each other")
    if r.command == "rollback" and r.source is not None and r.inventory:
        raise UsageError(
            f"{r.source} is one device's snapshot: it restores only the device it was taken from. "
            "To roll back a fleet run, use: deployer rollback --from-report REPORT.json"
        )


def _fleet_jobs(recipe: Recipe | None, r: RunRequest) -> list[Job]:
    from ..fleet.inventory import fleet_jobs, load_inventory

    assert r.inventory is not None
    inv = load_inventory(r.inventory)
    jobs = fleet_jobs(inv, recipe, r.limit, timeout=r.timeout, retries=r.retries, unit=r.unit)
    if not jobs:
        raise UsageError(f"no device selected from {inv.path}")
    return jobs


def _recipe_jobs(r: RunRequest) -> PreparedRun:
    """apply RECIPE or PLAN.json: one device, or every device of the inventory."""
    from ..execute.job import Job
    from ..planning.planfile import load_plan
    from ..recipe.loader import load_recipe
    from ..transport.urls import overridden, parse_url

    assert r.source is not None
    expected = None
    if is_fleet_plan_file(r.source):
        return _fleet_plan_jobs(r)
    if is_plan_file(r.source):
        if r.inventory or r.write_all:
            raise UsageError("a saved plan runs unchanged: --inventory and --write-all do not apply to it")
        rec, expected = load_plan(r.source)
    else:
        rec = load_recipe(r.source, force=r.force)
    if rec.snapshot is not None:
        raise UsageError(f"{r.source} is a snapshot: restore it with deployer rollback {r.source}")
    if r.inventory:
        return PreparedRun(r, _fleet_jobs(rec, r), r.source)
    text = r.device or (rec.device.url if rec.device else None)
    if text is None:
        raise UsageError("no device: pass --device URL or set device.url in the recipe")
    unit = r.unit if r.unit is not None else (rec.device.unit if rec.device and rec.device.unit is not None else 1)
    url = parse_url(text, timeout=r.timeout, retries=r.retries)  # BadURL is a UsageError
    if expected is not None and r.device is None:  # the saved plan's URL: a timeout given now goes over its own
        url = overridden(url, r.timeout, r.retries)
    return PreparedRun(r, [Job(rec.name, rec, url, unit, plan=expected)], r.source)


def _fleet_plan_jobs(r: RunRequest) -> PreparedRun:
    """apply FLEET.json: every device the saved fleet plan names, each executing its own plan unchanged."""
    from ..fleet.plans import executable_jobs, load_fleet_plan

    assert r.source is not None
    given = [
        o
        for o, v in (
            ("--inventory", r.inventory),
            ("--limit", r.limit),
            ("--device", r.device),
            ("--unit", r.unit is not None),
            ("--write-all", r.write_all),
        )
        if v
    ]
    if given:
        raise UsageError(
            f"a saved fleet plan runs unchanged, on every device it names: {', '.join(given)} do not apply to it "
            "(plan the fleet again for other devices)"
        )
    fleet = load_fleet_plan(r.source, timeout=r.timeout, retries=r.retries)
    made_from = fleet.inventory if os.path.isfile(fleet.inventory) else None  # where it still is
    return PreparedRun(r, executable_jobs(fleet), r.source, inventory=made_from)


def prepare(r: RunRequest) -> PreparedRun:
    """Check ``r`` and build its jobs; nothing is sent. Raises UsageError or InputError."""
    from ..run.rollback import report_jobs, snapshot_job

    _check_numbers(r)
    _check_combinations(r)
    if r.from_reports:  # every device those runs wrote, each from its own snapshot
        refused: list[str] = []  # devices changed since the run, left alone
        jobs, notices = report_jobs(
            r.from_reports,
            limit=r.limit,
            force=r.force,
            timeout=r.timeout,
            retries=r.retries,
            accept_edited=r.accept_edited_snapshot,
            even_if_changed=r.even_if_changed,
            refused=None if r.all_or_nothing else refused,
        )
        prepared = PreparedRun(
            r,
            jobs,
            r.from_reports[0] if len(r.from_reports) == 1 else ", ".join(r.from_reports),
            notices=list(notices),
            refused=refused,
        )
    elif r.source is None:  # each device's recipe from the inventory
        prepared = PreparedRun(r, _fleet_jobs(None, r), None)
    elif r.command == "rollback":
        job, moved, notices = snapshot_job(
            r.source,
            device=r.device,
            unit=r.unit,
            timeout=r.timeout,
            retries=r.retries,
            force=r.force,
            accept_edited=r.accept_edited_snapshot,
        )
        prepared = PreparedRun(r, [job], r.source, moved=moved, notices=list(notices))
    else:
        prepared = _recipe_jobs(r)
    if r.soak is not None:
        from ..window.soak import check_soak_profiles

        check_soak_profiles([j.recipe.profile for j in prepared.jobs])
    if r.html_path:  # before anything is sent: a link, a FIFO or a folder there is refused now
        from ..state.durable import check_output

        check_output(r.html_path, what="the page")
    from ..change.gate import check_run  # the change control's one check, before anything is sent

    inventory = r.inventory or prepared.inventory
    change = check_run(
        command=r.command,
        source=r.source,
        jobs=prepared.jobs,
        policy_path=r.policy,
        inventory=inventory,
        state_dir=r.state_dir,
    )
    return replace(prepared, change=change, inventory=inventory)


def safe_plans(jobs: Sequence[Job], r: RunRequest, label: str | None) -> None:
    """A safe change executes only plans made for one: they read the health checks before writing (else a device
    already in alarm would be written, then rolled back and the change blamed). UsageError, nothing sent."""
    if r.soak is None and r.confirm_within is None:
        return
    fleet = r.fleet  # a saved fleet plan's jobs (an inventory's run makes its plans: none of them is saved)
    for j in jobs:
        if j.plan is not None and j.recipe.profile.health and not any(s.kind == "health" for s in j.plan.steps):
            made = "[RECIPE] --inventory FILE" if fleet else f"{j.plan.recipe or 'RECIPE'} --device URL"
            where = f"--safe-change --out {'FLEET' if fleet else 'PLAN'}.json"
            raise UsageError(
                f"{label or 'the plan'} is not the plan of a safe change: it reads no health checks "
                "before writing (a device already in alarm would be written, then rolled back and the "
                f"change blamed); make it with: deployer plan {made} {where} (Python: plan(..., safe_change=True))"
            )


async def execute(
    prepared: PreparedRun,
    *,
    confirm: Confirm | None = None,
    command_line: str | None = None,
    argv: Sequence[str] = (),
    via: str = "api",
    signals: bool = False,
    on_start: Callable[[Job], None] | None = None,
    on_done: Callable[[DeviceResult], None] | None = None,
    **hooks: Any,
) -> Report:
    """Run a prepared request as one journaled run; its report (RunInterrupted carries it when interrupted).

    ``confirm(plan, device)``: asked before each device's write (None: no question). ``command_line``
    and ``argv``: what started the run, for the report and the journal; ``via``: "cli", "api", "ansible".
    ``hooks``: ``between_batches``, ``on_confirm_wait``, ``on_soak``, ``on_changed`` of the rollout.
    """
    from ..execute.session import ApplyOptions
    from ..run.runner import run_async

    r = prepared.request
    safe_plans(prepared.jobs, r, prepared.label)
    options = ApplyOptions(
        on_error=r.on_error,
        write_all=r.write_all,
        allow_broadcast=r.allow_broadcast,
        state_dir=os.fspath(r.state_dir),
        confirm=confirm,
        lock_timeout=r.lock_timeout,
        soak=r.soak,
        health_interval=r.health_interval,
        confirm_within=r.confirm_within,
        allow_unhealthy=r.allow_unhealthy,
        command=command_line,
    )
    return await run_async(
        prepared.jobs,
        command=r.command,
        label=prepared.label,
        argv=argv,
        via=via,
        options=options,
        parallel=r.parallel,
        batch=r.batch,
        max_failures=r.max_failures,
        batch_by=r.batch_by,
        report_path=r.report_path,
        signals=signals,
        refuse_broadcast=True,
        rollback_on_failure=r.rollback_on_failure,
        on_start=on_start,
        on_done=on_done,
        workers=r.workers,
        **hooks,
    )
