"""The plan: a plain, serializable value saying exactly which requests apply will send.

``profile + recipe (+ current values) -> Plan``. Pure: no I/O. ``plan --out`` writes it as
JSON (schemas/plan.schema.json) and ``apply PLAN.json`` executes it unchanged.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

from .diagnostics import Diagnostic, InputError, UsageError

if TYPE_CHECKING:
    from .profile import Limits, Profile
    from .recipe import Desired, Recipe

PLAN_SCHEMA = "deployer.plan/1"
Action = Literal["write", "unchanged", "bridge"]


@dataclass(frozen=True)
class Target:
    url: str | None
    unit: int
    profile: str  # built-in id, or the profile file's path


@dataclass(frozen=True)
class PlannedParameter:
    name: str
    address: int
    count: int
    desired: str  # engineering text, "10 s"
    desired_raw: tuple[int, ...]
    current_raw: tuple[int, ...] | None  # None when the device was not read
    action: Action
    stage: int = 0


@dataclass(frozen=True)
class WriteRequest:
    function: int  # 16, or 6 for devices without FC16 (then exactly one register)
    address: int
    registers: tuple[int, ...]
    parameters: tuple[str, ...]
    stage: int = 0

    @property
    def count(self) -> int:
        return len(self.registers)


@dataclass(frozen=True)
class ReadRequest:
    address: int
    count: int
    function: int = 3


@dataclass(frozen=True)
class Plan:
    recipe: str | None
    device: Target
    parameters: tuple[PlannedParameter, ...]
    writes: tuple[WriteRequest, ...]
    reads: tuple[ReadRequest, ...]
    schema: str = PLAN_SCHEMA


# ---- write planning ------------------------------------------------------------------------
#
# Within one stage, parameters split into maximal runs of contiguous registers (p.address ==
# previous end). A request can only cover registers of one run (it may not write a register
# the recipe does not name), so runs are planned independently.
#
# Every parameter known to need writing is "must"; with current values known, the others are
# "optional": they may be rewritten with their (unchanged) value to bridge two must-parameters.
# For a run p[0..n) and L registers per request, an exact dynamic program over positions:
#
#     best[0] = (0, 0)
#     best[i+1] <- best[i]                                  if p[i] is optional (left out)
#     best[j]   <- best[i] + (1, regs(p[i..j)))              for every j with regs(p[i..j)) <= L
#
# where costs compare lexicographically as (requests, registers written). Each request is a
# contiguous slice of whole parameters, so no parameter is ever split, and every way to cover
# the must-parameters is one path through the DP: the result is optimal. It costs O(n * k),
# k = parameters that fit in one request (<= 123).
#
# Without optional parameters this reduces to greedy packing left to right, which is optimal
# by exchange: take any optimal plan; its first request starts at p[0] and ends at or before
# where greedy's first request ends; moving that boundary right to greedy's end shrinks the
# second request without adding any, and induction on the rest gives greedy's count.
# tests/test_planner.py checks both against brute force on random small profiles.

_Cost = tuple[int, int]


def _plan_run(run: Sequence[Desired], must: Sequence[bool], limit: int) -> list[tuple[int, int]]:
    """Slices [i, j) of ``run`` to write, fewest requests then fewest registers."""
    n = len(run)
    if all(must):  # greedy is optimal here (exchange argument above) and O(n)
        slices: list[tuple[int, int]] = []
        start, regs = 0, 0
        for k, d in enumerate(run):
            if regs + d.parameter.count > limit:
                slices.append((start, k))
                start, regs = k, 0
            regs += d.parameter.count
        slices.append((start, n))
        return slices
    inf: _Cost = (1 << 30, 1 << 30)
    best: list[_Cost] = [inf] * (n + 1)
    back: list[tuple[int, bool]] = [(-1, False)] * (n + 1)  # (previous position, wrote a request)
    best[0] = (0, 0)
    for i in range(n):
        if best[i] == inf:
            continue
        if not must[i] and best[i] < best[i + 1]:
            best[i + 1], back[i + 1] = best[i], (i, False)
        regs = 0
        for j in range(i + 1, n + 1):
            regs += run[j - 1].parameter.count
            if regs > limit:
                break
            cost = (best[i][0] + 1, best[i][1] + regs)
            if cost < best[j]:
                best[j], back[j] = cost, (i, True)
    slices = []
    j = n
    while j > 0:
        i, wrote = back[j]
        if wrote:
            slices.append((i, j))
        j = i
    slices.reverse()
    return slices


def plan_writes(desired: Sequence[Desired], limits: Limits, current: Mapping[str, tuple[int, ...]] | None = None,
                *, write_all: bool = False) -> tuple[tuple[PlannedParameter, ...], tuple[WriteRequest, ...]]:
    """The fewest write requests carrying ``desired`` (see the proof above)."""
    limit = limits.write_registers
    ordered = sorted(desired, key=lambda d: (d.parameter.stage, d.parameter.address))
    for d in ordered:
        if limits.write_function == 16 and d.parameter.count > limit:
            raise UsageError(f"{d.name} needs {d.parameter.count} registers in one request, but the device takes "
                             f"at most {limit} per request (limits in the profile)")

    def needs_write(d: Desired) -> bool:
        if write_all or current is None:
            return True
        return current.get(d.name) != tuple(d.registers)

    actions: dict[str, Action] = {d.name: "write" if needs_write(d) else "unchanged" for d in ordered}
    writes: list[WriteRequest] = []
    i = 0
    while i < len(ordered):
        j = i + 1  # a maximal run: same stage, contiguous registers
        while (j < len(ordered) and ordered[j].parameter.stage == ordered[i].parameter.stage
               and ordered[j].parameter.address == ordered[j - 1].parameter.end):
            j += 1
        run = ordered[i:j]
        stage = run[0].parameter.stage
        if limits.write_function == 6:
            # FC06 carries one register: a 32-bit value goes as two requests, upper word first in
            # address order. "Never split" cannot hold on such devices; they latch words themselves.
            for d in run:
                if actions[d.name] == "write":
                    for k, word in enumerate(d.registers):
                        writes.append(WriteRequest(6, d.parameter.address + k, (word,), (d.name,), stage))
        else:
            for a, b in _plan_run(run, [actions[d.name] == "write" for d in run], limit):
                part = run[a:b]
                for d in part:
                    if actions[d.name] == "unchanged":
                        actions[d.name] = "bridge"
                writes.append(WriteRequest(16, part[0].parameter.address,
                                           tuple(w for d in part for w in d.registers),
                                           tuple(d.name for d in part), stage))
        i = j
    params = tuple(
        PlannedParameter(d.name, d.parameter.address, d.parameter.count, d.text, tuple(d.registers),
                         None if current is None or d.name not in current else tuple(current[d.name]),
                         actions[d.name], d.parameter.stage)
        for d in ordered)
    return params, tuple(writes)


# ---- read planning -------------------------------------------------------------------------


def plan_reads(profile: Profile, names: Iterable[str]) -> tuple[ReadRequest, ...]:
    """FC03 blocks covering ``names`` with the fewest requests, spanning declared readable registers only.

    Greedy per run of contiguous readable parameters: open a block at the first parameter still
    to read and stretch it over every needed parameter that fits. A standard interval-covering
    argument makes this optimal (no block can start earlier and still cover that parameter).
    """
    wanted = set(names)
    limit = profile.limits.read_registers
    reads: list[ReadRequest] = []
    params = [p for p in profile.parameters if p.readable]
    i = 0
    while i < len(params):
        j = i + 1
        while j < len(params) and params[j].address == params[j - 1].end:
            j += 1
        start: int | None = None
        end = 0
        for p in params[i:j]:
            if p.name not in wanted:
                continue
            if p.count > limit:
                raise UsageError(f"{p.name} needs {p.count} registers, the device reads at most {limit} at once")
            if start is not None and p.end - start <= limit:
                end = p.end
                continue
            if start is not None:
                reads.append(ReadRequest(start, end - start))
            start, end = p.address, p.end
        if start is not None:
            reads.append(ReadRequest(start, end - start))
        i = j
    missing = wanted - {p.name for p in params}
    if missing:
        raise UsageError(f"not readable in profile {profile.id}: {', '.join(sorted(missing))}")
    return tuple(reads)


def make_plan(recipe: Recipe, target: Target, current: Mapping[str, tuple[int, ...]] | None = None,
              *, write_all: bool = False) -> Plan:
    prof = recipe.profile
    params, writes = plan_writes(recipe.desired, prof.limits, current, write_all=write_all)
    reads = plan_reads(prof, [d.name for d in recipe.desired if d.parameter.readable])
    return Plan(recipe.path, target, params, writes, reads)


# ---- JSON ------------------------------------------------------------------------------------


def plan_to_json(plan: Plan) -> dict[str, Any]:
    """The plan as DESIGN.md's "Plan JSON" (parameters also carry their stage)."""
    return {
        "schema": plan.schema,
        "recipe": plan.recipe,
        "device": {"url": plan.device.url, "unit": plan.device.unit, "profile": plan.device.profile},
        "parameters": [{"name": p.name, "address": p.address, "count": p.count, "desired": p.desired,
                        "desired_raw": list(p.desired_raw),
                        "current_raw": None if p.current_raw is None else list(p.current_raw),
                        "action": p.action, "stage": p.stage} for p in plan.parameters],
        "writes": [{"function": w.function, "address": w.address, "count": w.count, "registers": list(w.registers),
                    "parameters": list(w.parameters), "stage": w.stage} for w in plan.writes],
        "reads": [{"function": r.function, "address": r.address, "count": r.count} for r in plan.reads],
    }


