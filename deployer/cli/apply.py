"""apply, rollback and status: the commands that write, and what they report."""

from __future__ import annotations

import asyncio
import json
import os
import time
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any

import click

from ..errors import EXIT_CHANGES, EXIT_FAILED, EXIT_OK, Declined, StalePlan, UsageError
from ..limits import BATCH_BY, LIMITS
from .base import (
    _n,
    agent_option,
    cli_context,
    command_line,
    console,
    device_options,
    echo,
    fleet_option,
    float_range,
    int_range,
    limit_option,
    parallel_option,
    safe,
    stdin_is_terminal,
)
from .outcome import print_outcome
from .plan import print_plan

if TYPE_CHECKING:
    from rich.console import Console

    from ..api import DeviceResult, Plan, Report
    from ..api.commands import PreparedRun


def run_apply(source: str | None, *, yes: bool, as_json: bool, to_other_device: bool = False, **options: Any) -> int:
    """apply / rollback: the request checked and its jobs built by the library (``deployer.prepare_run``), the
    user's consent asked here, then run by the library (``deployer.run_prepared``) with a progress display."""
    from ..api.commands import RunRequest, prepare_run
    from .base import record_meta

    meta_given: tuple[str, ...] = options.pop("meta", ())
    compact: bool = options.pop("compact", False)
    prepared = prepare_run(RunRequest(source, **options))
    meta = record_meta(prepared.inventory, meta_given) if prepared.request.html_path else []
    for n in prepared.notices:
        echo(safe(n), err=True)
    for n in prepared.refused:
        echo(f"refused: {safe(n)}", err=True)
    if not prepared.jobs:
        echo("nothing restored: every device was refused", err=True)
        return EXIT_FAILED
    request = prepared.request
    if request.ask and not stdin_is_terminal():
        raise UsageError("--ask asks before each batch: stdin is not a terminal (use --pause for an unattended run)")
    err = console(stderr=True)
    _consent_to_move(prepared.moved, err, yes=yes, to_other_device=to_other_device)
    report, interrupted = _run(prepared, err, confirm=None if yes else _confirm_each(prepared, err), as_json=as_json)
    from ..audit.commands import after_run  # the audit trail's records and the plan's change in the report

    after_run(
        report,
        command=request.command,
        change=prepared.change,
        state_dir=request.state_dir,
        policy_path=request.policy,
        inventory=prepared.inventory,
        report_path=request.report_path,
    )
    if request.html_path:
        from ..pages import run_page
        from .base import write_page

        try:
            write_page(run_page(report, meta=meta, compact=compact), request.html_path)
            err.print(f"page: {safe(request.html_path)}")
        except UsageError as e:  # a full disk: what the devices hold is still said, below
            report.unrecorded.append(str(e))
    print_outcome(report, fleet_run=request.fleet, as_json=as_json, report_path=request.report_path)
    if interrupted:
        _said_interrupted(report, request.report_path)
    for what in [*report.unrecorded, *(f"{d.name}: {u}" for d in report.devices for u in d.unrecorded)]:
        echo(f"not recorded: {safe(what)}", err=True)
    if prepared.refused:
        err.print(
            f"refused {len(prepared.refused)} changed device{'s' if len(prepared.refused) != 1 else ''}: "
            + ", ".join(safe(r.split(" ", 1)[0]) for r in prepared.refused)
        )
        return max(report.exit_code, EXIT_FAILED)
    return report.exit_code


def _consent_to_move(moved: str | None, err: Console, *, yes: bool, to_other_device: bool) -> None:
    """A snapshot restored to another device than its own: --to-other-device, or a yes at the terminal."""
    if moved is None:
        return
    if to_other_device:
        err.print(f"warning: {safe(moved)}; restoring it there (--to-other-device)")
        return
    if yes or not stdin_is_terminal():
        raise UsageError(
            f"{moved}: restoring a snapshot to another device needs --to-other-device "
            "(--yes alone is not enough); nothing was sent"
        )
    if not click.confirm(f"{safe(moved)}. Restore it to that other device?", default=False, err=True):
        raise UsageError("nothing was written (declined)")


