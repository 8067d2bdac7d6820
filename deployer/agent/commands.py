"""What a client asks the agent to do (``POST /v1/runs``, a run's rollback, a confirmation): each request checked
against the files, the devices and the ledger before anything is sent (a refusal is an ApiError), then a run
(``runs.Runs``) or a window confirmed.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import Mapping
from dataclasses import replace
from typing import Any

from ..errors import DeployerError, UsageError
from ..execute.job import Job
from ..execute.session import ApplyOptions
from ..load.durations import parse_duration
from ..run.rollback import report_jobs
from ..state import journal
from ..window.confirm import confirm_run
from .ledger import Ledger
from .model import ApiError, RunState
from .runs import Runs
from .site import Site


class Commands:
    def __init__(self, site: Site, runs: Runs, ledger: Ledger) -> None:
        self.site, self.runs, self.ledger = site, runs, ledger

    def start_apply(self, req: Mapping[str, Any], *, take_up: bool = True) -> RunState:
        """``POST /v1/runs`` with command apply: roll out the files for the selected devices (every check
        before anything is sent; refusals are ApiError). ``take_up``: the files are read again first, so what
        is rolled out is what they say now, checked (``files_sha256``: refused if they changed since the client
        looked); without it (a user who may not take up an edit) what was taken up last is rolled out.
        ``req["by"]``: who asked (access.Who.record), for the run's records."""
        site = self.site
        if take_up:
            with contextlib.suppress(ApiError):
                site.reload()
        if site.files_problem:
            raise ApiError(
                "input", "the files are invalid; nothing was sent", status=400, diagnostics=site.files_problem
            )
        files = site.files
        assert files is not None
        want = req.get("files_sha256")
        if want and want != files.sha256:
            raise ApiError(
                "conflict",
                "the files changed since you looked (files_sha256 differs): look again "
                "(deployer plan --agent) and apply what you saw",
                status=409,
            )
        try:
            chosen = [d.name for d in files.inventory.select(req.get("limit"))]
        except UsageError as e:
            raise ApiError("usage", str(e), status=400) from None
        problems = [n for n in chosen if n not in site.devices]
        if problems:
            raise ApiError(
                "conflict",
                f"{', '.join(problems)}: new in the inventory; the agent owns them from its next start",
                status=409,
                exit_code=1,
            )
        recipe = req.get("recipe")
        if recipe:
            other = [n for n in chosen if os.path.abspath(files.jobs[n].recipe.path or "") != os.path.abspath(recipe)]
            if other:
                raise ApiError(
                    "refused",
                    f"{recipe} is not the recipe the inventory gives {', '.join(other)}: the "
                    "agent holds one desired state; edit the files (inventory and recipes) instead",
                    status=422,
                )
        opts = ApplyOptions(write_all=bool(req.get("write_all")))
        changes: dict[str, Any] = {}
        for key in ("soak", "health_interval", "confirm_within"):
            if req.get(key) is not None:
                try:
                    changes[key] = parse_duration(str(req[key]))
                except ValueError as e:
                    raise ApiError("usage", f"{key}: {e}", status=400) from None
        if req.get("allow_unhealthy"):
            if "soak" not in changes and "confirm_within" not in changes:
                raise ApiError(
                    "usage",
                    "allow_unhealthy goes with soak or confirm_within (only a safe change reads "
                    "the health checks before it writes)",
                    status=400,
                )
            changes["allow_unhealthy"] = True
        opts = replace(opts, **changes)
        jobs = [files.jobs[n] for n in chosen]
        self.ledger.check(jobs, force=bool(req.get("force_endurance")))
        options = {
            k: req[k]
            for k in (
                "limit",
                "batch",
                "max_failures",
                "parallel",
                "soak",
                "health_interval",
                "confirm_within",
                "allow_unhealthy",
                "rollback_on_failure",
                "write_all",
                "by",
                "recipe",
            )
            if req.get(k) is not None
        }
        return self.runs.start_run(
            jobs,
            command="apply",
            options=options,
            opts=opts,
            label=site.settings.inventory,
            batch=req.get("batch"),
            max_failures=req.get("max_failures"),
            parallel=int(req.get("parallel") or 8),
            rollback_on_failure=bool(req.get("rollback_on_failure")),
            adopt=True,
        )

    def start_restore(self, req: Mapping[str, Any]) -> RunState:
        """``POST /v1/runs`` with command restore: write the adopted state back to the selected devices."""
        site = self.site
        assert site.files is not None
        try:
            chosen = [d.name for d in site.files.inventory.select(req.get("limit")) if d.name in site.devices]
        except UsageError as e:
            raise ApiError("usage", str(e), status=400) from None
        jobs = []
        for n in chosen:
            dev = site.devices[n]
            if dev.adopted is not None:
                jobs.append(Job(n, dev.adopted, dev.job.url, dev.job.unit))
        if not jobs:
            raise ApiError("usage", "no device selected", status=400)
        self.ledger.check(jobs, force=bool(req.get("force_endurance")))
        return self.runs.start_run(
            jobs,
            command="restore",
            options={"reason": "requested", "by": req.get("by")},
            opts=ApplyOptions(),
            label="the adopted state",
        )

    async def start_rollback(self, run_id: str, *, by: Mapping[str, Any] | None = None) -> RunState:
        """``POST /v1/runs/{id}/rollback``: restore what a finished run wrote, from its snapshots."""
        site = self.site
        run = self.runs.live.get(run_id)
        if run is None:
            raise ApiError("not-found", f"no run {run_id} in this agent", status=404)
        if run.state in ("running", "waiting"):
            raise ApiError(
                "conflict",
                f"run {run_id} has not ended (it is {run.state}); wait for it, or let its window run out",
                status=409,
            )
        path = os.path.join(site.folder, "reports", f"{run_id}.json")
        try:  # it reads the devices (do they still hold what the run wrote?) with a loop of its own
            jobs, notices = await asyncio.to_thread(report_jobs, [path])
        except DeployerError as e:
            raise ApiError("usage", f"run {run_id}: {e}", status=400) from None
        jobs = [j for j in jobs if j.name in site.devices]
        if not jobs:
            raise ApiError("usage", f"run {run_id} wrote nothing to roll back", status=400)
        return self.runs.start_run(
            jobs,
            command="rollback",
            options={"reason": f"rollback of run {run_id}", "notices": notices, "by": by},
            opts=ApplyOptions(),
            label=path,
        )

    def confirm(self, run_id: str | None, *, by: Mapping[str, Any] | None = None) -> RunState:
        """Confirm a run waiting in its confirm window (the one waiting when ``run_id`` is None); ``by``: who."""
        site = self.site
        waiting = [r for r in self.runs.live.values() if r.state == "waiting"]
        if run_id is None:
            if len(waiting) != 1:
                raise ApiError(
                    "conflict",
                    "no run waits for a confirmation"
                    if not waiting
                    else "several runs wait for a confirmation: name one: " + ", ".join(r.id for r in waiting),
                    status=409,
                )
            run_id = waiting[0].id
        run = self.runs.live.get(run_id)
        if run is None:
            raise ApiError("not-found", f"no run {run_id} in this agent", status=404)
        if run.state != "waiting":
            raise ApiError("conflict", f"run {run_id} does not wait for a confirmation (it is {run.state})", status=409)
        if not run.options.get("resumed"):  # a live run waits for the journal's confirmed line
            try:
                confirm_run(site.state_dir, run_id)
            except UsageError as e:
                raise ApiError("conflict", str(e), status=409) from None
        else:
            journal.append(
                site.state_dir,
                {
                    "event": "confirmed",
                    "run": run_id,
                    "time": journal._now(),
                    "user": journal.user_name(),
                    "pid": os.getpid(),
                    "via": "agent",
                },
            )
        if run.window is not None:
            self.runs.close_window(run.window, "confirmed")
        run.state = "running"
        site.event(
            "window-confirmed",
            f"run {run_id} confirmed" + (f" by {by['user']}" if by and by.get("user") else ""),
            detail={"run": run_id, "by": by},
        )
        run.emit("window-confirmed", run=run_id)
        return run
