"""The agent's runs: started (every check before anything is sent), executed by the library's runner with the
agent's hooks (the ledger counts each write, a soak or confirm window is opened in the store), and ended: what a
run wrote adopted, its restores and rollbacks said. A window an earlier agent left open is ended from here too
(``window.recover``: the agent is its ``Agent``).
"""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

from ..api import DeviceResult, Report
from ..errors import DeployerError, RunInterrupted, UsageError
from ..execute.job import Job
from ..execute.session import ApplyOptions
from ..run.rollback import report_jobs
from ..run.runner import fleet_options, run_async
from ..state import journal
from ..window import recover
from ..window.soak import check_soak_profiles
from ..window.state import WindowState
from .audit_events import run_finished
from .ledger import Ledger
from .model import ApiError, RunState
from .site import Site
from .store import Store


class Runs:
    def __init__(self, site: Site, ledger: Ledger) -> None:
        self.site, self.ledger = site, ledger
        self.state_dir = site.state_dir
        self.live: dict[str, RunState] = {}  # the runs since the agent's start (earlier ones: the store's)
        self.tasks: set[asyncio.Task[Any]] = set()  # the waits of windows an earlier agent left open

    def event(
        self, kind: str, message: str, *, device: str | None = None, detail: Mapping[str, Any] | None = None
    ) -> dict[str, Any]:
        return self.site.event(kind, message, device=device, detail=detail)

    def start_run(
        self,
        jobs: Sequence[Job],
        *,
        command: str,
        options: dict[str, Any],
        opts: ApplyOptions,
        label: str | None,
        batch: str | None = None,
        max_failures: str | None = None,
        parallel: int = 8,
        rollback_on_failure: bool = False,
        adopt: bool = False,
        health_unchecked: bool = False,
    ) -> RunState:
        """Start a run of ``jobs`` (ApiError: refused, nothing sent). ``health_unchecked``: a soak may include
        profiles without health checks (the agent's staged first restores); a client's soak may not."""
        devices = self.site.devices
        busy = [j.name for j in jobs if devices[j.name].run is not None]
        if busy:
            raise ApiError(
                "conflict",
                f"{', '.join(busy)}: in run {devices[busy[0]].run} now; wait for it",
                status=409,
                exit_code=3,
            )
        unowned = [j.name for j in jobs if not devices[j.name].owned]
        if unowned:
            why = devices[unowned[0]].not_owned_why or "its lock is held elsewhere"
            raise ApiError(
                "locked",
                f"{', '.join(unowned)}: not owned by the agent ({why}); nothing was sent",
                status=409,
                exit_code=3,
            )
        try:
            fleet_options(len(jobs), parallel=parallel, batch=batch, max_failures=max_failures)
            if opts.soak is not None and not health_unchecked:
                check_soak_profiles([j.recipe.profile for j in jobs])
        except UsageError as e:
            raise ApiError("usage", str(e), status=400) from None
        run_id = journal.new_run_id()
        by = options.get("by") or {}
        who = by.get("user") or (f"the {by['credential']}" if by.get("credential") else None)
        opts = replace(
            opts,
            state_dir=self.state_dir,
            run_id=run_id,
            command=f"agent {command}"
            + (f" by {who}" if who else "")
            + (f": {options['reason']}" if options.get("reason") else ""),
        )
        run = RunState(run_id, command, [j.name for j in jobs], options)
        self.live[run_id] = run
        for j in jobs:
            devices[j.name].run = run_id
        self._store.run_started(run_id, command, options)
        run.emit("run-started", run=run_id, command=command, devices=run.devices, by=options.get("by"))
        run.task = asyncio.ensure_future(
            self._execute(
                run,
                jobs,
                opts,
                label=label,
                batch=batch,
                max_failures=max_failures,
                parallel=parallel,
                rollback_on_failure=rollback_on_failure,
                adopt=adopt,
            )
        )
        return run

    @property
    def _store(self) -> Store:
        assert self.site.store is not None
        return self.site.store

    async def _execute(
        self,
        run: RunState,
        jobs: Sequence[Job],
        opts: ApplyOptions,
        *,
        label: str | None,
        batch: str | None,
        max_failures: str | None,
        parallel: int,
        rollback_on_failure: bool,
        adopt: bool,
    ) -> None:
        reports = os.path.join(self.site.folder, "reports")
        os.makedirs(reports, exist_ok=True)
        report_path = os.path.join(reports, f"{run.id}.json")
        counted: dict[str, int] = {}
        by_name = {j.name: j for j in jobs}

        def count(r: DeviceResult) -> None:
            run.results[r.name] = r
            start = counted.get(r.name, 0)
            counted[r.name] = len(r.requests)
            self.ledger.count(r, by_name[r.name].recipe.profile, r.requests[start:])

        def done(r: DeviceResult) -> None:
            count(r)
            run.emit("device-finished", device=r.to_json())

        def changed(r: DeviceResult) -> None:
            count(r)
            run.emit("device-changed", device=r.to_json())

        def started(j: Job) -> None:
            run.emit("device-started", name=j.name)

        report: Report | None = None
        state = "finished"
        error: DeployerError | None = None
        try:
            report = await run_async(
                list(jobs),
                command=run.command,
                label=label,
                argv=[],
                via="agent",
                user=(run.options.get("by") or {}).get("user"),  # the person the credential names (None: a site token)
                options=opts,
                parallel=parallel,
                batch=batch,
                max_failures=max_failures,
                report_path=report_path,
                on_start=started,
                on_done=done,
                on_changed=changed,
                on_confirm_wait=lambda _, deadline: self._waiting(run, deadline),
                on_soak=lambda n, names: self._soaking(run, n, names, opts.soak or 0),
                rollback_on_failure=rollback_on_failure,
            )
        except RunInterrupted as e:
            report, state = e.report, "interrupted"
        except DeployerError as e:  # refused before anything was sent (a stale plan ...)
            error, state = e, "refused"
        except asyncio.CancelledError:
            state = "interrupted"
        finally:
            for j in jobs:
                self.site.devices[j.name].run = None
            self._window_ends(run, report)
        if report is not None:
            self.site.run_ended(run, report, by_name, adopt=adopt)
            run.report = report.to_json()
            run.exit_code = report.exit_code
        else:
            run.exit_code = 130 if state == "interrupted" else (error.exit_code if error else 1)
        run.state, run.finished = state, time.time()
        self.site.first.finished(self, run.id, report, state)
        self._store.run_ended(run.id, state, run.exit_code, report_path if report is not None else None)
        self.event(
            "run-finished",
            f"run {run.id} ({run.command}) {state}, exit code {run.exit_code}",
            detail={"run": run.id, "exit_code": run.exit_code, "by": run.options.get("by")},
        )
        if report is not None:
            run_finished(self.site, report, command=run.command, by=run.options.get("by"))
        run.emit(
            "run-finished",
            run=run.id,
            state=state,
            exit_code=run.exit_code,
            report=run.report,
            error=None if error is None else str(error),
        )

    # ---- its windows ----------------------------------------------------------------------------------

    def _soaking(self, run: RunState, number: int, names: list[str], seconds: float) -> None:
        """A batch's soak starts: its window opened (in the store, and the run's)."""
        run.window = WindowState.opened(
            run.id, "soak", names, time.time() + seconds, state_dir=self.state_dir, boot_id=self.site.boot
        )
        self._store.open_window(run.window)
        run.emit("soak-started", batch=number, devices=names, deadline=run.window.deadline)

    def _waiting(self, run: RunState, deadline: float) -> None:
        """The run waits for its confirmation: the soak passed, the confirm window opened."""
        names = [n for n, r in run.results.items() if r.status == "ok" and r.snapshot is not None]
        if run.window is not None and run.window.kind == "soak":
            self.close_window(run.window, "passed")
        run.window = w = WindowState.opened(
            run.id, "confirm", names, deadline, state_dir=self.state_dir, boot_id=self.site.boot
        )
        self._store.open_window(w)
        run.state = "waiting"
        self.event(
            "window-waiting",
            f"run {run.id} waits for its confirmation until {w.deadline} "
            f"({', '.join(names)}): deployer confirm --agent {self.site.url} {run.id}",
            detail={"run": run.id, "devices": names, "deadline": w.deadline},
        )
        run.emit("window-waiting", run=run.id, devices=names, deadline=w.deadline, deadline_epoch=deadline)

    def _window_ends(self, run: RunState, report: Report | None) -> None:
        """The run ended: a soak still open ended with it; a confirm window not confirmed expired (rolled back)."""
        w = run.window
        if w is None or w.state != "open":
            return
        if w.kind == "soak":
            self.close_window(w, "ended")
            return
        expired = report is None or any(r.status == "rolled-back" for r in report.devices)
        self.close_window(w, "expired" if expired else "confirmed")
        if expired:
            self.event("window-expired", f"run {run.id}: not confirmed in time, rolled back", detail={"run": run.id})
            run.emit("window-expired", run=run.id)

    def close_window(self, w: WindowState, state: str) -> None:
        self._store.close_window(w, state)

    # ---- what a run leaves ----------------------------------------------------------------------------

    # ---- windows an earlier agent left open (window.recover) -----------------------------------------

    def job(self, name: str) -> Job | None:
        dev = self.site.devices.get(name)
        return None if dev is None else Job(dev.name, dev.job.recipe, dev.job.url, dev.job.unit)

    async def roll_back(self, report: str, *, reason: str) -> str | None:
        jobs, _ = await asyncio.to_thread(report_jobs, [report], force=True, even_if_changed=True)
        jobs = [j for j in jobs if j.name in self.site.devices]
        if not jobs:
            return None
        run = self.start_run(
            jobs, command="rollback", options={"reason": reason}, opts=ApplyOptions(hold_commit=True), label=report
        )
        if run.task is not None:
            await asyncio.shield(run.task)
        return run.id

    def resume(self, w: WindowState) -> None:
        self.tasks.add(asyncio.ensure_future(self._resume(w)))

    async def _resume(self, w: WindowState) -> None:
        """A confirm window that outlived its agent and has time left: wait for the confirmation, then commit."""
        run = RunState(w.run, "apply (resumed window)", list(w.devices), {"resumed": True}, state="waiting", window=w)
        self.live[w.run] = run
        held = [self.site.devices[n] for n in w.devices if n in self.site.devices]
        for dev in held:
            dev.run = w.run
        self.event(
            "window-waiting",
            f"run {w.run} (from before the agent's restart) waits for its confirmation until {w.deadline}",
            detail={"run": w.run, "devices": w.devices},
        )
        try:
            confirmed = await recover.wait(run, w)
        finally:
            for dev in held:
                dev.run = None
        if not confirmed:
            run.state = "finished"
            await recover.roll_back(self, w, "not confirmed in time")
            run.finished = time.time()
            run.emit("run-finished", run=w.run, state="rolled-back", exit_code=4, report=None, error=None)
            return
        run.results.update(await recover.commit(self, w))
        self.site.pending()
        run.state, run.finished, run.exit_code = "finished", time.time(), 0
        run.emit("run-finished", run=w.run, state="finished", exit_code=0, report=None, error=None)

    def committed(self, run: str, job: Job, result: DeviceResult, requests: Sequence[Any]) -> None:
        self.ledger.count(result, job.recipe.profile, requests)
        if result.commit == "sent":  # the run's end, which its agent did not live to see: adopted now
            dev = self.site.devices[job.name]
            values = {p.name: tuple(p.desired_raw) for p in result.parameters if p.status in ("ok", "unchanged")}
            self.site.adopt(
                dev,
                dev.job,
                {**dev.adopted_values, **values},
                run=run,
                why=f"run {run}, confirmed after the agent's restart",
            )
