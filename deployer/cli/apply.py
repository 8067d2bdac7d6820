"""apply, rollback and status: the commands that write, and what they report."""

from __future__ import annotations

import asyncio
import json
import os
import shlex
import sys
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import click

from ..errors import StateError
from ..load.diagnostics import EXIT_OK, Diagnostic, InputError, UsageError
from .base import (
    _ARGV,
    _OWN_PROCESS,
    _fleet,
    _n,
    _target,
    console,
    describe,
    device_options,
    fleet_option,
    limit_option,
    parallel_option,
)
from .plan import print_plan
from .tables import show

if TYPE_CHECKING:
    from rich.console import Console

    from ..fleet.rollout import Job
    from ..planning.model import Plan
    from ..report import DeviceResult, Report


_STATUS_ORDER = {"failed": 0, "mismatch": 1, "unverified": 2, "rolled-back": 3, "skipped": 4, "ok": 5, "unchanged": 6}
_STATUS_STYLE = {"ok": "green", "unchanged": "dim", "failed": "bold red", "mismatch": "bold red",
                 "unverified": "yellow", "skipped": "yellow", "partial": "yellow", "unreachable": "bold red",
                 "sent": "cyan", "rolled-back": "bold yellow"}


def print_report(report: Report, out: Console, *, only_not_ok: bool = False) -> None:
    """Per device, every parameter; ``only_not_ok`` (fleets): only the devices that need a look, by parameter."""
    for d in report.devices:
        if only_not_ok and d.status in ("ok", "skipped"):
            continue
        style = _STATUS_STYLE.get(d.status, "")
        out.print(f"[bold]{d.name}[/bold] {d.url} unit {d.unit} ({d.profile}): [{style}]{d.status}[/{style}]"
                  + (f" - {d.error}" if d.error else ""))
        rows = sorted(d.parameters, key=lambda p: (_STATUS_ORDER.get(p.status, 9), p.address))
        if only_not_ok:
            rows = [p for p in rows if p.status not in ("ok", "unchanged")]
        if d.status != "unreachable" and rows:
            show(out, ["parameter", "before", "desired", "after", "status", ""],
                 [[p.name, p.before or "-", p.desired, p.after or "-", (p.status, _STATUS_STYLE.get(p.status, "")),
                   p.error or ""] for p in rows])
        if d.status == "sent":
            out.print("broadcast sent: every request went out; no device answers a broadcast, so nothing was "
                      "read back or verified")
        if d.identity:
            out.print("identity: " + ", ".join(f"{k} {v!r}" for k, v in d.identity.items()))
        for note in d.notices:
            out.print(f"note: {note}")
        if d.status == "rolled-back" and d.commit == "not sent":
            out.print("commit: not sent (the profile's commit steps)")
        elif d.commit in ("held", "not sent"):
            out.print(f"commit: {d.commit} (the profile's commit steps): the values written are not stored to "
                      "non-volatile memory; on devices that keep Modbus writes in RAM they revert at a power cycle")
        if d.snapshot and d.status != "rolled-back":
            out.print(f"snapshot: {d.snapshot}  (undo with: deployer rollback {d.snapshot})")
        out.print(f"{d.write_requests} write and {d.read_requests} read requests")
    s = report.summary()
    if len(report.devices) > 1 and not only_not_ok:
        out.print(f"{_n(s['devices'], 'device')}: {s['ok']} ok, " + (f"{s['sent']} sent, " if s["sent"] else "")
                  + f"{s['partial']} partial, {s['failed']} failed, {s['unreachable']} unreachable"
                  + (f", {s['rolled-back']} rolled back" if s["rolled-back"] else "")
                  + f" in {s['seconds']:.2f} s")


def _is_plan_file(path: str) -> bool:
    if path.endswith(".json"):
        return True
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    return head.lstrip().startswith(b"{") and b"deployer.plan/" in head


