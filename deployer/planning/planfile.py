"""Saved plans (`plan --out`): JSON to Plan and back, checked against the plan schema."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ..errors import CodecError, Diagnostic, InputError, UsageError
from .model import COIL_WRITES, Plan, PlannedParameter, ReadRequest, Target, WriteRequest
from .wire import wire_stats

if TYPE_CHECKING:
    from ..load.yamlsrc import Source
    from ..recipe.loader import Recipe


# ---- JSON ------------------------------------------------------------------------------------


def plan_to_json(plan: Plan) -> dict[str, Any]:
    """The plan as saved-plan JSON (docs/reference/plan.md).

    Extra keys beyond the base format (readers ignore them; plan_from_json does not need them):
    ``parameters[].stage`` and ``writes[].stage`` (write order), and ``summary`` = wire_stats()
    plus the number of parameters per action.
    """
    actions = {a: sum(1 for p in plan.parameters if p.action == a) for a in ("write", "bridge", "unchanged")}
    return {
        "schema": plan.schema,
        "recipe": plan.recipe,
        "device": {"url": plan.device.url, "unit": plan.device.unit, "profile": plan.device.profile},
        "parameters": [{"name": p.name, "address": p.address, "count": p.count, "desired": p.desired,
                        "desired_raw": list(p.desired_raw),
                        "current_raw": None if p.current_raw is None else list(p.current_raw),
                        "action": p.action, "stage": p.stage,
                        **({"register_type": p.register_type} if p.register_type != "holding" else {})}
                       for p in plan.parameters],
        "writes": [{"function": w.function, "address": w.address, "count": w.count, "registers": list(w.registers),
                    "parameters": list(w.parameters), "stage": w.stage} for w in plan.writes],
        "reads": [{"function": r.function, "address": r.address, "count": r.count} for r in plan.reads],
        "summary": {**wire_stats(plan), **actions},
        **({"recipe_name": plan.recipe_name} if plan.recipe_name is not None else {}),
    }


def plan_from_json(data: Any, path: str = "<plan>", *, src: Source | None = None) -> Plan:
    """A plan back from JSON: the schema first, then consistency, all problems at once (InputError).

    ``src`` (a yamlsrc.Source from yamlsrc.load) gives every problem its FILE:LINE:COL; without
    it problems print as FILE:0:0 with the JSON path in the message. Consistency: each write's
    ``count`` matches its registers, carries exactly the desired values of the parameters it names
    (whole parameters, contiguous, in order; FC06 one word of one parameter), and the actions agree
    with the writes (``write``/``bridge`` written, ``unchanged`` not) — a hand-edited plan can
    not make ``apply`` write a register no parameter names.
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
    errors = schema.validate(data, "plan", source or yamlsrc.Source(path))
    if errors:
        raise InputError(errors if source is not None else [Diagnostic(path, 0, 0, e.message) for e in errors])
    dev = data["device"]
    params = tuple(PlannedParameter(str(p["name"]), int(p["address"]), int(p["count"]), str(p["desired"]),
                                    tuple(int(x) for x in p["desired_raw"]),
                                    None if p.get("current_raw") is None else tuple(int(x) for x in p["current_raw"]),
                                    p["action"], int(p.get("stage", 0)), str(p.get("register_type", "holding")))
                   for p in data["parameters"])
    writes = tuple(WriteRequest(int(w["function"]), int(w["address"]), tuple(int(x) for x in w["registers"]),
                                tuple(str(n) for n in w["parameters"]), int(w.get("stage", 0)))
                   for w in data["writes"])
    reads = tuple(ReadRequest(int(r["address"]), int(r["count"]), int(r.get("function", 3))) for r in data["reads"])
    problems: list[Diagnostic] = []
    by_name: dict[str, PlannedParameter] = {}
    for k, pp in enumerate(params):
        if pp.name in by_name:
            problems.append(error(("parameters", k, "name"), f"{pp.name} is listed twice"))
        by_name[pp.name] = pp
        if len(pp.desired_raw) != pp.count:
            problems.append(error(("parameters", k, "desired_raw"),
                                  f"{pp.name}: {len(pp.desired_raw)} registers for count {pp.count}"))
        if pp.current_raw is not None and len(pp.current_raw) != pp.count:
            problems.append(error(("parameters", k, "current_raw"),
                                  f"{pp.name}: {len(pp.current_raw)} registers for count {pp.count}"))
        if pp.address + pp.count > 0x10000:
            problems.append(error(("parameters", k, "address"), f"{pp.name} runs past register 65535"))
    written: set[str] = set()
    for k, (w, wj) in enumerate(zip(writes, data["writes"], strict=True)):
        if int(wj["count"]) != w.count:
            problems.append(error(("writes", k, "count"), f"count {wj['count']} but {w.count} registers"))
        if w.address + w.count > 0x10000:
            problems.append(error(("writes", k, "address"), "the request runs past register 65535"))
        table = "coil" if w.function in COIL_WRITES else "holding"
        regs: dict[int, int] = {}
        for n in w.parameters:
            pp_ = by_name.get(n)
            if pp_ is None:
                problems.append(error(("writes", k, "parameters"), f"names '{n}', which is not among the parameters"))
                continue
            if pp_.register_type != table:
                problems.append(error(("writes", k, "function"), f"function {w.function} writes {table}s, but {n} "
                                                                 f"is a {pp_.register_type}"))
            written.add(n)
            regs.update({pp_.address + i: v for i, v in enumerate(pp_.desired_raw)})
        if w.function in (5, 6):  # one word of one parameter (one coil)
            ok = w.count == 1 and len(w.parameters) == 1 and regs.get(w.address) == w.registers[0]
        else:  # whole parameters, back to back from the request's address, nothing more
            ok = sorted(regs) == list(range(w.address, w.address + w.count)) and \
                [regs[a] for a in sorted(regs)] == list(w.registers)
        if not ok and all(n in by_name for n in w.parameters):
            problems.append(error(("writes", k, "registers"),
                                  f"the request at {w.address} does not carry exactly the desired values of "
                                  f"{', '.join(w.parameters)}"))
    for k, pp in enumerate(params):
        if (pp.name in written) != (pp.action != "unchanged"):
            problems.append(error(("parameters", k, "action"),
                                  f"{pp.name} is '{pp.action}' but is {'' if pp.name in written else 'not '}"
                                  "in a write request"))
    for k, r in enumerate(reads):
        if r.address + r.count > 0x10000:
            problems.append(error(("reads", k, "address"), "the read runs past register 65535"))
    if problems:
        raise InputError(problems)
    name = data.get("recipe_name")
    return Plan(data.get("recipe"), Target(dev.get("url"), int(dev["unit"]), str(dev["profile"])),
                params, writes, reads, recipe_name=None if name is None else str(name))


