"""A run: apply (or roll back) jobs on one device or a fleet, journaled, with its report, whoever calls.

The command line, the Python API and the Ansible modules all run through ``run_async``, so every
run is in the audit log and visible to ``deployer status``:

1. checks before anything is sent: a broadcast (unit 0) needs ``allow_broadcast``, fleet options
   (batch sizes, the failure budget, open files), a report file that can be written; then the worker
   processes of a big fleet are launched (``fleet.workers``), before any thread of this run exists;
2. the journal's ``run-started`` line, then the report file's first state (a stream: every device
   ``skipped``, "not finished", with the run id and the state folder: ``rollback --from-report`` finds the
   journal by them);
3. the devices (``fleet.rollout.apply_many``); a device's line says ``interrupted`` with its
   snapshot from its first write until its result is appended;
4. the final report file (assembled from the stream) and the journal's ``run-finished`` line.

Interrupted (Ctrl-C or SIGTERM when ``signals`` is set, or the task cancelled), the devices in flight
end ``interrupted`` (with their snapshot when something may have been written), the others
``skipped``; the run-finished line and the report file are still written, and ``RunInterrupted``
carries the report. A run refused before anything was sent (a stale saved plan, a "no" at the
prompt) gets a run-finished line saying so.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

from ..errors import Declined, RunInterrupted, StalePlan, UsageError
from ..execute.job import Job
from ..execute.session import ApplyOptions
from ..fleet.livereport import LiveReport
from ..fleet.rollout import apply_many, batch_plan, batch_sizes, failure_budget
from ..fleet.workers import NotStarted, Pool, auto_count, ineligible
from ..portable import interrupt_signals, on_signals, raise_open_files
from ..report import DeviceResult, Report, run_info
from ..state import journal, snapshot
from ..state.durable import Line, disk_error, durable, settled
from ..transport.urls import describe
from ..window.soak import check_soak_profiles

__all__ = ["check_broadcast", "check_writable", "ensure_files", "fleet_options", "run", "run_async", "worker_count"]


def check_broadcast(jobs: Sequence[Job], allow_broadcast: bool) -> None:
    """Unit 0 writes every device of a bus and nobody answers: only with explicit consent."""
    for j in jobs:
        if j.unit == 0 and not allow_broadcast:
            raise UsageError(
                f"{j.name}: unit 0 is broadcast (no device answers, nothing can be verified); "
                "pass --allow-broadcast to send it anyway"
            )


def ensure_files(parallel: int, devices: int) -> None:
    """One socket per device in flight: raise the soft open-file limit towards the hard one, or say why not."""
    need = min(parallel, devices) + 64  # sockets, plus the report, snapshots, logs and the interpreter's own
    hard = raise_open_files(need)  # POSIX only: Windows has no such limit on sockets
    if hard is not None:
        raise UsageError(
            f"--parallel {parallel} needs about {need} open files, but this system allows {hard} "
            f"(ulimit -Hn); use --parallel {max(1, hard - 64)} or raise the limit"
        )


def worker_count(
    workers: int | None, devices: int, parallel: int, opts: ApplyOptions, *, rollback_on_failure: bool
) -> int:
    """The worker processes a run takes (``fleet.workers``): ``workers`` itself (never more than devices at once),
    or for None one per CPU when the fleet is big enough; 0 where the devices must stay in this process. A count
    given for such a run is a UsageError before anything happens."""
    why = ineligible(opts, rollback_on_failure=rollback_on_failure)
    if workers is None:
        return 0 if why is not None else auto_count(devices, parallel)
    if workers and why is not None:
        raise UsageError(f"--workers {workers}: {why}, so its devices run in this process (use --workers 0)")
    return min(workers, parallel, devices)


def check_writable(folder: str, what: str) -> None:
    """Create ``folder`` if needed and make sure a file can be written there, or say why not (UsageError)."""
    probe = os.path.join(folder, f".deployer-probe-{os.getpid()}")
    try:
        os.makedirs(folder, exist_ok=True)
        with open(probe, "w", encoding="utf-8"):
            pass
        os.remove(probe)
    except OSError as e:
        raise UsageError(f"cannot write {what}: {disk_error(e)}") from None


def fleet_options(
    devices: int, *, parallel: int, batch: str | None, max_failures: str | None, report_path: str | None = None
) -> tuple[list[int], int | None]:
    """Check a run's options before anything happens: batch sizes, failure budget, open files,
    and that the report file can be written (it is written before the first device starts)."""
    sizes = batch_sizes(batch, devices)
    budget = failure_budget(max_failures, devices)
    ensure_files(parallel, devices)
    if report_path:  # before anything is sent: a link, a FIFO or a folder there is refused now
        from ..state.durable import check_output

        check_output(report_path, what="the report")
        check_writable(os.path.dirname(os.path.abspath(report_path)), f"the report {report_path}")
    return sizes, budget


async def run_async(
    jobs: Sequence[Job],
    *,
    command: str = "apply",
    label: str | None = None,
    argv: Sequence[str] = (),
    via: str = "api",
    options: ApplyOptions | None = None,
    parallel: int = 8,
    batch: str | None = None,
    max_failures: str | None = None,
    batch_by: str = "profile",
    report_path: str | None = None,
    signals: bool = False,
    refuse_broadcast: bool = False,
    on_start: Callable[[Job], None] | None = None,
    on_done: Callable[[DeviceResult], None] | None = None,
    keep_results: bool = True,
    workers: int | None = 0,
    user: str | None = None,
    **safe: Any,
) -> Report:
    """Run ``jobs`` as one journaled run (see the module's docstring); the report of every device.

    ``label``: what is applied (recipe, plan or snapshot file; the report's ``recipe``). ``command``,
    ``argv`` and ``via`` ("cli", "api", "ansible") go into the journal. ``batch`` ("1,10%,100%")
    stages the rollout, per profile (or per first group: ``batch_by="group"``); ``max_failures`` ("2", "5%")
    caps it. ``signals``: SIGINT and SIGTERM
    interrupt the run (its own process's main thread only; the command line and Ansible set it).
    ``refuse_broadcast``: a unit 0 without ``options.allow_broadcast`` is a UsageError before anything
    happens (the command line), not a ``failed`` device in the report.
    ``safe``: ``rollback_on_failure``, ``between_batches``, ``on_confirm_wait`` of ``fleet.rollout.apply_many``.
    ``keep_results`` False: devices that ended ok come back as ``DeviceResult.small()`` (counts, no
    requests or parameters: the report file has them), as ``apply_many`` says. ``workers``: worker processes
    running the devices (``fleet.workers``; 0: none; None: one per CPU for a big plain fleet); a run that must
    keep its devices in this process (a soak, a question per device) refuses a count given. ``user``: who asked,
    for the journal and the report, where it is not this process's user (the agent's authenticated user).

    Raises UsageError (nothing sent) for bad options, StalePlan or Declined when the run was refused
    before any write, RunInterrupted (with ``.report``) when it was interrupted.
    """
    opts = options or ApplyOptions()
    if not jobs:
        raise UsageError("no device to write")
    if refuse_broadcast:
        check_broadcast(jobs, opts.allow_broadcast)
    if opts.soak is not None:  # a soak watches the profiles' health checks: each profile must have some
        check_soak_profiles([j.recipe.profile for j in jobs])
    _, budget = fleet_options(
        len(jobs), parallel=parallel, batch=batch, max_failures=max_failures, report_path=report_path
    )
    workers = worker_count(
        workers, len(jobs), parallel, opts, rollback_on_failure=bool(safe.get("rollback_on_failure"))
    )
    jobs, sizes = batch_plan(jobs, batch, batch_by)  # each batch covers every profile (or group) of the line
    # before the journal's line and the report file: this process has no other thread yet (the report's comes
    # with it), so the workers may be forked; spawned ones import meanwhile. Nothing is sent until their setup.
    pool = await Pool.launch(workers, jobs) if workers else None
    try:
        started = time.time()
        state_dir = os.path.abspath(opts.state_dir)
        applied = opts.applied  # the journal and the snapshots name it so that it is found from anywhere
        if applied is None and label is not None:
            applied = os.path.abspath(label) if os.path.exists(label) else label
        snapshot.recovered(state_dir)  # a process that died before fsync'ing its snapshots left them in their log
        if not any(j.plan for j in jobs):  # what devices taught changes what is sent: a damaged file is refused now
            from ..state import learned

            learned.load(state_dir)
        run_id = opts.run_id or journal.new_run_id()  # a confirmation window names its run before it starts
        journal.run_started(
            state_dir,
            run_id,
            command=command,
            argv=argv,
            recipe=applied,
            via=via,
            devices=[(j.name, describe(j.url), j.unit) for j in jobs],
            user=user,
        )
        info = {
            **run_info(opts.command or f"Python API: {command}", started, user),
            "id": run_id,
            "state_dir": state_dir,
        }
        try:
            live = LiveReport(report_path, label, jobs, sizes, run=info) if report_path else None
        except UsageError as e:  # the report's first state could not be written: refused, nothing sent
            journal.run_refused(state_dir, run_id, str(e), command=command, argv=argv, recipe=label)
            raise
        opts = replace(
            opts,
            run_id=run_id,
            applied=applied,
            state_dir=state_dir,
            on_writing=_both(opts.on_writing, live.writing if live is not None else None),
        )

        done = _both(live.finished if live is not None else None, on_done)
        # a finished device's result changed (a soak rolled it back): its line anew, then the caller's
        changed = _both(live.update if live is not None else None, safe.pop("on_changed", None))
        why: list[str] = []
        restore = _on_signals(why) if signals else (lambda: None)
        try:
            report = await apply_many(
                jobs,
                parallel=parallel,
                options=opts,
                recipe_name=label,
                on_start=on_start,
                on_done=done,
                batches=sizes,
                max_failures=budget,
                on_changed=changed,
                keep_results=keep_results,
                pool=pool,
                report_lines=live is not None,
                **safe,
            )
        except RunInterrupted as e:
            report = e.report
            report.interrupted = why[0] if why else "cancelled"
        except (StalePlan, Declined, NotStarted) as e:  # nothing was written anywhere: the run ends, and says why
            refused = _refused_report(e, label, time.time() - started, info, run_id, state_dir)
            if live is not None:
                if refused is None:
                    live.stop()
                else:  # the report file says what the device was found holding, as --json does
                    try:
                        live.close(refused)
                    except UsageError as le:
                        refused.unrecorded.append(str(le))
            journal.run_refused(state_dir, run_id, str(e), command=command, argv=argv, recipe=label)
            raise
        finally:
            restore()
            if pool is not None:  # every device's lines are in; the run-finished line comes after the workers ended
                await pool.close()
        report.run, report.run_id, report.state_dir = info, run_id, state_dir
        await _record_end(report, live, command=command, argv=argv)
        if report.interrupted is not None:
            raise RunInterrupted(report, report.interrupted)
        return report
    finally:  # also when the journal's line or the report file could not be started (closing again does nothing)
        if pool is not None:
            await pool.close()


def _refused_report(
    e: Exception, label: str | None, seconds: float, info: dict[str, Any], run_id: str, state_dir: str
) -> Report | None:
    """The report of a one-device run refused before its first write (a stale plan, a "no"), set on the error as
    ``e.report``: the device skipped with the values it was found holding. None where no device was read."""
    if not isinstance(e, StalePlan | Declined) or e.result is None:
        return None
    report = Report(label, [e.result], seconds, run=info, run_id=run_id, state_dir=state_dir, refused=str(e))
    e.report = report
    return report


async def _record_end(report: Report, live: LiveReport | None, *, command: str, argv: Sequence[str]) -> None:
    """The final report file, then the journal's run-finished line. What reached the devices is never lost to a
    full disk: a file or line that cannot be written is said in the report (``unrecorded``, exit 4), which the
    caller still has and shows."""
    assert report.state_dir is not None
    if live is not None:
        try:
            live.close(report)
        except UsageError as e:
            report.unrecorded.append(f"{e}; what the devices hold is in this output")
    # the run's snapshot files fsync'ed themselves, their write-ahead log removed (state.wal); then, through the
    # group commit: after every line it still holds (a device interrupted while its snapshot and device-started
    # line were being made durable), so the run-finished line is the run's last
    await settled()
    with contextlib.suppress(OSError):  # a worker that died left its log: restored now (else by the next run)
        snapshot.recover(report.state_dir)
    path = journal.path_of(report.state_dir)
    try:
        await durable(Line(path, journal.finished_record(report.run_id, report, command=command, argv=argv)))
    except OSError as e:
        report.unrecorded.append(
            f"the journal {path} could not record the run's end (run-finished): "
            f"{disk_error(e)}; deployer status lists it as unfinished"
        )


def run(jobs: Sequence[Job], **kw: object) -> Report:
    """``run_async`` for callers without an event loop."""
    return asyncio.run(run_async(jobs, **kw))  # type: ignore[arg-type]


def _both(
    a: Callable[[DeviceResult], None] | None, b: Callable[[DeviceResult], None] | None
) -> Callable[[DeviceResult], None] | None:
    if a is None or b is None:
        return a or b

    def call(r: DeviceResult) -> None:
        a(r)
        b(r)

    return call


def _on_signals(why: list[str]) -> Callable[[], None]:
    """SIGINT (Ctrl-C) and SIGTERM (Ctrl-Break on Windows) cancel the running run (each one again: a second
    Ctrl-C also stops a device's closing lock writes); only the main thread of a process can own its
    signals. Returns the undo. ``portable.on_signals``: the event loop's handlers where it has them,
    ``signal.signal`` on Windows."""
    task = asyncio.current_task()
    assert task is not None

    def stop(sig: signal.Signals) -> None:
        why.append(sig.name)
        task.cancel()

    return on_signals(asyncio.get_running_loop(), interrupt_signals(), stop)