def run_apply(source: str | None, *, device: str | None, unit: int | None, timeout: float | None,
              retries: int | None, yes: bool, report_path: str | None, as_json: bool, inventory: str | None,
              limit: str | None, parallel: int, on_error: str, write_all: bool, allow_broadcast: bool, state_dir: str,
              lock_timeout: float = 0.0, force: bool = False, from_report: str | None = None,
              batch: str | None = None, max_failures: str | None = None, command: str = "apply",
              soak: float | None = None, health_interval: float = 1.0, confirm_within: float | None = None,
              rollback_on_failure: bool = False, pause: float | None = None, ask: bool = False,
              html_path: str | None = None) -> int:
    """apply / rollback: everything validated, then confirmed, then sent."""
    from ..api import fleet_options, run_fleet_async
    from ..execute.session import ApplyOptions
    from ..fleet.rollout import Job, apply_many
    from ..planning.planfile import load_plan
    from ..recipe.loader import load_recipe
    from ..report import write_json
    from ..state import journal

    expected: Plan | None = None
    jobs: list[Job] = []
    moved: list[str] = []  # rollback to another device than the snapshot's: asked about first
    if not (inventory or from_report) and (batch or max_failures or limit):
        raise UsageError("--limit, --batch and --max-failures need --inventory")
    if from_report is not None:  # rollback --report: every device of that run from its own snapshot
        if inventory or device or unit is not None:
            raise UsageError("rollback --report restores each device from its own snapshot, to the device it was "
                             "taken from: --inventory, --device and --unit do not apply")
        jobs = _rollback_report_jobs(from_report, force=force, timeout=timeout, retries=retries)
        if limit:  # names and patterns select among that run's devices (it has no groups)
            from ..fleet.inventory import FleetDevice, Inventory, select

            chosen = {d.name for d in select(Inventory(from_report, tuple(FleetDevice(j.name, describe(j.url))
                                                                          for j in jobs)), limit)}
            jobs = [j for j in jobs if j.name in chosen]
        label: str | None = from_report
    elif source is None:  # each device's recipe from the inventory
        if not inventory:
            raise UsageError(f"pass {'SNAPSHOT' if command == 'rollback' else 'RECIPE'}, or --inventory FILE "
                             "whose devices name their recipes")
        if device:
            raise UsageError("--device and --inventory exclude each other")
        label = None
        jobs = _fleet(None, inventory, limit, timeout, retries, unit)
    else:
        label = source
        if _is_plan_file(source):
            if inventory or write_all:
                raise UsageError("a saved plan runs unchanged: --inventory and --write-all do not apply to it")
            rec, expected = load_plan(source)
        else:
            rec = load_recipe(source, force=force)
        if rec.snapshot is not None and inventory:
            raise UsageError(f"{source} is one device's snapshot: it restores only the device it was taken from. "
                             "To roll back a fleet run, use: deployer rollback --report REPORT.json")
        if inventory:
            if device:
                raise UsageError("--device and --inventory exclude each other")
            jobs = _fleet(rec, inventory, limit, timeout, retries, unit)
        else:
            one, u = _target(rec, device, unit, timeout, retries, required=True)
            assert one is not None
            jobs.append(Job(rec.name, rec, one, u))
            if rec.snapshot is not None and rec.device is not None and rec.device.url is not None:
                taken, taken_unit = _target(rec, None, None, timeout, retries, required=True)
                assert taken is not None
                if (taken.bus, taken_unit) != (one.bus, u):
                    moved.append(f"{source} was taken from {describe(taken)} unit {taken_unit}, not "
                                 f"{describe(one)} unit {u}")
    if soak is not None:
        from ..execute.soak import check_soak_profiles

        check_soak_profiles([j.recipe.profile for j in jobs])
    if (pause is not None or ask) and not batch:
        raise UsageError("--pause and --ask go between batches: give --batch too")
    if ask and not sys.stdin.isatty():
        raise UsageError("--ask asks before each batch: stdin is not a terminal (use --pause for an unattended run)")
    for j in jobs:
        if j.unit == 0 and not allow_broadcast:
            raise UsageError(f"{j.name}: unit 0 is broadcast (no device answers, nothing can be verified); "
                             "pass --allow-broadcast to send it anyway")

    out = console()
    err = console(stderr=True)
    confirm = None
    if not yes:
        if not sys.stdin.isatty():
            raise UsageError("refusing to write without confirmation: stdin is not a terminal; pass --yes")
        for why in moved:
            if not click.confirm(f"{why}. Restore it to that other device?", default=False, err=True):
                raise UsageError("nothing was written (declined)")
        ask_lock = asyncio.Lock()
        profiles = {j.name: j.recipe.profile for j in jobs}

        async def confirm(p: Plan, res: DeviceResult) -> bool:
            async with ask_lock:  # one question at a time, even for fleets
                err.print(f"[bold]{res.name}[/bold] {res.url} unit {res.unit}:")
                print_plan(p, profiles[res.name], changes_only=True, out=err)
                return await asyncio.to_thread(click.confirm, "Write these values?", default=False, err=True)
    elif moved:
        for why in moved:
            err.print(f"warning: {why}; restoring it there (--yes)")

    fleet_run = bool(inventory or from_report)
    if report_path or html_path:  # before anything is sent: a link, a FIFO or a folder there is refused now
        from ..state.durable import check_output

        if report_path:
            check_output(report_path, what="the report")
        if html_path:
            check_output(html_path, what="the page")
    if fleet_run:
        fleet_options(len(jobs), parallel=parallel, batch=batch, max_failures=max_failures, report_path=report_path)
    run_id = journal.new_run_id()
    journal.run_started(state_dir, run_id, command=command, argv=_ARGV, recipe=label,
                        devices=[(j.name, describe(j.url), j.unit) for j in jobs])
    options = ApplyOptions(on_error=on_error, write_all=write_all,  # type: ignore[arg-type]
                           allow_broadcast=allow_broadcast, state_dir=state_dir, expected=expected, confirm=confirm,
                           run_id=run_id, applied=os.path.abspath(label) if label else None, lock_timeout=lock_timeout,
                           soak=soak, health_interval=health_interval, confirm_within=confirm_within,
                           command=shlex.join(["deployer", *_ARGV]) if _ARGV else f"deployer {command}")
    safe = _safe_hooks(err, state_dir, pause=pause, ask=ask, rollback_on_failure=rollback_on_failure, soak=soak,
                       interval=health_interval, staged=bool(batch), fleet=fleet_run)
    if fleet_run:
        import gc

        from .progress import FleetProgress  # rich's live display: only fleets pay for importing it

        if _OWN_PROCESS:  # the command's own process only: the library and callers keep their collector
            # what is loaded now (modules, profiles, recipes) lives as long as the command: later collections
            # need not walk it, and a fleet allocates fast, so collect less often (the cyclic collector
            # took 35-50 ms of a 0.7 s run of 200 devices, a 20 ms pause among them)
            gc.freeze()
            gc.set_threshold(20_000, 20, 10)
        # a live display on a terminal (not while asking questions), else a line per device
        progress = FleetProgress(len(jobs), err, live=err.is_terminal and yes and not ask and confirm_within is None,
                                 staged=bool(batch))
        with progress:
            report = asyncio.run(run_fleet_async(
                jobs, recipe_name=label, parallel=parallel, batch=batch, max_failures=max_failures, options=options,
                report_path=report_path, on_start=lambda j: progress.start(j.name), on_done=progress.device_done,
                **safe))
    else:
        started = time.time()
        report = asyncio.run(apply_many(jobs, parallel=parallel, options=options, recipe_name=label, **safe))
        from ..report import run_info

        report.run = run_info(options.command, started)
        if report_path:
            write_json(report.to_json(), report_path, what="the report")
    try:
        journal.run_finished(state_dir, run_id, report, command=command, argv=_ARGV)
    except StateError as e:  # the devices' outcome stands; only the journal misses its last line
        err.print(f"warning: {e}")
    if html_path:
        from ..pages import run_page
        from .base import write_page

        write_page(run_page(report), html_path)
        err.print(f"page: {html_path}")
    if as_json:
        if fleet_run:
            from ..report import report_text

            click.echo(report_text(report), nl=False)
        else:
            click.echo(json.dumps(report.to_json(), indent=2))
    elif fleet_run:
        from .progress import fleet_summary

        print_report(report, out, only_not_ok=True)
        fleet_summary(report, out)
    else:
        print_report(report, out)
    return report.exit_code