def _confirm_each(prepared: PreparedRun, err: Console) -> Callable[[Plan, DeviceResult], Awaitable[bool]]:
    """The question before each device's write (one at a time, even for fleets); needs a terminal."""
    if not stdin_is_terminal():
        raise UsageError("refusing to write without confirmation: stdin is not a terminal; pass --yes")
    ask_lock = asyncio.Lock()
    profiles = {j.name: j.recipe.profile for j in prepared.jobs}

    async def confirm(p: Plan, res: DeviceResult) -> bool:
        async with ask_lock:
            from .text import styled

            err.print(styled((res.name, "bold"), f" {res.url} unit {res.unit}:"))
            print_plan(p, profiles[res.name], changes_only=True, out=err)
            return await asyncio.to_thread(click.confirm, "Write these values?", default=False, err=True)

    return confirm


def _run(
    prepared: PreparedRun,
    err: Console,
    *,
    confirm: Callable[[Plan, DeviceResult], Awaitable[bool]] | None,
    as_json: bool,
) -> tuple[Report, bool]:
    """The run (through the library), with its display; (its report, whether it was interrupted)."""
    from ..api import RunInterrupted
    from ..api.commands import run_prepared_async

    r = prepared.request
    hooks = _safe_hooks(
        err,
        r.state_dir,
        pause=r.pause,
        ask=r.ask,
        soak=r.soak,
        interval=r.health_interval,
        staged=bool(r.batch),
        fleet=r.fleet,
    )
    ctx = cli_context()
    kw: dict[str, Any] = dict(
        confirm=confirm, command_line=command_line(r.command), argv=ctx.argv, via="cli", signals=True, **hooks
    )
    # a fleet's table shows only the devices that need a look: the others' details are in the report file
    kw["keep_results"] = bool(as_json or r.html_path or not r.fleet)
    try:
        if r.fleet:
            return _run_fleet(
                prepared,
                kw,
                err,
                live=err.is_terminal and confirm is None and not r.ask and r.confirm_within is None,
                staged=bool(r.batch),
            ), False
        return asyncio.run(run_prepared_async(prepared, **kw)), False
    except RunInterrupted as e:
        return e.report, True
    except (StalePlan, Declined) as e:  # refused before the first write: a caller reading stdout gets the report
        if as_json and e.report is not None:
            print_outcome(e.report, fleet_run=False, as_json=True, report_path=r.report_path)
        raise


def _run_fleet(prepared: PreparedRun, kw: dict[str, Any], err: Console, *, live: bool, staged: bool) -> Report:
    """A fleet run with its progress display (a live one on a terminal, else a line per device)."""
    import gc

    from ..api.commands import run_prepared_async
    from .progress import FleetProgress  # rich's live display: only fleets pay for importing it

    if cli_context().own_process:  # the command's own process only: the library and callers keep their collector
        # what is loaded now (modules, profiles, recipes) lives as long as the command: later collections
        # need not walk it, and a fleet allocates fast, so collect less often (the cyclic collector
        # took 35-50 ms of a 0.7 s run of 200 devices, a 20 ms pause among them)
        gc.freeze()
        gc.set_threshold(20_000, 20, 10)
    # a live display on a terminal (not while asking questions), else a line per device
    progress = FleetProgress(len(prepared.jobs), err, live=live, staged=staged, later=True)  # workers first
    with progress:
        return asyncio.run(
            run_prepared_async(prepared, on_start=lambda j: progress.start(j.name), on_done=progress.device_done, **kw)
        )


def interrupted_outcome(report: Report) -> str:
    """What an interrupted run left, device by device as its report says (the report file, the page and
    stdout say the same): may hold new values, rolled back, kept, failed; or nothing written."""

    def names(ds: list[DeviceResult]) -> str:
        return ", ".join(safe(d.name) for d in ds)

    wrote = [d for d in report.devices if d.snapshot]
    groups = [
        ([d for d in wrote if d.status == "interrupted"], "may hold some new values", ""),
        (
            [d for d in wrote if d.status == "rolled-back"],
            "rolled back to what it held before (verified)",
            "rolled back to what they held before (verified)",
        ),
        ([d for d in wrote if d.status == "ok"], "keeps the new values (verified)", "keep the new values (verified)"),
        (
            [d for d in wrote if d.status not in ("interrupted", "rolled-back", "ok")],
            "did not end as it should (see its status and error)",
            "did not end as they should (see the report)",
        ),
    ]
    said = [
        f"{_n(len(ds), 'device')} {many or one} ({names(ds)})" if len(ds) > 1 else f"{names(ds)} {one}"
        for ds, one, many in groups
        if ds
    ]
    return "; ".join(said) if said else "nothing was written"


