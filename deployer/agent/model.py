"""The agent's things: its settings, a device as it sees it, a run it executes, the refusal it answers with.

The parts of the agent (``site``, ``watch``, ``runs``, ``commands``, ``ledger``, ``views``) share these.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from ..api import DeviceResult, Recipe
from ..errors import DeployerError
from ..execute.job import Job
from ..state import journal, lock
from ..window.state import WindowState

API_VERSION = 1
WRITES = (5, 6, 15, 16)
STATUSES = ("ok", "drifted", "unreachable", "replaced", "running", "not-owned", "unknown")


class ApiError(DeployerError):
    """A request the agent refuses: ``kind`` and HTTP ``status`` for the answer, ``exit_code`` for the CLI."""

    def __init__(
        self, kind: str, message: str, *, status: int, exit_code: int = 1, diagnostics: Sequence[str] = ()
    ) -> None:
        super().__init__(message)
        self.kind, self.status, self.diagnostics = kind, status, list(diagnostics)
        object.__setattr__(self, "exit_code", exit_code)  # per refusal: what the command line would exit with


@dataclass
class Settings:
    inventory: str
    state_dir: str = ".deployer"
    check_every: float = 300.0
    on_drift: str = "report"
    on_replace: str = "report"
    bus_share: float = 0.2  # at most this share of a bus's time goes to watching
    max_restores: int = 3  # per device and hour; a device that keeps drifting back is reported, not fought
    first_restore_soak: float = 10.0  # the first restores after a start: the canary batch's soak (firstrestores)
    endurance_warn: float = 0.8
    keep_events: float = 90 * 86400.0
    parallel: int = 64  # buses read at once by the watch


@dataclass
class Device:
    name: str
    job: Job  # the files' job (URL, unit, the files' recipe)
    adopted: Recipe | None = None
    adopted_values: dict[str, tuple[int, ...]] = field(default_factory=dict)
    owned: bool = False
    locks: list[lock.DeviceLock] = field(default_factory=list)
    not_owned_why: str | None = None
    status: str = "unknown"
    drift: list[dict[str, Any]] = field(default_factory=list)
    last_values: dict[str, tuple[int, ...]] | None = None
    asleft: dict[str, tuple[int, ...]] | None = None  # as stored in the database
    last_check: float | None = None
    unreachable_since: float | None = None
    unreachable_why: str | None = None
    run: str | None = None  # the agent's run that has it now
    checking: bool = False  # being read now (the watch and a client's check never read it twice at once)
    restores: deque[float] = field(default_factory=deque)
    replaced: str | None = None
    pending: list[dict[str, Any]] = field(default_factory=list)
    # the inventory's agent settings for it (defaults < groups < its own), over the command line's
    check_every: float = 300.0
    on_drift: str = "report"
    on_replace: str = "report"
    # counters for /metrics (loaded from the database at start, so they survive restarts)
    drift_events: int = 0
    drift_restores: int = 0
    replaced_total: int = 0
    writes: int = 0


@dataclass
class RunState:
    id: str
    command: str
    devices: list[str]
    options: dict[str, Any]
    started: float = field(default_factory=time.time)
    state: str = "running"  # running, waiting, finished, refused, interrupted
    events: list[dict[str, Any]] = field(default_factory=list)
    changed: asyncio.Event = field(default_factory=asyncio.Event)
    task: asyncio.Task[None] | None = None
    report: dict[str, Any] | None = None
    exit_code: int | None = None
    window: WindowState | None = None  # the window it is in or ended with (its one state: window/state.py)
    finished: float | None = None
    results: dict[str, DeviceResult] = field(default_factory=dict)

    def emit(self, event: str, **data: Any) -> None:
        self.events.append({"n": len(self.events), "event": event, "time": journal._now(), **data})
        self.changed.set()
        self.changed = asyncio.Event()

    def to_json(self, *, report: bool = True) -> dict[str, Any]:
        out: dict[str, Any] = {
            "id": self.id,
            "command": self.command,
            "state": self.state,
            "devices": self.devices,
            "options": self.options,
            "started": iso(self.started),
            "finished": None if self.finished is None else iso(self.finished),
            "exit_code": self.exit_code,
            "window": None if self.window is None else self.window.run_json(),
        }
        if report:
            out["report"] = self.report
        return out


def iso(t: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t))
