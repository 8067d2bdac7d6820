"""One device of a run: what is written where (the rollout, the window and the runner share it)."""

from __future__ import annotations

from dataclasses import dataclass

from ..planning.model import Plan
from ..recipe.loader import Recipe
from ..transport import clients as tp


@dataclass(frozen=True)
class Job:
    name: str
    recipe: Recipe
    url: tp.DeviceURL
    unit: int
    group: str | None = None  # the first group an inventory lists for the device (--batch-by group)
    hold_commit: bool = False  # a rollback of a run that never sent its commit there: it sends none either
    commit_owed: bool = False  # ``--limit @REPORT``: its commit failed there; sent even with nothing to write
    plan: Plan | None = None  # ``apply PLAN.json``: the saved plan, executed unchanged
