"""Saved plans (`plan --out`): JSON to Plan and back, checked against the plan schema and the profile."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ..errors import CodecError, Diagnostic, InputError, UsageError
from .model import (
    COIL_WRITES,
    MOST_PER_REQUEST,
    OLD_SCHEMAS,
    STEP_KINDS,
    Expect,
    Pacing,
    Plan,
    PlannedParameter,
    Step,
    Target,
)
from .model import plan_to_json as plan_to_json  # where saved plans are read and written: its other half

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from ..load.yamlsrc import Path_, Source
    from ..profile import Profile
    from ..recipe.loader import Recipe


# ---- JSON ------------------------------------------------------------------------------------


def _step(d: dict[str, Any]) -> Step:
    values = d.get("values", ())
    e = d.get("expect")
    return Step(
        d["kind"],
        int(d["function"]),
        int(d["address"]),
        int(d["count"]),
        None if values is None else tuple(int(x) for x in values),
        tuple(str(n) for n in d.get("parameters", ())),
        int(d.get("stage", 0)),
        float(d.get("wait", 0)),
        None if e is None else Expect(int(e["equals"]), int(e.get("mask", 0xFFFF))),
        str(d.get("note", "")),
    )


# the place of each kind in a plan: reads before a bit-field write share the writes' place
_RANK = {k: i for i, k in enumerate(STEP_KINDS)}
_RANK["read-modify-write"] = _RANK["write"]


def plan_from_json(data: Any, path: str = "<plan>", *, src: Source | None = None) -> Plan:
    """A plan back from JSON: the schema first, then consistency, all problems at once (InputError).

    ``src`` (a yamlsrc.Source from yamlsrc.load) gives every problem its FILE:LINE:COL; without it problems
    print as FILE:0:0 with the JSON path in the message. Consistency: each write step carries exactly the
    desired values of the parameters it names (whole parameters, contiguous, in order; FC06 one word of one
    parameter), the actions agree with the writes (``write``/``bridge`` written, ``unchanged`` not), reads carry
    no values, and the kinds keep their order: a hand-edited plan cannot make ``apply`` write a register no
    parameter names, nor write before the identity check.
    """
    from ..load import schema, yamlsrc

    source = src

    def error(at: yamlsrc.Path_, message: str) -> Diagnostic:
        if source is not None:
            return source.error(at, message)
        where = "".join(f"[{x}]" if isinstance(x, int) else f".{x}" for x in at).lstrip(".")
        return Diagnostic(path, 0, 0, f"{where}: {message}" if where else message)

    if not isinstance(data, dict):
        raise InputError([error((), "a plan must be a JSON object")])
    if data.get("schema") in OLD_SCHEMAS:
        again = f"deployer plan {data.get('recipe') or 'RECIPE'}"
        url = data.get("device", {}).get("url") if isinstance(data.get("device"), dict) else None
        again += f" --device {url}" if isinstance(url, str) else ""
        raise InputError(
            [
                error(
                    ("schema",),
                    f"this plan was made by an older deployer ({data['schema']}), whose "
                    "plans did not list every step apply takes; make it again with: "
                    f"{again} --out {path}",
                )
            ]
        )
    errors = schema.validate(data, "plan", source or yamlsrc.Source(path))
    if errors:
        raise InputError(errors if source is not None else [Diagnostic(path, 0, 0, e.message) for e in errors])
    dev = data["device"]
    params = tuple(
        PlannedParameter(
            str(p["name"]),
            int(p["address"]),
            int(p["count"]),
            str(p["desired"]),
            tuple(int(x) for x in p["desired_raw"]),
            None if p.get("current_raw") is None else tuple(int(x) for x in p["current_raw"]),
            p["action"],
            int(p.get("stage", 0)),
            str(p.get("register_type", "holding")),
        )
        for p in data["parameters"]
    )
    steps = tuple(_step(d) for d in data["steps"])
    problems = _check_parameters(params, error)
    problems += _check_steps(steps, [("values" in d) for d in data["steps"]], params, error)
    if problems:
        raise InputError(problems)
    name = data.get("recipe_name")
    pacing = data.get("pacing") or {}
    return Plan(
        data.get("recipe"),
        Target(dev.get("url"), int(dev["unit"]), str(dev["profile"])),
        params,
        steps,
        recipe_name=None if name is None else str(name),
        pacing=Pacing(float(pacing.get("after_connect", 0)), float(pacing.get("between_requests", 0))),
        profile_sha256=data.get("profile_sha256"),
    )


def _check_parameters(params: tuple[PlannedParameter, ...], error: Any) -> list[Diagnostic]:
    problems: list[Diagnostic] = []
    seen: set[str] = set()
    for k, pp in enumerate(params):
        if pp.name in seen:
            problems.append(error(("parameters", k, "name"), f"{pp.name} is listed twice"))
        seen.add(pp.name)
        if len(pp.desired_raw) != pp.count:
            problems.append(
                error(
                    ("parameters", k, "desired_raw"), f"{pp.name}: {len(pp.desired_raw)} registers for count {pp.count}"
                )
            )
        if pp.current_raw is not None and len(pp.current_raw) != pp.count:
            problems.append(
                error(
                    ("parameters", k, "current_raw"), f"{pp.name}: {len(pp.current_raw)} registers for count {pp.count}"
                )
            )
        if pp.address + pp.count > 0x10000:
            problems.append(error(("parameters", k, "address"), f"{pp.name} runs past register 65535"))
    return problems


def _check_steps(
    steps: tuple[Step, ...], valued: list[bool], params: tuple[PlannedParameter, ...], error: Any
) -> list[Diagnostic]:
    """Every write carries exactly what its parameters desire, reads write nothing, the kinds keep their order."""
    by_name = {pp.name: pp for pp in params}
    problems: list[Diagnostic] = []
    written: set[str] = set()
    rank = -1
    for k, s in enumerate(steps):
        at = ("steps", k)
        if _RANK[s.kind] < rank:
            problems.append(
                error(
                    (*at, "kind"),
                    f"{_a(s.kind)} step after a later kind of step: steps keep the order {', '.join(STEP_KINDS)}",
                )
            )
        rank = max(rank, _RANK[s.kind])
        if s.address + s.count > 0x10000:
            problems.append(error((*at, "address"), "the request runs past register 65535"))
        most = MOST_PER_REQUEST.get(s.function)
        if most is not None and s.count > most:  # the device would refuse it, and pymodbus will not encode it
            problems.append(error((*at, "count"), f"function {s.function} carries at most {most} in one request"))
        writes = s.kind in ("unlock", "write", "commit", "lock")
        if writes != s.writes:
            problems.append(error((*at, "function"), f"function {s.function} does not fit {_a(s.kind)} step"))
            continue
        if (s.kind == "device-id") != (s.function == 43):
            problems.append(error((*at, "function"), f"function {s.function} does not fit {_a(s.kind)} step"))
        if not writes and valued[k]:
            problems.append(error((*at, "values"), f"{_a(s.kind)} step reads: it carries no values"))
        if (s.expect is not None and s.kind not in ("identity", "precondition")) or (
            s.expect is None and s.kind in ("identity", "precondition")
        ):
            problems.append(error((*at, "expect"), "only identity and precondition steps (all of them) expect a value"))
        if s.writes and s.values is not None and len(s.values) != s.count:
            problems.append(error((*at, "values"), f"count {s.count} but {len(s.values)} values"))
            continue
        if s.kind == "write":
            problems += _check_write(s, by_name, written, at, error)
        elif s.kind in ("unlock", "commit", "lock") and s.parameters:
            problems.append(error((*at, "parameters"), f"{_a(s.kind)} step writes the profile's action, no parameter"))
    for k, pp in enumerate(params):
        if (pp.name in written) != (pp.action != "unchanged"):
            problems.append(
                error(
                    ("parameters", k, "action"),
                    f"{pp.name} is '{pp.action}' but is {'' if pp.name in written else 'not '}in a write step",
                )
            )
    return problems


def _a(kind: str) -> str:
    return f"an {kind}" if kind[0] in "aeiou" else f"a {kind}"


def _check_write(
    s: Step, by_name: dict[str, PlannedParameter], written: set[str], at: tuple[Any, ...], error: Any
) -> list[Diagnostic]:
    problems: list[Diagnostic] = []
    if s.values is None:
        return [error((*at, "values"), "a write step's values are the recipe's: never secret")]
    if not s.parameters:
        return [error((*at, "parameters"), "a write step names the parameters it carries")]
    table = "coil" if s.function in COIL_WRITES else "holding"
    regs: dict[int, int] = {}
    for n in s.parameters:
        pp = by_name.get(n)
        if pp is None:
            problems.append(error((*at, "parameters"), f"names '{n}', which is not among the parameters"))
            continue
        if pp.register_type != table:
            problems.append(
                error((*at, "function"), f"function {s.function} writes {table}s, but {n} is a {pp.register_type}")
            )
        written.add(n)
        regs.update({pp.address + i: v for i, v in enumerate(pp.desired_raw)})
    if s.function in (5, 6):  # one word of one parameter (one coil), or the one word its bit fields share
        ok = (
            s.count == 1 and regs.get(s.address) == s.values[0] and (len(s.parameters) == 1 or set(regs) == {s.address})
        )
    else:  # whole parameters, back to back from the request's address, nothing more
        ok = sorted(regs) == list(range(s.address, s.address + s.count)) and [regs[a] for a in sorted(regs)] == list(
            s.values
        )
    if not ok and all(n in by_name for n in s.parameters):
        problems.append(
            error(
                (*at, "values"),
                f"the request at {s.address} does not carry exactly the desired values of {', '.join(s.parameters)}",
            )
        )
    return problems


def check_actions(plan: Plan, prof: Profile) -> list[str]:
    """The plan's unlock, commit and lock steps that are not the profile's own actions (words and places)."""
    from .steps import secret_words

    wrong = []
    for i, s in enumerate(plan.steps, 1):
        if s.kind not in ("unlock", "commit", "lock"):
            continue
        try:
            words = secret_words(prof, s)
        except KeyError:
            wrong.append(f"step {i} ({s.kind} at 0x{s.address:04X}) is no {s.kind} action of profile {prof.id}")
            continue
        if s.values is not None and s.values != words:
            wrong.append(
                f"step {i} ({s.kind} at 0x{s.address:04X}) writes other words than profile {prof.id}'s {s.kind}"
            )
        elif s.values is None and not _secret_at(prof, s):
            wrong.append(f"step {i} ({s.kind} at 0x{s.address:04X}) hides words the profile does not keep secret")
    return wrong


def _secret_at(prof: Profile, s: Step) -> bool:
    from .steps import writes_action

    actions = {"unlock": prof.unlock, "commit": prof.commit, "lock": prof.lock}[s.kind]
    return any(
        a.secret and writes_action(a, s.function) and a.address <= s.address < a.address + len(a.registers)
        for a in actions
    )


def check_guards(plan: Plan, prof: Profile) -> list[str]:
    """The plan's identity, precondition and health steps that are not the profile's (a saved plan edited or made
    for another profile): they keep a device of another type, a running drive or a failing one from being written,
    so a plan runs only with every one of them, each as the profile has it. A broadcast reads nothing."""
    from .steps import health_steps, identity_steps, precondition_steps

    if plan.device.unit == 0:
        return []

    def said(steps: Sequence[Step]) -> list[tuple[int, int, int, Expect | None]]:
        return [(s.function, s.address, s.count, s.expect) for s in steps]

    def of(kind: str) -> list[Step]:
        return [s for s in plan.steps if s.kind == kind]

    writes = any(s.kind == "write" for s in plan.steps)
    wanted = (
        ("identity", identity_steps(prof), "its identity checks"),
        ("precondition", precondition_steps(prof) if writes else (), "its preconditions (before a write)"),
        ("health", health_steps(prof) if of("health") else (), "its health checks"),
    )
    return [
        f"the plan's {kind} steps are not profile {prof.id}'s: a plan checks {what}, each as the profile has it "
        "(make the plan again)"
        for kind, steps, what in wanted
        if said(of(kind)) != said(steps)
    ]


def load_plan(path: str) -> tuple[Recipe, Plan]:
    """A saved plan file -> (the recipe it carries, the plan), checked against its profile first (``plan_recipe``),
    every problem at its position in the file."""
    from ..load import yamlsrc

    data, src = yamlsrc.load(path)
    p = plan_from_json(data, path, src=src)
    return plan_recipe(p, path, src.error), p


def plan_recipe(p: Plan, path: str = "<plan>", error: Callable[[Path_, str], Diagnostic] | None = None) -> Recipe:
    """The recipe a plan carries, for executing it: its parameters must be the profile's (writable, in range),
    its action steps the profile's actions, and the profile's text the one the plan was made with. ``path`` and
    ``error``: where problems are said (a saved plan's positions; without ``error``, FILE:0:0 and the JSON path).

    Raises InputError with every problem."""
    import os

    from ..profile import resolve_profile
    from ..recipe.loader import Desired, Recipe
    from ..recipe.model import DeviceSpec

    def at(where: Path_, message: str) -> Diagnostic:
        if error is not None:
            return error(where, message)
        return Diagnostic(path, 0, 0, f"{'.'.join(str(x) for x in where)}: {message}")

    try:
        prof = resolve_profile(p.device.profile)
    except UsageError as e:
        raise InputError([at(("device", "profile"), str(e))]) from None
    errors = []
    if p.profile_sha256 != prof.digest:
        errors.append(
            at(
                ("profile_sha256",),
                f"profile {prof.id} changed since the plan was made ({prof.source or 'built-in'}): make the plan again",
            )
        )
    errors += [at(("steps",), why) for why in check_actions(p, prof) + check_guards(p, prof)]
    desired = []
    for i, pp in enumerate(p.parameters):
        param = prof.get(pp.name)
        if (
            param is None
            or param.address != pp.address
            or param.count != len(pp.desired_raw)
            or param.register_type != pp.register_type
        ):
            errors.append(
                at(("parameters", i, "name"), f"{pp.name} does not match profile {prof.id} (address or size differ)")
            )
            continue
        if param.is_string:
            try:
                param.text_of(pp.desired_raw)
            except CodecError as e:
                errors.append(at(("parameters", i, "desired_raw"), f"{pp.name}: {e}"))
                continue
        raw = None if param.is_string else param.decode(pp.desired_raw)
        bounds = param.raw_bounds()
        if not param.writable or (raw is not None and bounds is not None and not bounds[0] <= raw <= bounds[1]):
            errors.append(
                at(("parameters", i, "desired_raw"), f"{pp.name}: raw {raw} is not writable within the profile's range")
            )
            continue
        desired.append(Desired(param, pp.desired, pp.desired_raw))
    if errors:
        raise InputError(errors)
    # named after the recipe it was made from (snapshots, reports), not after the plan file
    name = p.recipe_name or os.path.splitext(os.path.basename(p.recipe or path))[0]
    return Recipe(
        name=name,
        path=p.recipe,
        profile=prof,
        desired=tuple(desired),
        device=DeviceSpec(p.device.url, p.device.unit),
        profile_ref=p.device.profile,
    )