def _said_interrupted(report: Report, report_path: str | None) -> None:
    """After Ctrl-C or SIGTERM: what may have been written, and how to undo it (plain lines, never wrapped)."""
    written = [d for d in report.devices if d.status == "interrupted" and d.snapshot]
    echo(
        f"interrupted ({report.interrupted}): {interrupted_outcome(report)}; the journal "
        f"{safe(report.state_dir)}/audit.jsonl has it as run {report.run_id}",
        err=True,
    )
    if len(written) == 1:
        echo(f"undo with: deployer rollback {safe(written[0].snapshot)}", err=True)
    elif written and report_path:
        echo(f"undo with: deployer rollback --from-report {safe(report_path)}", err=True)
    elif written:
        echo("undo with: deployer rollback SNAPSHOT, for each snapshot above", err=True)


def _safe_hooks(
    err: Console,
    state_dir: str,
    *,
    pause: float | None,
    ask: bool,
    soak: float | None = None,
    interval: float = 1.0,
    staged: bool = False,
    fleet: bool = False,
) -> dict[str, Any]:
    """apply_many's keywords for a safe change: a pause and a question between batches, the confirmation wait."""
    from ..load.durations import format_duration

    async def between(number: int, so_far: Report) -> str | None:
        s = so_far.summary()
        done = ", ".join(f"{s[k]} {k}" for k in ("ok", "partial", "failed", "unreachable", "rolled-back") if s[k])
        if pause:
            err.print(f"batch {number - 1} done ({done}); batch {number} starts in {format_duration(pause)}")
            await asyncio.sleep(pause)
        if ask and not await asyncio.to_thread(
            click.confirm, f"batch {number - 1} done ({done}). Continue with batch {number}?", default=False, err=True
        ):
            return f"not started: stopped at the question before batch {number} (--ask)"
        return None

    def waiting(run: str, deadline: float) -> None:

        left = max(0.0, deadline - time.time())
        left = round(left) if left >= 1 else round(left, 3)
        from .text import styled

        err.print(
            styled(
                ("waiting for confirmation", "bold"),
                f" until {time.strftime('%H:%M:%S UTC', time.gmtime(deadline))} ({format_duration(left)} "
                "left): confirm from another shell with",
            )
        )
        err.print(
            f"    deployer confirm {run} --state-dir {safe(state_dir)}\n"
            "without it every device written is rolled back and the commit is never sent"
        )

    def soaking(number: int, names: list[str]) -> None:
        which = safe(names[0]) if len(names) == 1 else _n(len(names), "device")
        err.print(
            f"{f'batch {number}: ' if number > 1 or staged else ''}watching the health of {which} for "
            f"{format_duration(soak or 0)} (every {format_duration(interval)}); a failed check rolls that device "
            "back",
            soft_wrap=True,
        )

    told: set[str] = set()

    def changed(r: DeviceResult) -> None:  # fleets: a progress line for a device its soak rolled back
        if r.status != "ok" and r.name not in told:
            from .text import styled

            told.add(r.name)
            err.print(
                styled(r.name, ": ", (r.status, "bold yellow"), f" - {r.error}" if r.error else ""), soft_wrap=True
            )

    return {
        "between_batches": between,
        "on_confirm_wait": waiting,
        "on_soak": soaking,
        **({"on_changed": changed} if fleet else {}),
    }


