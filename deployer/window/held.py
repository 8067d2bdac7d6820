"""A device in its window, and the window's journal lines."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from ..execute.job import Job
from ..execute.session import ApplyOptions
from ..recipe.loader import Recipe
from ..report import DeviceResult
from ..state import journal
from ..state.durable import append_lines
from ..transport import clients as tp


@dataclass(frozen=True)
class Written:
    """A device whose change is verified and waits: for its soak, its commit or the run's confirmation."""

    job: Job
    result: DeviceResult

    @property
    def name(self) -> str:
        return self.job.name

    @property
    def recipe(self) -> Recipe:
        return self.job.recipe

    @property
    def url(self) -> tp.DeviceURL:
        return self.job.url

    @property
    def unit(self) -> int:
        return self.job.unit


def needs_soak(r: DeviceResult) -> bool:
    """Something was written and verified (a device with nothing to write has nothing to watch or undo)."""
    return r.status == "ok" and r.snapshot is not None


def pending_path(state_dir: str, run: str) -> str:
    """The report of a run that waits for its confirmation (what ``status`` points a rollback at)."""
    return os.path.join(os.path.abspath(state_dir), "pending", f"{run}.json")


def record(options: ApplyOptions, line: dict[str, Any]) -> None:
    append_lines(journal.path_of(options.state_dir), [line])