def _safe_hooks(err: Console, state_dir: str, *, pause: float | None, ask: bool, rollback_on_failure: bool,
                soak: float | None = None, interval: float = 1.0, staged: bool = False, fleet: bool = False
                ) -> dict[str, Any]:
    """apply_many's keywords for a safe change: a pause and a question between batches, the confirmation wait."""
    from ..load.durations import format_duration

    async def between(number: int, so_far: Report) -> str | None:
        s = so_far.summary()
        done = ", ".join(f"{s[k]} {k}" for k in ("ok", "partial", "failed", "unreachable", "rolled-back") if s[k])
        if pause:
            err.print(f"batch {number - 1} done ({done}); batch {number} starts in {format_duration(pause)}")
            await asyncio.sleep(pause)
        if ask and not await asyncio.to_thread(click.confirm, f"batch {number - 1} done ({done}). "
                                                              f"Continue with batch {number}?", default=False,
                                               err=True):
            return f"not started: stopped at the question before batch {number} (--ask)"
        return None

    def waiting(run: str, deadline: float) -> None:
        import time

        left = max(0.0, deadline - time.time())
        left = round(left) if left >= 1 else round(left, 3)
        err.print(f"[bold]waiting for confirmation[/bold] until {time.strftime('%H:%M:%S UTC', time.gmtime(deadline))} "
                  f"({format_duration(left)} left): confirm from another shell with\n"
                  f"    deployer confirm {run} --state-dir {state_dir}\n"
                  "without it every device written is rolled back and the commit is never sent")

    def soaking(number: int, names: list[str]) -> None:
        which = names[0] if len(names) == 1 else _n(len(names), "device")
        err.print(f"{f'batch {number}: ' if number > 1 or staged else ''}watching the health of {which} for "
                  f"{format_duration(soak or 0)} (every {format_duration(interval)}); a failed check rolls that device "
                  "back", soft_wrap=True)

    told: set[str] = set()

    def changed(r: DeviceResult) -> None:  # fleets: a progress line for a device its soak rolled back
        if r.status != "ok" and r.name not in told:
            from rich.markup import escape

            told.add(r.name)
            err.print(f"{escape(r.name)}: [bold yellow]{r.status}[/bold yellow]"
                      + (f" - {escape(r.error)}" if r.error else ""), soft_wrap=True, highlight=False)

    return {"rollback_on_failure": rollback_on_failure, "between_batches": between, "on_confirm_wait": waiting,
            "on_soak": soaking, **({"on_changed": changed} if fleet else {})}