def apply_options(f: Callable[..., Any]) -> Callable[..., Any]:
    opts = [
        click.option("--yes", "-y", is_flag=True, help="do not ask for confirmation"),
        click.option("--report", "report_path", type=click.Path(dir_okay=False), help="write the report JSON here"),
        click.option("--json", "as_json", is_flag=True, help="print the report JSON"),
        click.option(
            "--meta",
            multiple=True,
            metavar="KEY=VALUE",
            help="with --html: a line of the record's page header (site=..., project=..., customer=..., "
            "line=...; repeatable; wins over the inventory's meta:)",
        ),
        click.option(
            "--compact",
            is_flag=True,
            help="with --html: a record for large lines: one table row per device, parameters only for "
            "devices that changed or did not end ok",
        ),
        click.option(
            "--html",
            "html_path",
            type=click.Path(dir_okay=False),
            metavar="FILE",
            help="also write the report as one self-contained HTML page (sortable, filterable; it "
            "prints as the commissioning record: as found / as left per device)",
        ),
        fleet_option,
        limit_option,
        click.option(
            "--batch",
            metavar="1,10%,100%",
            help="staged rollout: each batch takes this count or % of every profile of the selection "
            "(1,25%,100%: one device of each profile first; % rounded, never 0; the last repeats); "
            "each batch finishes before the next; any canary (batch 1) device not ending ok, or a "
            "later batch with no ok device, ends the rollout",
        ),
        click.option(
            "--batch-by",
            type=click.Choice(BATCH_BY),
            default="profile",
            show_default=True,
            help="what each --batch share is taken of: every profile, or every group (a device counts "
            "in the first group it lists)",
        ),
        click.option(
            "--max-failures",
            metavar="N|P%",
            help="after this many devices did not end ok (failed, partial, unreachable, interrupted or "
            "rolled back count; skipped ones never), start no new device",
        ),
        parallel_option,
        click.option(
            "--on-error",
            type=click.Choice(["continue", "stop"]),
            default="continue",
            show_default=True,
            help="after a rejected value: send the rest, or skip it",
        ),
        click.option("--write-all", is_flag=True, help="write every parameter, even those already right"),
        click.option("--allow-broadcast", is_flag=True, help="allow unit 0 (broadcast; nothing can be verified)"),
        click.option(
            "--state-dir",
            default=".deployer",
            show_default=True,
            type=click.Path(file_okay=False),
            help="where snapshots and the audit log go",
        ),
        click.option(
            "--policy",
            type=click.Path(dir_okay=False),
            metavar="INVENTORY",
            help="the site's change-control policy: an inventory's change_control: (default: the "
            "DEPLOYER_POLICY environment variable; --inventory's own counts too)",
        ),
        click.option(
            "--lock-timeout",
            type=float_range(LIMITS.lock_timeout),
            default=0,
            show_default=True,
            metavar="S",
            help="wait up to S seconds for a device another run on this machine is writing",
        ),
        click.option(
            "--workers",
            type=int_range(LIMITS.workers),
            default=None,
            metavar="N",
            help="worker processes running a fleet's devices (0: all in this process; default: one per "
            "CPU for 100 devices or more on Linux, where they are forked, 1,000 elsewhere, unless "
            "--soak, --confirm-within, --rollback-on-failure or a question per device keeps them in "
            "this process)",
        ),
    ]
    for opt in reversed(opts):
        f = opt(f)
    return device_options(f)


def safe_options(f: Callable[..., Any]) -> Callable[..., Any]:
    from .base import Duration

    opts = [
        click.option(
            "--soak",
            type=Duration(LIMITS.soak),
            metavar="DURATION",
            help="after the verified write, read the profile's health checks for this long (30s, 5m, 1h; "
            "a bare number is seconds); a failed check rolls that device back from its snapshot "
            "(status rolled-back, exit 4); the commit is sent only after the soak passed",
        ),
        click.option(
            "--health-interval",
            type=Duration(LIMITS.health_interval),
            default="1s",
            show_default=True,
            metavar="DURATION",
            help="time between two rounds of health checks during --soak",
        ),
        click.option(
            "--confirm-within",
            type=Duration(LIMITS.confirm_within),
            metavar="DURATION",
            help="hold the profile's commit back until `deployer confirm` (another shell, same "
            "--state-dir); not confirmed in time: every device written is rolled back",
        ),
        click.option(
            "--allow-unhealthy",
            is_flag=True,
            help="with --soak or --confirm-within: write a device although one of its health checks fails "
            "already (else it is not written: failed, 'health check already failing before the "
            "change'); its window then does not hold that check against the change",
        ),
        click.option(
            "--rollback-on-failure",
            is_flag=True,
            help="when the rollout stops (a failed batch or canary, --max-failures), roll back every device it wrote",
        ),
        click.option("--pause", type=Duration(LIMITS.pause), metavar="DURATION", help="wait this long between batches"),
        click.option(
            "--ask",
            is_flag=True,
            help="ask before each batch after the first (needs a terminal; --yes does not answer it)",
        ),
    ]
    for opt in reversed(opts):
        f = opt(f)
    return f


