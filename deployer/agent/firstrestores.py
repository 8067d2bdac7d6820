"""The first restores after the agent starts go like a rollout, not all at once.

An agent started with ``--on-drift restore`` (or ``--on-replace restore``) finds, at its first check, every
device that drifted while it was down, and each used to be written within a second of the start, with
no canary. The restores the first round of checks asks for are kept, then run as one staged restore run:
one device of each profile first (the canary batch), soaked ``--first-restore-soak`` on its profile's
health checks (read before the write too: a device already in alarm is not written), then the rest.
The first device that does not end ok stops them: the rest are not started, automatic restores stay off
until the agent restarts (the watch reports drift; a restore asked through the API still runs), and a
``restores-stopped`` event says so (``--notify`` receivers get it like every event).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from ..api import Report
from ..errors import DeployerError
from ..execute.job import Job
from ..execute.session import ApplyOptions


class Agent(Protocol):
    """What of the agent (``runs.Runs``) the staging uses."""

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
    ) -> Any: ...

    def event(
        self, kind: str, message: str, *, device: str | None = None, detail: Mapping[str, Any] | None = None
    ) -> dict[str, Any]: ...


BATCH = "1,100%"  # one device of each profile, then the rest


@dataclass
class FirstRestores:
    soak: float  # seconds the canary batch is watched (0: its health checks read once after the write)
    collecting: bool = True  # the first round of checks is not over: restores are kept, not started
    kept: list[tuple[Job, str]] = field(default_factory=list)  # each restore asked for, and why (drift, replaced)
    run: str | None = None  # the staged run, once started
    stopped: str | None = None  # why automatic restores are off (until the agent restarts)

    def keep(self, job: Job, why: str) -> bool:
        """Keep a restore the first round asks for; False once that round is over (start it now)."""
        if not self.collecting:
            return False
        self.kept.append((job, why))
        return True

    def start(self, agent: Agent) -> None:
        """The first round of checks is over: the restores it asked for start, staged."""
        self.collecting = False
        if not self.kept:
            return
        jobs = [j for j, _ in self.kept]
        watched = any(j.recipe.profile.health for j in jobs)  # nothing to watch: the canary's read-back decides
        opts = ApplyOptions(soak=self.soak if watched else None)
        why = ", ".join(f"{j.name} ({w})" for j, w in self.kept)
        try:
            run = agent.start_run(
                jobs,
                command="restore",
                label="the adopted state",
                batch=BATCH,
                max_failures="1",
                options={
                    "reason": f"first restores after the start: {why}",
                    "batch": BATCH,
                    "max_failures": "1",
                    "staged": True,
                },
                opts=opts,
                health_unchecked=True,
            )
        except DeployerError as e:  # the agent refused it (model.ApiError)
            self._stop(agent, f"the first restores after the start could not start: {e}", [j.name for j in jobs])
            return
        self.run = run.id

    def finished(self, agent: Agent, run_id: str, report: Report | None, state: str) -> None:
        """The staged run ended: any device not ok stops the automatic restores (an event says which)."""
        if run_id != self.run:
            return
        if report is None:
            self._stop(
                agent,
                f"the first restores after the start ended {state} (run {run_id})",
                [j.name for j, _ in self.kept],
            )
            return
        bad = [d for d in report.devices if d.status != "ok"]
        if not bad:
            return
        failed = [d for d in bad if d.status != "skipped"]
        first = failed[0] if failed else bad[0]
        self._stop(
            agent,
            f"the first restores after the start stopped at {first.name} ({first.status}: "
            f"{first.error or 'see its parameters'}) in run {run_id}",
            [d.name for d in bad],
        )

    def _stop(self, agent: Agent, why: str, devices: Sequence[str]) -> None:
        self.stopped = why
        detail: dict[str, Any] = {"run": self.run, "not_restored": list(devices)}
        agent.event(
            "restores-stopped",
            f"{why}; not restored: {', '.join(devices)}. Automatic restores are off "
            "until the agent restarts (drift is reported); restore through the agent after a look "
            "(POST /v1/runs with command restore)",
            detail=detail,
        )
