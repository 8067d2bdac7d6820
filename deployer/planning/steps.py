"""A device's whole plan: the checks, the writes and every step around them, in the order apply sends them.

``Planner(recipe)`` works out once what every device of a recipe shares (the reads, the checks that lead
every plan); ``Planner.plan(target, current)`` is one device's plan against what it holds. Pure: no I/O.

The order (docs/design.md#the-plan-is-the-contract):

    identity       each identity register, read and compared       (the wrong device: nothing written)
    snapshot       the blocks holding the recipe's parameters      (what the device holds: the snapshot)
    device-id      Function 43 basic objects                       (vendor, product code, revision)
    firmware       the revision's registers, where a profile says so
    --- the plan is made here, against what the checks read ---
    precondition   each precondition's register, with its condition ("drive stopped")
    health         each health check's register(s), in the plan of a safe change (--soak, --confirm-within):
                   a device already failing one is not written
    unlock         the profile's unlock writes
    read-modify-write, write   per request; a bit field's register is read right before its write
    verify         the same blocks as the snapshot, read back
    commit         the profile's commit writes, sent only when every parameter verified
    lock           the profile's lock writes, sent whenever the unlock was

A plan that writes nothing ends after the checks (a retry that owes a commit: unlock, commit, lock). A
broadcast (unit 0) has only its write steps: nobody answers a read.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

from ..profile.model import READ_FUNCTION
from .model import DEVICE_ID, NO_PAUSES, Expect, Pacing, Plan, ReadRequest, Step, StepKind, Target, WriteRequest
from .planner import plan_reads, plan_writes, read_key

if TYPE_CHECKING:
    from ..profile import Profile, WriteAction
    from ..recipe.loader import Recipe
    from ..transport.urls import DeviceURL

_KEPT = 64  # plans a Planner remembers (devices holding the same values share one)


def pacing_for(url: DeviceURL | None, profile: Profile | None) -> Pacing:
    """Seconds of silence the device needs after connecting and between requests: the URL's options
    (``pause_after_connect``, ``pause_between_requests``), else the profile's ``limits``."""
    from ..transport.urls import pacing

    lim = profile.limits if profile is not None else None
    after_ms = lim.pause_after_connect if lim else 0
    between_ms = lim.pause_between_requests if lim else 0
    if url is None:
        return Pacing(after_ms / 1000, between_ms / 1000) if after_ms or between_ms else NO_PAUSES
    after, between = pacing(url, after_ms, between_ms)
    return Pacing(after, between) if after or between else NO_PAUSES


def action_steps(kind: StepKind, prof: Profile, actions: Iterable[WriteAction]) -> list[Step]:
    """The profile's own writes (unlock, commit, lock) as steps, in the form the device takes: Function 16, or
    one Function 06 per register where the profile (or what the device taught) says 06; a coil with Function 05
    (a Danfoss FC 102 stores to EEPROM with coil 65). A secret's words are not in the plan (``values`` None):
    the executor takes them from the profile."""
    out: list[Step] = []
    for a in actions:
        values = None if a.secret else a.registers
        if a.is_coil:
            out.append(Step(kind, 5, a.address, 1, values, (), wait=a.wait_ms / 1000, note=a.description))
        elif prof.limits.write_function == 6:
            n = len(a.registers)
            out.extend(
                Step(
                    kind,
                    6,
                    a.address + i,
                    1,
                    None if values is None else (values[i],),
                    (),
                    wait=a.wait_ms / 1000 if i == n - 1 else 0.0,
                    note=a.description,
                )
                for i in range(n)
            )
        else:
            out.append(
                Step(kind, 16, a.address, len(a.registers), values, (), wait=a.wait_ms / 1000, note=a.description)
            )
    return out


def identity_steps(prof: Profile) -> tuple[Step, ...]:
    """The profile's identity checks as steps: each register read and compared (the wrong device: nothing written)."""
    return tuple(
        Step("identity", READ_FUNCTION[c.register_type], c.address, 1, expect=Expect(c.raw), note=c.description)
        for c in prof.identity
    )