def _rollback_report_jobs(path: str, *, force: bool, timeout: float | None, retries: int | None) -> list[Job]:
    """One job per device of an earlier run that has a snapshot: its own snapshot, to its own device."""
    from ..fleet.rollout import Job
    from ..recipe.loader import load_recipe
    from ..state.snapshot import snapshots_of_report

    restored: list[str] = []
    found, without = snapshots_of_report(path, restored)
    if without:
        click.echo(f"nothing to roll back on {', '.join(without)}: nothing was written there", err=True)
    if restored:
        click.echo(f"nothing to roll back on {', '.join(restored)}: that run already rolled it back", err=True)
    if not found and restored and not without:
        raise UsageError(f"{path}: every device of that run was already rolled back: nothing to roll back")
    if not found:
        raise UsageError(f"{path}: no device of that run has a snapshot (nothing was written): nothing to roll back")
    jobs: list[Job] = []
    errors: list[Diagnostic] = []
    for rs in found:
        try:
            rec = load_recipe(rs.snapshot, force=force)
        except InputError as e:
            errors.extend(e.diagnostics)
            continue
        if rec.snapshot is None or rec.device is None or rec.device.url is None:
            errors.append(Diagnostic(rs.snapshot, 1, 1, f"{rs.name}: not a snapshot with its device (made by an "
                                                        "older deployer?): roll it back with rollback SNAPSHOT "
                                                        "--device URL"))
            continue
        url, u = _target(rec, None, None, timeout, retries, required=True)
        assert url is not None
        jobs.append(Job(rs.name, rec, url, u))
    if errors:
        raise InputError(errors)
    # one device in the run twice (older deployers allowed it): its snapshots are restored last written
    # first, so the earliest one, what it held before the run, is the one that stays
    slots: dict[tuple[tuple[str, ...], int], list[int]] = {}
    for i, j in enumerate(jobs):
        slots.setdefault((j.url.lock_keys, j.unit), []).append(i)
    order = list(range(len(jobs)))
    for same in slots.values():
        for i, k in zip(same, reversed(same), strict=True):
            order[i] = k
    return [jobs[k] for k in order]