def plan_from_json(data: Any, path: str = "<plan>") -> Plan:
    """A plan back from JSON: schema first, then consistency (writes carry the desired values)."""
    from . import yamlsrc

    src = yamlsrc.Source(path)
    if not isinstance(data, dict):
        raise InputError([Diagnostic(path, 1, 1, "a plan must be a JSON object")])
    errors = yamlsrc.validate(data, "plan", src)
    if errors:
        raise InputError(errors)
    dev = data["device"]
    params = tuple(PlannedParameter(p["name"], int(p["address"]), int(p["count"]), p["desired"],
                                    tuple(int(x) for x in p["desired_raw"]),
                                    None if p.get("current_raw") is None else tuple(int(x) for x in p["current_raw"]),
                                    p["action"], int(p.get("stage", 0))) for p in data["parameters"])
    writes = tuple(WriteRequest(int(w["function"]), int(w["address"]), tuple(int(x) for x in w["registers"]),
                                tuple(w["parameters"]), int(w.get("stage", 0))) for w in data["writes"])
    reads = tuple(ReadRequest(int(r["address"]), int(r["count"]), int(r.get("function", 3))) for r in data["reads"])
    problems: list[str] = []
    by_name = {p.name: p for p in params}
    for k, w in enumerate(writes):
        regs: dict[int, int] = {}
        for n in w.parameters:
            pp = by_name.get(n)
            if pp is None:
                problems.append(f"writes[{k}] names '{n}', which is not among the parameters")
                continue
            regs.update({pp.address + i: v for i, v in enumerate(pp.desired_raw)})
        if [regs.get(w.address + i) for i in range(w.count)] != list(w.registers):
            problems.append(f"writes[{k}] at {w.address} does not carry exactly the desired values of "
                            f"{', '.join(w.parameters)}")
    if problems:
        raise InputError([Diagnostic(path, 1, 1, m) for m in problems])
    return Plan(data.get("recipe"), Target(dev.get("url"), int(dev["unit"]), dev["profile"]), params, writes, reads)