def precondition_steps(prof: Profile) -> tuple[Step, ...]:
    """The profile's preconditions as steps, each with its condition ("drive stopped"): read before anything is
    written."""
    return tuple(
        Step("precondition", 3, c.address, 1, expect=Expect(c.equals, c.mask), note=c.description)
        for c in prof.preconditions
    )


def health_steps(prof: Profile) -> tuple[Step, ...]:
    """The profile's health checks as steps: a safe change's reads before it writes."""
    return tuple(Step("health", c.function, c.address, c.count, note=c.what()) for c in prof.health)


def writes_action(a: WriteAction, function: int) -> bool:
    """Whether a request of ``function`` is how the profile's action ``a`` is sent (``action_steps``): Function 05
    for a coil, 06 or 16 for registers. A coil and a register at one address are two places."""
    return function in ((5,) if a.is_coil else (6, 16))


def secret_words(prof: Profile, step: Step) -> tuple[int, ...]:
    """A secret step's words, from the profile's action it was planned from (the same kind, address, count, and
    the function the action is planned with: ``writes_action``)."""
    actions = {"unlock": prof.unlock, "commit": prof.commit, "lock": prof.lock}.get(step.kind, ())
    for a in actions:
        if not writes_action(a, step.function):
            continue
        if a.address <= step.address and step.address + step.count <= a.address + len(a.registers):
            return a.registers[step.address - a.address : step.address - a.address + step.count]
    raise KeyError(f"no {step.kind} action of profile {prof.id} at 0x{step.address:04X}")


def _covered(reads: Sequence[ReadRequest], prof: Profile, names: Sequence[str]) -> list[tuple[str, ...]]:
    """For each read block, the named parameters it holds (a block is found by its first register: bisect)."""
    keys = sorted((read_key(r), i) for i, r in enumerate(reads))
    starts = [k for k, _ in keys]
    out: list[list[str]] = [[] for _ in reads]
    for n in names:
        p = prof.parameter(n)
        j = bisect.bisect_right(starts, p.key) - 1
        if j >= 0:
            k, i = keys[j]
            if p.key + p.count <= k + reads[i].count:
                out[i].append(n)
    return [tuple(x) for x in out]