@click.command()
@click.argument("source", metavar="[RECIPE|PLAN.json]", required=False, type=click.Path(dir_okay=False))
@apply_options
@safe_options
@agent_option
@click.option(
    "--force-endurance",
    is_flag=True,
    help="with --agent: write although a register is past the endurance its profile states",
)
def apply(source: str | None, **kw: Any) -> int:
    """Write a recipe (or a saved plan) to a device, read it back, report what it holds.

    With --inventory and no RECIPE, each device gets its recipe from the inventory. With --agent URL the
    site agent rolls out its files (RECIPE, if given, must be the one they name) and holds the windows."""
    url = kw.pop("agent_url")
    force_endurance = kw.pop("force_endurance")
    if url:
        from . import agentclient

        return agentclient.apply(url, source, kw, force_endurance=force_endurance)
    if force_endurance:
        raise UsageError("--force-endurance goes with --agent (the agent keeps the write ledger)")
    return run_apply(source, **kw)


@click.command()
@click.argument("snapshot", required=False, type=click.Path(dir_okay=False, exists=True))
@apply_options
@click.option(
    "--from-report",
    "from_reports",
    multiple=True,
    type=click.Path(dir_okay=False),
    metavar="RUN.json",
    help="every device that run may have written, each from its own snapshot (repeatable)",
)
@click.option(
    "--force",
    is_flag=True,
    help="restore the recorded raw registers, each where the snapshot read it, although the profile "
    "changed since the snapshot",
)
@click.option(
    "--to-other-device",
    is_flag=True,
    help="consent to restore a snapshot to another device or unit than the one it was taken from",
)
@click.option(
    "--accept-edited-snapshot",
    is_flag=True,
    help="consent to restore a snapshot whose SHA-256 differs from the one its report or journal recorded",
)
@click.option(
    "--even-if-changed",
    is_flag=True,
    help="with --from-report: restore devices that no longer hold what the run wrote (else each such "
    "device is refused by name, the others restored, and the exit code is 4)",
)
@click.option(
    "--all-or-nothing",
    is_flag=True,
    help="with --from-report: one changed device refuses them all, nothing sent (the old behaviour)",
)
@click.option(
    "--save-report",
    type=click.Path(dir_okay=False),
    metavar="FILE",
    hidden=True,
    help="the old form rollback --report RUN.json: write this rollback's own report here",
)
@agent_option
def rollback(snapshot: str | None, **kw: Any) -> int:
    """Restore a snapshot that apply saved, to the device it was taken from.

    \b
    rollback SNAPSHOT               that device, from that snapshot
    rollback --from-report RUN.json every device an earlier run may have written, each from its own
                                    snapshot (the run's journal names those its report could not);
                                    repeat it for a rollout and its retries (the earliest snapshot wins)
    --report FILE writes this rollback's own report, as on apply.
    """
    save = kw.pop("save_report")
    from_reports: tuple[str, ...] = kw.pop("from_reports")
    url = kw.pop("agent_url")
    if url:  # rollback --agent URL --from-report RUN: the agent restores what its run wrote
        from . import agentclient

        return agentclient.rollback(url, from_reports, kw)
    if snapshot is None and not from_reports and kw["report_path"] and os.path.isfile(kw["report_path"]):
        # the old reading form: rollback --report RUN.json [--save-report FILE]
        echo(
            f"warning: rollback --report {safe(kw['report_path'])} reads an earlier run's report: say "
            f"--from-report {safe(kw['report_path'])} (--report FILE writes this rollback's report, as on apply)",
            err=True,
        )
        from_reports, kw["report_path"] = (kw["report_path"],), save
    elif save:
        raise UsageError("--save-report belongs to the old form rollback --report RUN.json; use --report FILE")
    if snapshot is None and not from_reports:
        raise UsageError("rollback needs a SNAPSHOT, or --from-report RUN.json to roll back every device of a run")
    if snapshot is not None and from_reports:
        raise UsageError("rollback takes a SNAPSHOT or --from-report RUN.json, not both")
    return run_apply(snapshot, from_reports=from_reports, command="rollback", **kw)