def load_plan(path: str) -> tuple[Recipe, Plan]:
    """A saved plan file -> (the recipe it carries, the plan), checked against its profile first."""
    import os

    from ..load import yamlsrc
    from ..profile import resolve_profile
    from ..recipe.loader import Desired, Recipe
    from ..recipe.model import DeviceSpec

    data, src = yamlsrc.load(path)
    p = plan_from_json(data, path, src=src)
    try:
        prof = resolve_profile(p.device.profile)
    except UsageError as e:
        raise InputError([src.error(("device", "profile"), str(e))]) from None
    errors = []
    desired = []
    for i, pp in enumerate(p.parameters):
        param = prof.get(pp.name)
        if param is None or param.address != pp.address or param.count != len(pp.desired_raw) or \
                param.register_type != pp.register_type:
            errors.append(src.error(("parameters", i, "name"),
                                    f"{pp.name} does not match profile {prof.id} (address or size differ)"))
            continue
        if param.is_string:
            try:
                param.text_of(pp.desired_raw)
            except CodecError as e:
                errors.append(src.error(("parameters", i, "desired_raw"), f"{pp.name}: {e}"))
                continue
        raw = None if param.is_string else param.decode(pp.desired_raw)
        bounds = param.raw_bounds()
        if not param.writable or (raw is not None and bounds is not None and not bounds[0] <= raw <= bounds[1]):
            errors.append(src.error(("parameters", i, "desired_raw"),
                                    f"{pp.name}: raw {raw} is not writable within the profile's range"))
            continue
        desired.append(Desired(param, pp.desired, pp.desired_raw))
    if errors:
        raise InputError(errors)
    # named after the recipe it was made from (snapshots, reports), not after the plan file
    name = p.recipe_name or os.path.splitext(os.path.basename(p.recipe or path))[0]
    rec = Recipe(name=name, path=p.recipe, profile=prof, desired=tuple(desired),
                 device=DeviceSpec(p.device.url, p.device.unit), profile_ref=p.device.profile)
    return rec, p