def apply_options(f: Callable[..., Any]) -> Callable[..., Any]:
    opts = [
        click.option("--yes", "-y", is_flag=True, help="do not ask for confirmation"),
        click.option("--report", "report_path", type=click.Path(dir_okay=False), help="write the report JSON here"),
        click.option("--json", "as_json", is_flag=True, help="print the report JSON"),
        click.option("--html", "html_path", type=click.Path(dir_okay=False), metavar="FILE",
                     help="also write the report as one self-contained HTML page (sortable, filterable; it "
                          "prints as the commissioning record: as found / as left per device)"),
        fleet_option,
        limit_option,
        click.option("--batch", metavar="1,10%,100%",
                     help="staged rollout: batch sizes (count or % of the selected devices; the last repeats); "
                          "each batch finishes before the next, a batch with no ok device ends the rollout"),
        click.option("--max-failures", metavar="N|P%",
                     help="after this many devices did not end ok (failed, partial, unreachable or rolled back "
                          "count; skipped ones never), start no new device"),
        parallel_option,
        click.option("--on-error", type=click.Choice(["continue", "stop"]), default="continue", show_default=True,
                     help="after a rejected value: send the rest, or skip it"),
        click.option("--write-all", is_flag=True, help="write every parameter, even those already right"),
        click.option("--allow-broadcast", is_flag=True, help="allow unit 0 (broadcast; nothing can be verified)"),
        click.option("--state-dir", default=".deployer", show_default=True, type=click.Path(file_okay=False),
                     help="where snapshots and the audit log go"),
        click.option("--lock-timeout", type=click.FloatRange(min=0), default=0, show_default=True, metavar="S",
                     help="wait up to S seconds for a device another run on this machine is writing"),
    ]
    for opt in reversed(opts):
        f = opt(f)
    return device_options(f)


def safe_options(f: Callable[..., Any]) -> Callable[..., Any]:
    from .base import DURATION

    opts = [
        click.option("--soak", type=DURATION, metavar="DURATION",
                     help="after the verified write, read the profile's health checks for this long (30s, 5m, 1h; "
                          "a bare number is seconds); a failed check rolls that device back from its snapshot "
                          "(status rolled-back, exit 4); the commit is sent only after the soak passed"),
        click.option("--health-interval", type=DURATION, default="1s", show_default=True, metavar="DURATION",
                     help="time between two rounds of health checks during --soak"),
        click.option("--confirm-within", type=DURATION, metavar="DURATION",
                     help="hold the profile's commit back until `deployer confirm` (another shell, same "
                          "--state-dir); not confirmed in time: every device written is rolled back"),
        click.option("--rollback-on-failure", is_flag=True,
                     help="when the rollout stops (a failed batch or canary, --max-failures), roll back every "
                          "device it wrote"),
        click.option("--pause", type=DURATION, metavar="DURATION", help="wait this long between batches"),
        click.option("--ask", is_flag=True,
                     help="ask before each batch after the first (needs a terminal; --yes does not answer it)"),
    ]
    for opt in reversed(opts):
        f = opt(f)
    return f


@click.command()
@click.argument("source", metavar="[RECIPE|PLAN.json]", required=False, type=click.Path(dir_okay=False))
@apply_options
@safe_options
def apply(source: str | None, **kw: Any) -> int:
    """Write a recipe (or a saved plan) to a device, read it back, report what it holds.

    With --inventory and no RECIPE, each device gets its recipe from the inventory."""
    return run_apply(source, **kw)


@click.command()
@click.argument("snapshot", required=False, type=click.Path(dir_okay=False, exists=True))
@apply_options
@click.option("--force", is_flag=True,
              help="restore the recorded raw registers although the profile changed since the snapshot")
@click.option("--save-report", type=click.Path(dir_okay=False), metavar="FILE",
              help="with --report RUN.json: write this rollback's own report here")
def rollback(snapshot: str | None, **kw: Any) -> int:
    """Restore a snapshot that apply saved, to the device it was taken from.

    \b
    rollback SNAPSHOT            that device, from that snapshot (--report FILE writes this run's report)
    rollback --report RUN.json   every device of an earlier run, each from its own snapshot
                                 (--save-report FILE writes this run's report)
    """
    save = kw.pop("save_report")
    if snapshot is None:
        if not kw["report_path"]:
            raise UsageError("rollback needs a SNAPSHOT, or --report REPORT.json to roll back every device of a run")
        from_report, kw["report_path"] = kw["report_path"], save
        return run_apply(None, from_report=from_report, command="rollback", **kw)
    if save:
        raise UsageError("--save-report goes with rollback --report RUN.json; with a SNAPSHOT use --report FILE")
    return run_apply(snapshot, command="rollback", **kw)