@click.command()
@click.option(
    "--state-dir",
    default=".deployer",
    show_default=True,
    type=click.Path(file_okay=False),
    help="where snapshots and the audit log are",
)
@click.option("--json", "as_json", is_flag=True, help="print the runs that need a look as JSON")
@click.option("--resolve", metavar="RUN", help="acknowledge a run listed here after a look (recorded in the audit log)")
@agent_option
def status(state_dir: str, as_json: bool, resolve: str | None, agent_url: str | None) -> int:
    """Runs that need a look: never finished (a crash, kill -9, a laptop asleep), interrupted while writing,
    or waiting for a confirmation.

    A run drops out once the devices it left half-written are rolled back, or with --resolve RUN.
    Exit code 2 while any run needs a look, 0 when none does.
    """
    if agent_url:
        from . import agentclient

        return agentclient.status(agent_url, as_json=as_json)
    from ..api.commands import resolve_run, run_status

    if resolve is not None:
        r = resolve_run(resolve, state_dir=state_dir)
        echo(
            f"resolved run {safe(r.run)} ({_what_ran(r)} by {safe(r.user)} at {safe(r.time)}); "
            f"recorded in {safe(run_status(state_dir).journal)}"
        )
        return EXIT_OK
    st = run_status(state_dir)
    runs, torn, waits, soaks, folder, locks = st.runs, st.unreadable, st.awaiting, st.soaking, st.lock_folder, st.locks
    if as_json:
        echo(
            json.dumps(
                {
                    "locks": locks,
                    "owned": st.owned,
                    "unfinished": [
                        {
                            "run": r.run,
                            "time": r.time,
                            "user": r.user,
                            "pid": r.pid,
                            "running": r.running,
                            "command": r.command,
                            "via": r.via,
                            "argv": r.argv,
                            "recipe": r.recipe,
                            "devices": r.devices,
                            "interrupted": r.interrupted,
                            "finished": r.finished,
                            "ended": r.ended,
                            **(
                                {
                                    "awaiting_confirmation": {
                                        "deadline": waits[r.run].until(),
                                        "report": waits[r.run].report,
                                        "waiting": waits[r.run].alive,
                                    }
                                }
                                if r.run in waits
                                else {}
                            ),
                            **({"soaking": {"report": soaks[r.run]}} if r.run in soaks else {}),
                        }
                        for r in runs
                    ],
                },
                indent=2,
            )
        )
        return EXIT_CHANGES if runs else EXIT_OK
    if not runs:
        echo(f"no unfinished runs in {safe(st.journal)}")
    if locks:
        echo(f"devices held on this machine now ({safe(folder)}):")
        for line in st.held:
            echo(f"  {safe(line)}")
    if st.owned:  # whatever lock folder each agent was given
        echo(f"devices site agents of this machine own ({safe(st.owner_folder)}):")
        for line in st.owners:
            echo(f"  {safe(line)}")
    for r in runs:
        state = "still running" if r.running else (f"interrupted ({safe(r.ended)})" if r.ended else "did not finish")
        echo(
            f"{_what_ran(r)} by {safe(r.user)} at {safe(r.time)} (run {safe(r.run)}, PID {safe(r.pid)}): "
            f"{state}; {_n(len(r.devices), 'device')} selected, {len(r.finished)} finished"
        )
        dirs = "" if state_dir == ".deployer" else f" --state-dir {safe(state_dir)}"
        a = waits.get(r.run)
        if a is not None and a.alive:
            echo(
                f"  awaits confirmation until {a.until()} ({max(0.0, a.left()):.0f} s left): "
                f"deployer confirm {safe(r.run)} --state-dir {safe(state_dir)}"
            )
        elif a is not None:
            echo(
                f"  awaited confirmation (until {safe(a.deadline)}) when its process died: its devices hold values "
                "that were never committed (a power cycle also reverts them on devices whose commit stores "
                "to non-volatile memory)"
            )
            echo(
                f"    restore them with: deployer rollback --from-report {safe(a.report)} --state-dir "
                f"{safe(state_dir)} --yes"
            )
        if r.run in soaks and not r.running:
            echo(
                "  died while its change soaked: its devices hold values whose health was not proven and "
                "that were never committed (a power cycle also reverts them on devices whose commit stores "
                "to non-volatile memory)"
            )
            if soaks[r.run]:
                echo(
                    f"    restore them with: deployer rollback --from-report {safe(soaks[r.run])} "
                    f"--state-dir {safe(state_dir)} --yes"
                )
        for d in r.interrupted:
            where = f"{safe(d.get('url'))} unit {safe(d.get('unit'))}"
            echo(f"  interrupted while writing: {safe(d.get('name'))} {where}; snapshot {safe(d.get('snapshot'))}")
            if r.command == "rollback" and d.get("restoring"):  # its snapshot holds the values being undone
                echo(
                    f"    the rollback did not finish: re-run it with: deployer rollback {safe(d['restoring'])}"
                    + ("" if d.get("restoring") == r.recipe else f" --device {safe(d.get('url'))}")
                    + dirs
                )
            else:
                check = _diff_command(r, d)
                undo = f"undo with: deployer rollback {safe(d.get('snapshot'))}{dirs}"
                echo(f"    check with: {check}; {undo}" if check else f"    {undo}")
        done = {(d.get("name"), d.get("url"), d.get("unit")) for d in (*r.finished, *r.interrupted)}
        never = [d for d in r.devices if (d.get("name"), d.get("url"), d.get("unit")) not in done]
        if never and not r.running and not r.ended:
            echo(f"  not written (never started or nothing to write): {', '.join(safe(d.get('name')) for d in never)}")
        if not r.running:
            echo(f"  after a look: deployer status --resolve {safe(r.run)}{dirs}")
    if torn:
        echo(f"({_n(torn, 'line')} of the log could not be read: cut off by the crash)")
    return EXIT_CHANGES if runs else EXIT_OK  # 2: something needs a look (scripts and monitoring can tell)


