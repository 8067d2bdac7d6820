"""Windows a site agent left open (docs/agent.md, "It owns windows"), found at its next start.

One whose time ran out while the agent was down, one opened in another boot of the machine, and a soak nobody
watched to its end are rolled back from the run's snapshots (``roll_back``). A confirm window with time left waits
for its confirmation (``wait``), then sends its held commits (``commit``; each device's parameters read again
first) or rolls back. The agent runs the rollback and keeps the waiting run (``Agent`` below): the decisions and
the window's files are here.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from collections.abc import Mapping, Sequence
from typing import Any, Protocol

from ..errors import DeployerError
from ..execute.job import Job
from ..execute.session import ApplyOptions
from ..report import DeviceResult, read_report, report_from_json
from ..state import journal
from .finish import send_commit
from .held import Written
from .state import WindowState


class Agent(Protocol):
    """What of the site agent a window's end uses (``agent.runs.Runs``)."""

    state_dir: str

    def event(
        self, kind: str, message: str, *, device: str | None = None, detail: Mapping[str, Any] | None = None
    ) -> dict[str, Any]: ...

    def close_window(self, w: WindowState, state: str) -> None: ...

    def job(self, name: str) -> Job | None:
        """The device's job as the agent has it (None: not one of its devices)."""

    async def roll_back(self, report: str, *, reason: str) -> str | None:
        """Run a rollback of what ``report``'s run wrote to the agent's devices (even values changed since; commits
        held) to its end: the rollback's run id (None: nothing of it to roll back); DeployerError: not started."""

    def resume(self, w: WindowState) -> None:
        """Wait for the window's confirmation in the background (``wait``, then ``commit`` or ``roll_back``)."""

    def committed(self, run: str, job: Job, result: DeviceResult, requests: Sequence[Any]) -> None:
        """``requests`` were sent to ``job``'s device for the commit of ``run``, which ``result`` now shows."""


class Waiting(Protocol):
    """The agent's run that waits for a window's confirmation."""

    state: str  # "waiting" until confirmed

    @property
    def changed(self) -> asyncio.Event: ...


async def recover(agent: Agent, windows: Sequence[WindowState], boot_id: str) -> None:
    """Each window left open: rolled back now (its time is over), or waiting for its confirmation."""
    for w in windows:
        why = w.expired_why(boot_id, time.time())
        if why is not None:
            await roll_back(agent, w, why)
        else:
            agent.resume(w)


async def roll_back(agent: Agent, w: WindowState, why: str) -> None:
    """The window is over without a confirmation: its devices rolled back from the run's snapshots (even values
    changed since: the window's owner is gone), the report it held given up."""
    agent.close_window(w, "expired")
    agent.event(
        "window-expired",
        f"run {w.run}: {why}; rolling back {', '.join(w.devices)}",
        detail={"run": w.run, "devices": w.devices},
    )
    try:
        back = await agent.roll_back(w.report, reason=f"window of run {w.run}: {why}")
    except DeployerError as e:
        agent.event("restore-failed", f"run {w.run}: cannot roll back its window: {e}", detail={"run": w.run})
        return
    if back is not None:
        _resolved(agent, w, f"agent: rolled back by run {back} ({why})")


async def wait(run: Waiting, w: WindowState) -> bool:
    """Wait for ``run``'s confirmation until the window's deadline: whether it came."""
    deadline = time.monotonic() + (w.deadline_epoch - time.time())  # from now on the monotonic clock counts
    while run.state == "waiting" and time.monotonic() < deadline:
        ev = run.changed
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(ev.wait(), min(0.2, max(0.0, deadline - time.monotonic())))
    return run.state != "waiting"


async def commit(agent: Agent, w: WindowState) -> dict[str, DeviceResult]:
    """The window was confirmed: its held commits sent (each device's parameters read again first: one changed
    meanwhile is never committed). What each device ended with."""
    held = report_from_json(read_report(w.report))  # what the run wrote and read back, per parameter
    opts = ApplyOptions(state_dir=agent.state_dir, run_id=w.run)
    out: dict[str, DeviceResult] = {}
    for res in held.devices:
        job = agent.job(res.name)
        if job is None or res.commit != "held":
            continue
        sent = len(res.requests)
        await send_commit(Written(job, res), opts)
        agent.committed(w.run, job, res, res.requests[sent:])
        out[res.name] = res
    _resolved(agent, w, "agent: confirmed after the agent's restart, commit sent")
    return out


def _resolved(agent: Agent, w: WindowState, note: str) -> None:
    """The run's journal says how its window ended; its held report is no longer needed."""
    with contextlib.suppress(KeyError, OSError):
        journal.resolve(agent.state_dir, w.run, note=note)
    with contextlib.suppress(OSError):
        os.remove(w.report)
