"""The write ledger: every write and commit request the agent sends, counted per register (in its store), and the
endurance budgets a profile states for its registers' memory (a warning near one, a refusal past one)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from ..api import DeviceResult, Profile
from ..execute.job import Job
from ..profile.model import SPACE
from .model import ApiError, Device
from .site import Site
from .store import Store

WRITES = (5, 6, 15, 16)  # the function codes that write


def budgets(profile: Profile) -> dict[int, tuple[int, str]]:
    """Register key -> (endurance, what) for the registers a profile states a budget for."""
    out: dict[int, tuple[int, str]] = {}
    for p in profile.parameters:
        e = p.endurance or profile.endurance
        if e:
            for k in range(p.key, p.key + p.count):
                out[k] = (e, p.name)
    if profile.endurance:
        for a in profile.commit:
            out[a.key] = (profile.endurance, "commit")
    return out


class Ledger:
    def __init__(self, agent: Site) -> None:
        self.agent = agent

    @property
    def store(self) -> Store:
        assert self.agent.store is not None
        return self.agent.store

    def count(self, r: DeviceResult, profile: Profile, requests: Sequence[Any]) -> None:
        """Count write requests (every attempt sent) per register; a commit action's register counts commits."""
        commit_keys = {a.key for a in profile.commit}
        writes: dict[int, int] = {}
        commits: dict[int, int] = {}
        for q in requests:
            if q.function not in WRITES or not q.attempts:
                continue
            space = SPACE["coil"] << 16 if q.function in (5, 15) else 0
            for a in range(q.address, q.address + q.count):
                target = commits if space | a in commit_keys else writes
                target[space | a] = target.get(space | a, 0) + q.attempts
        if not writes and not commits:
            return
        self.store.count_writes(r.name, writes, commits)
        dev = self.agent.devices.get(r.name)
        if dev is not None:
            dev.writes += sum(writes.values()) + sum(commits.values())
            self._warn(dev, profile, set(writes) | set(commits))

    def _warn(self, dev: Device, profile: Profile, keys: set[int]) -> None:
        have = budgets(profile)
        counts = self.store.ledger(dev.name).get(dev.name, {})
        for k in sorted(keys & set(have)):
            budget, what = have[k]
            used = sum(counts.get(k, (0, 0)))
            if used >= budget * self.agent.settings.endurance_warn:
                self.agent.event(
                    "endurance-warning",
                    f"{dev.name}: register 0x{k & 0xFFFF:04X} ({what}) has taken "
                    f"{used} of the {budget} writes its memory is rated for",
                    device=dev.name,
                    detail={"register": k, "writes": used, "endurance": budget},
                )

    def check(self, jobs: Sequence[Job], *, force: bool) -> None:
        """Refuse (ApiError, nothing sent) a run that would write a register past its budget, unless ``force``."""
        over = []
        for j in jobs:
            have = budgets(j.recipe.profile)
            counts = self.store.ledger(j.name).get(j.name, {})
            keys = {k for d in j.recipe.desired for k in range(d.parameter.key, d.parameter.key + d.parameter.count)}
            keys |= {a.key for a in j.recipe.profile.commit}
            for k in sorted(keys & set(have)):
                used = sum(counts.get(k, (0, 0)))
                if used >= have[k][0]:
                    over.append(f"{j.name} register 0x{k & 0xFFFF:04X} ({have[k][1]}): {used} of {have[k][0]} writes")
        if over and not force:
            self.agent.event("endurance-refused", "past the endurance budget: " + "; ".join(over))
            raise ApiError(
                "refused",
                "past the rated endurance of its memory, nothing sent: "
                + "; ".join(over)
                + " (force_endurance, --force-endurance, to write anyway)",
                status=422,
                exit_code=1,
            )

    def to_json(self) -> dict[str, Any]:
        """``GET /v1/ledger``: per device, each register's writes and commits, and its budget."""
        counts = self.store.ledger()
        out = []
        for dev in self.agent.devices.values():
            prof = dev.adopted.profile if dev.adopted else dev.job.recipe.profile
            have = budgets(prof)
            regs = counts.get(dev.name, {})
            out.append(
                {
                    "name": dev.name,
                    "registers": [
                        {
                            "register": k,
                            "address": k & 0xFFFF,
                            "writes": w,
                            "commits": c,
                            "budget": have[k][0] if k in have else None,
                        }
                        for k, (w, c) in sorted(regs.items())
                    ],
                }
            )
        return {"devices": out}