def _inventory_of(r: Any) -> str | None:
    argv = [str(a) for a in r.argv]
    return argv[argv.index("--inventory") + 1] if "--inventory" in argv[:-1] else None


def _what_ran(r: Any) -> str:
    """``apply line.yaml``, ``apply --inventory site.yaml`` (each device's recipe from its groups), or the
    command alone, with who started it when that was not the command line."""
    via = {"api": " (through the Python API)", "ansible": " (through Ansible)"}.get(r.via, "")
    inventory = _inventory_of(r)
    what = " ".join(safe(w) for w in (r.recipe, None if inventory is None else f"--inventory {inventory}") if w)
    return f"{safe(r.command)}{via}" + (f" {what}" if what else "")


def _diff_command(r: Any, d: dict[str, Any]) -> str | None:
    """The diff that shows what a device holds against what the run applied: its recipe, and for a
    fleet its inventory (per-device profiles and values), as the run's command line named them; else
    against the snapshot taken before the write (what changed since). None: nothing to compare with."""
    recipe = r.recipe if r.recipe and os.path.isfile(r.recipe) and not r.recipe.endswith(".json") else None
    inventory = _inventory_of(r)
    name, url, unit = safe(d.get("name")), safe(d.get("url")), safe(d.get("unit"))
    if inventory:  # without a recipe, each device's own from the inventory
        return f"deployer diff {safe(recipe) + ' ' if recipe else ''}--inventory {safe(inventory)} --limit {name}"
    if recipe:
        return f"deployer diff {safe(recipe)} --device {url} --unit {unit}"
    if d.get("snapshot"):
        return f"deployer diff {safe(d.get('snapshot'))} --device {url} --unit {unit} (what changed since the snapshot)"
    return None


@click.command()
@click.argument("run", required=False)
@click.option(
    "--state-dir",
    default=".deployer",
    show_default=True,
    type=click.Path(file_okay=False),
    help="the state directory of the run that waits (apply --confirm-within)",
)
@agent_option
def confirm(run: str | None, state_dir: str, agent_url: str | None) -> int:
    """Confirm a run that waits (apply --confirm-within): its held-back commit is sent.

    The run reads its parameters again first: one changed during the window is not committed (the rest is
    rolled back). This waits for the outcome: exit 0 once the commit went out, 4 when it did not (each
    device named, and why). RUN is needed only when several runs wait (deployer status lists them).
    """
    if agent_url:
        from . import agentclient

        return agentclient.confirm(agent_url, run)
    from ..api.commands import confirm_outcome

    confirmed: list[str] = []

    def said(run_id: str) -> None:
        confirmed.append(run_id)
        echo(f"confirmed run {safe(run_id)}: it reads its parameters again and sends the commit", err=True)

    # NotCommitted (exit 4) names each device the commit did not reach
    done = confirm_outcome(run, state_dir=state_dir, on_confirmed=said)
    from ..audit.commands import after_confirm

    for what in after_confirm(confirmed[0] if confirmed else str(run), done, state_dir=state_dir):
        echo(f"not recorded: {safe(what)}", err=True)
    sent, kept = done.get("committed") or [], done.get("kept") or []
    said_ = []
    if sent:
        said_.append(f"the commit was sent to {', '.join(safe(n) for n in sent)}")
    if kept:
        said_.append(
            f"kept as written on {', '.join(safe(n) for n in kept)} (its profile has no commit step: nothing to store)"
        )
    echo(f"run {safe(confirmed[0])}: " + ("; ".join(said_) or "confirmed"))
    return EXIT_OK