@click.command()
@click.option("--state-dir", default=".deployer", show_default=True, type=click.Path(file_okay=False),
              help="where snapshots and the audit log are")
@click.option("--json", "as_json", is_flag=True, help="print the unfinished runs as JSON")
def status(state_dir: str, as_json: bool) -> int:
    """Runs that never finished (a crash, kill -9, a laptop asleep): which devices were being written."""
    from ..execute.soak import awaiting, soaking
    from ..state.journal import unfinished

    runs, torn = unfinished(state_dir)
    waits = {a.run: a for a in awaiting(state_dir)}
    soaks = soaking(state_dir)
    if as_json:
        click.echo(json.dumps({"unfinished": [
            {"run": r.run, "time": r.time, "user": r.user, "pid": r.pid, "running": r.running, "command": r.command,
             "argv": r.argv, "recipe": r.recipe, "devices": r.devices, "interrupted": r.interrupted,
             "finished": r.finished,
             **({"awaiting_confirmation": {"deadline": waits[r.run].deadline, "report": waits[r.run].report,
                                           "waiting": waits[r.run].alive}} if r.run in waits else {}),
             **({"soaking": {"report": soaks[r.run]}} if r.run in soaks else {}),
             } for r in runs]}, indent=2))
        return EXIT_OK
    out = console()
    if not runs:
        out.print(f"no unfinished runs in {os.path.join(state_dir, 'audit.jsonl')}")
    for r in runs:
        state = "still running" if r.running else "did not finish"
        out.print(f"[bold]{r.command}[/bold] {r.recipe or ''} by {r.user} at {r.time} (run {r.run}, PID {r.pid}): "
                  f"{state}; {_n(len(r.devices), 'device')} selected, {len(r.finished)} finished")
        a = waits.get(r.run)
        if a is not None and a.alive:
            out.print(f"  awaits confirmation until {a.deadline}: deployer confirm {r.run} --state-dir {state_dir}",
                      soft_wrap=True)
        elif a is not None:
            out.print(f"  awaited confirmation (until {a.deadline}) when its process died: its devices hold values "
                      "that were never committed (a power cycle also reverts them on devices whose commit stores "
                      "to non-volatile memory)")
            out.print(f"    restore them with: deployer rollback --report {a.report} --state-dir {state_dir} --yes",
                      soft_wrap=True)
        if r.run in soaks and not r.running:
            out.print("  died while its change soaked: its devices hold values whose health was not proven and "
                      "that were never committed (a power cycle also reverts them on devices whose commit stores "
                      "to non-volatile memory)")
            if soaks[r.run]:
                out.print(f"    restore them with: deployer rollback --report {soaks[r.run]} --state-dir {state_dir} "
                          "--yes", soft_wrap=True)
        for d in r.interrupted:
            out.print(f"  interrupted while writing: {d.get('name')} {d.get('url')} unit {d.get('unit')}; "
                      f"snapshot {d.get('snapshot')}")
            out.print(f"    check with: deployer diff RECIPE --device {d.get('url')} --unit {d.get('unit')}; "
                      f"undo with: deployer rollback {d.get('snapshot')}")
        done = {(d.get("name"), d.get("url"), d.get("unit")) for d in (*r.finished, *r.interrupted)}
        never = [d for d in r.devices if (d.get("name"), d.get("url"), d.get("unit")) not in done]
        if never and not r.running:
            out.print(f"  not written (never started or nothing to write): "
                      f"{', '.join(str(d.get('name')) for d in never)}")
    if torn:
        out.print(f"({_n(torn, 'line')} of the log could not be read: cut off by the crash)")
    return EXIT_OK


@click.command()
@click.argument("run", required=False)
@click.option("--state-dir", default=".deployer", show_default=True, type=click.Path(file_okay=False),
              help="the state directory of the run that waits (apply --confirm-within)")
def confirm(run: str | None, state_dir: str) -> int:
    """Confirm a run that waits (apply --confirm-within): its held-back commit is sent.

    RUN is needed only when several runs wait (deployer status lists them).
    """
    from ..execute.soak import confirm_run

    target = confirm_run(state_dir, run)
    click.echo(f"confirmed run {target.run}: it sends the commit now (deployer status shows the outcome)")
    return EXIT_OK