class Planner:
    """One recipe's plans: the checks every device gets, worked out once, and each device's plan.

    ``device_id``: ask Function 43 (None: as the profile's ``limits.device_identification`` says; the URL and what
    the device taught decide it for an apply); ``commit``: plan the profile's commit (a rollback never commits);
    ``write_all``: every parameter, held or not; ``window``: a safe change's plan (``--soak``, ``--confirm-within``),
    which reads the profile's health checks before the change.
    """

    def __init__(
        self,
        recipe: Recipe,
        *,
        write_all: bool = False,
        device_id: bool | None = None,
        commit: bool = True,
        pacing: Pacing = NO_PAUSES,
        window: bool = False,
    ) -> None:
        prof = recipe.profile
        self.recipe = recipe
        self.write_all = write_all
        self.commit = commit
        self.pacing = pacing
        names = [d.name for d in recipe.desired if d.parameter.readable]
        self.reads = plan_reads(prof, names)
        covered = _covered(self.reads, prof, names)
        checks = list(identity_steps(prof))
        checks += [
            Step("snapshot", r.function, r.address, r.count, (), ps) for r, ps in zip(self.reads, covered, strict=True)
        ]
        if prof.limits.device_identification if device_id is None else device_id:
            checks.append(Step("device-id", DEVICE_ID, 0, 1, note="vendor, product code, revision"))
        src = prof.firmware
        gated = any(d.parameter.firmware is not None for d in recipe.desired)
        if src is not None and src.address is not None and (src.applies is not None or gated):
            checks.append(
                Step("firmware", READ_FUNCTION[src.register_type], src.address, src.count, note=src.describe())
            )
        self.checks: tuple[Step, ...] = tuple(checks)
        self.verify = tuple(
            Step("verify", r.function, r.address, r.count, (), ps) for r, ps in zip(self.reads, covered, strict=True)
        )
        self.preconditions = precondition_steps(prof)
        self.health = health_steps(prof) if window else ()
        self.unlock = tuple(action_steps("unlock", prof, prof.unlock))
        self.commits = tuple(action_steps("commit", prof, prof.commit)) if commit else ()
        self.lock = tuple(action_steps("lock", prof, prof.lock)) if prof.unlock else ()
        self.names = tuple(d.name for d in recipe.desired)
        self._plans: dict[tuple[bool, bool, tuple[tuple[int, ...] | None, ...] | None], Plan] = {}

    def plan(self, target: Target, current: Mapping[str, tuple[int, ...]] | None, *, commit_owed: bool = False) -> Plan:
        """The device's plan against ``current`` (name -> registers it holds; None: not read, an offline plan).

        Devices of this recipe holding the same values get the same plan (only ``target`` differs), made once.
        ``commit_owed``: a retry of a device whose commit failed earlier: with nothing to write, the plan
        still sends the commit (inside unlock and lock)."""
        held = None if current is None else tuple(map(current.get, self.names))
        key = (target.unit != 0, commit_owed, held)
        hit = self._plans.get(key)
        if hit is None:
            if len(self._plans) >= _KEPT:
                self._plans.clear()
            hit = self._plans[key] = self._make(Target("", target.unit, ""), current, commit_owed)
        return replace(hit, device=target)

    def _make(self, target: Target, current: Mapping[str, tuple[int, ...]] | None, commit_owed: bool) -> Plan:
        recipe = self.recipe
        prof = recipe.profile
        broadcast = target.unit == 0
        params, writes = plan_writes(
            recipe.desired, prof.limits, None if broadcast else current, write_all=self.write_all or broadcast
        )
        if broadcast:
            steps = [Step("write", w.function, w.address, w.count, w.registers, w.parameters, w.stage) for w in writes]
        else:
            steps = [*self.checks, *self._changes(prof, writes, commit_owed)]
        return Plan(
            recipe.path,
            target,
            params,
            tuple(steps),
            recipe_name=recipe.name,
            pacing=self.pacing,
            profile_sha256=prof.digest,
        )

    def _changes(self, prof: Profile, writes: Sequence[WriteRequest], commit_owed: bool) -> list[Step]:
        if not writes:
            if commit_owed and self.commits:
                return [*self.unlock, *self.commits, *self.lock]
            return []
        fields = prof.readable_fields()
        out: list[Step] = [*self.preconditions, *self.health, *self.unlock]
        for i, w in enumerate(writes):
            merged = [n for n in w.parameters if n in fields] if fields else []
            if merged:  # the register's other bits as the device holds them right before the write
                out += [
                    Step("read-modify-write", r.function, r.address, r.count, (), tuple(merged))
                    for r in plan_reads(prof, merged)
                ]
            last_of_stage = i + 1 == len(writes) or writes[i + 1].stage != w.stage
            wait = prof.wait_after(w.stage) / 1000 if last_of_stage else 0.0
            out.append(Step("write", w.function, w.address, w.count, w.registers, w.parameters, w.stage, wait))
        out += [*self.verify, *self.commits, *self.lock]
        return out


def make_plan(
    recipe: Recipe,
    target: Target,
    current: Mapping[str, tuple[int, ...]] | None = None,
    *,
    write_all: bool = False,
    device_id: bool | None = None,
    commit: bool = True,
    pacing: Pacing = NO_PAUSES,
    window: bool = False,
) -> Plan:
    """One device's whole plan (``Planner`` for a single device)."""
    return Planner(recipe, write_all=write_all, device_id=device_id, commit=commit, pacing=pacing, window=window).plan(
        target, current
    )