def load_plan(path: str) -> tuple[Recipe, Plan]:
    """A saved plan file -> (the recipe it carries, the plan), checked against its profile first."""
    import os

    from . import yamlsrc
    from .profile import resolve_profile
    from .recipe import Desired, DeviceSpec, Recipe

    data, src = yamlsrc.load(path)
    p = plan_from_json(data, path)
    try:
        prof = resolve_profile(p.device.profile)
    except UsageError as e:
        raise InputError([src.error(("device", "profile"), str(e))]) from None
    errors = []
    desired = []
    for i, pp in enumerate(p.parameters):
        param = prof.get(pp.name)
        if param is None or param.address != pp.address or param.count != len(pp.desired_raw):
            errors.append(src.error(("parameters", i, "name"),
                                    f"{pp.name} does not match profile {prof.id} (address or size differ)"))
            continue
        raw = param.decode(pp.desired_raw)
        bounds = param.raw_bounds()
        if not param.writable or (bounds is not None and not bounds[0] <= raw <= bounds[1]):
            errors.append(src.error(("parameters", i, "desired_raw"),
                                    f"{pp.name}: raw {raw} is not writable within the profile's range"))
            continue
        desired.append(Desired(param, pp.desired, pp.desired_raw))
    if errors:
        raise InputError(errors)
    rec = Recipe(name=os.path.basename(p.recipe or path), path=p.recipe, profile=prof, desired=tuple(desired),
                 device=DeviceSpec(p.device.url, p.device.unit), profile_ref=p.device.profile)
    return rec, p


# ---- cost on the wire --------------------------------------------------------------------------


def wire_stats(plan: Plan, baud: int = 19200) -> dict[str, Any]:
    """Bytes and line time of the write requests and their answers on an RTU line (8E1)."""
    frames = 0
    total = 0
    for w in plan.writes:
        if w.function == 6:
            total += 8 + 8
        else:
            total += (9 + 2 * w.count) + 8
        frames += 2
    char = 11 / baud  # start + 8 data + parity + stop
    return {"requests": len(plan.writes), "registers": sum(w.count for w in plan.writes), "rtu_bytes": total,
            "seconds_19200": round(total * char + frames * 3.5 * char, 6)}
