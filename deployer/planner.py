"""The plan: a plain, serializable value saying exactly which requests apply will send.

``profile + recipe (+ current values) -> Plan``. Pure: no I/O. ``plan --out`` writes it as
JSON (schemas/plan.schema.json) and ``apply PLAN.json`` executes it unchanged.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

from . import codec
from .diagnostics import Diagnostic, InputError, UsageError

if TYPE_CHECKING:
    from .profile import Limits, Parameter, Profile
    from .recipe import Desired, Recipe
    from .yamlsrc import Source

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
    recipe_name: str | None = None  # the recipe's own name: snapshots of 'apply PLAN.json' are named after it


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
# k = parameters that fit in one request (<= 123): the inner loop stops once the slice passes L.
# (Requests only start and end on must-parameters: see _plan_run.)
#
# Without optional parameters (no current values, or --write-all) the DP reduces to greedy
# packing left to right, O(n). Proof that greedy is optimal ("greedy stays ahead", an exchange
# argument): let any valid plan cut the run into requests ending at o1 < o2 < ... < om, greedy's
# at g1 < g2 < .... Greedy's first request is the longest prefix of whole parameters that fits
# in L, so g1 >= o1. If g(i-1) >= o(i-1), the plan's i-th request [o(i-1), oi) fits in L, so
# its sub-slice [g(i-1), oi) fits too, and greedy, taking the longest slice that fits from
# g(i-1), ends at gi >= oi. So greedy has covered the run after at most m requests: no plan
# needs fewer. All registers are written either way, so the register count ties.
# tests/test_planner.py checks both against brute force on random small profiles.

_REQUEST = 1 << 40  # cost = requests * _REQUEST + registers: one int compares like (requests, registers)


def _plan_run(sizes: Sequence[int], must: Sequence[bool], limit: int) -> list[tuple[int, int]]:
    """Slices [i, j) of a run (parameter sizes in registers) to write: fewest requests, then registers."""
    n = len(sizes)
    if all(must):  # greedy is optimal here (exchange argument above) and O(n)
        slices: list[tuple[int, int]] = []
        start, regs = 0, 0
        for k, size in enumerate(sizes):
            if regs + size > limit:
                slices.append((start, k))
                start, regs = k, 0
            regs += size
        slices.append((start, n))
        return slices
    if not any(must):
        return []
    # An optimal plan never starts or ends a request on an optional parameter: trimming it keeps
    # the request count and writes fewer registers. So requests run from a must-parameter i to a
    # must-parameter j-1; every other position is only "skip". Same optimum, far fewer candidates.
    pre = [0] * (n + 1)  # prefix sums: registers of run[i:j] = pre[j] - pre[i]
    for k, size in enumerate(sizes):
        pre[k + 1] = pre[k] + size
    inf = 1 << 62
    best = [inf] * (n + 1)
    back = [-1] * (n + 1)  # previous position; negative -(i + 1) marks "skipped run[i]", no request
    best[0] = 0
    for i in range(n):
        here = best[i]
        if here == inf:
            continue
        if not must[i]:
            if here < best[i + 1]:
                best[i + 1], back[i + 1] = here, -(i + 1)
            continue
        base = here + _REQUEST - pre[i]
        for j in range(i + 1, n + 1):
            if pre[j] - pre[i] > limit:
                break
            if must[j - 1]:
                cost = base + pre[j]
                if cost < best[j]:
                    best[j], back[j] = cost, i
    slices = []
    j = n
    while j > 0:
        i = back[j]
        if i < 0:
            j = -i - 1
        else:
            slices.append((i, j))
            j = i
    slices.reverse()
    return slices


def merge_fields(fields: Sequence[Parameter], bits: Sequence[int], current: int | None) -> int:
    """One register's word: the fields' new bits over what the device holds (0 where unknown)."""
    mask = 0
    word = 0
    for p, b in zip(fields, bits, strict=True):
        mask |= p.mask
        word |= b & p.mask
    return ((current or 0) & ~mask & 0xFFFF) | word


def plan_writes(desired: Sequence[Desired], limits: Limits, current: Mapping[str, tuple[int, ...]] | None = None,
                *, write_all: bool = False) -> tuple[tuple[PlannedParameter, ...], tuple[WriteRequest, ...]]:
    """The fewest write requests carrying ``desired`` (see the proof above).

    ``current``: parameter name -> registers the device holds; a missing name (or None for all)
    means unknown, so that parameter is written. Returns the parameters in write order (stage,
    address) with their action, and the requests in the order to send them.
    """
    limit = limits.write_registers
    fc6 = limits.write_function == 6
    ordered = sorted(desired, key=lambda d: (d.parameter.stage, d.parameter.address))
    # attributes read once into flat lists: properties cost more than the planning itself at 1M
    params_ = [d.parameter for d in ordered]
    names = [p.name for p in params_]
    addrs = [p.address for p in params_]
    sizes = [p.count for p in params_]
    stages = [p.stage for p in params_]
    regs = [tuple(d.registers) for d in ordered]
    n = len(ordered)
    # Bit fields of one register form one unit: one merged word, written or left together. Units are
    # slices of ``ordered``: unit u is params bounds[u]:bounds[u + 1] (one parameter each without fields).
    fields = any(p.mask for p in params_)
    bounds: Sequence[int] = range(n + 1)
    if fields:
        bounds = [0, *(k for k in range(1, n) if not (params_[k].mask and params_[k - 1].mask
                                                       and addrs[k] == addrs[k - 1] and stages[k] == stages[k - 1])), n]
    nu = len(bounds) - 1
    for u in range(nu):
        k = bounds[u]
        if not fc6 and sizes[k] > limit:
            raise UsageError(f"{names[k]} needs {sizes[k]} registers in one request, but the device takes "
                             f"at most {limit} per request (limits in the profile)")
        for m in range(k, bounds[u + 1]):
            if len(regs[m]) != sizes[m]:
                raise UsageError(f"{names[m]}: {len(regs[m])} register values for a {sizes[m]}-register parameter")
        # two values for one register would make the plan's outcome depend on request order
        h = k - 1
        if u and stages[h] == stages[k] and addrs[k] < addrs[h] + sizes[h]:
            raise UsageError(f"{names[k]} overlaps {names[h]} (registers {addrs[k]} and "
                             f"{addrs[h]}..{addrs[h] + sizes[h] - 1}): each register may be planned once")

    if write_all or current is None:
        must_p = [True] * n
    elif fields:
        must_p = [not params_[k].same_value(current.get(names[k]), regs[k]) for k in range(n)]
    else:
        must_p = [current.get(names[k]) != regs[k] for k in range(n)]
    must = must_p
    if fields:
        for u in range(nu):
            lo, hi = bounds[u], bounds[u + 1]
            if params_[lo].mask:
                known = None if current is None else next((current[names[k]][0] for k in range(lo, hi)
                                                            if names[k] in current), None)
                merged = (merge_fields(params_[lo:hi], [regs[k][0] for k in range(lo, hi)], known),)
                for k in range(lo, hi):
                    regs[k] = merged
        must = [any(must_p[bounds[u]:bounds[u + 1]]) for u in range(nu)]
    actions: list[Action] = ["write" if m else "unchanged" for m in must_p]
    writes: list[WriteRequest] = []
    i = 0
    while i < nu:
        j = i + 1  # a maximal run of units: same stage, contiguous registers
        while j < nu and stages[bounds[j]] == stages[bounds[i]] and \
                addrs[bounds[j]] == addrs[bounds[j - 1]] + sizes[bounds[j - 1]]:
            j += 1
        stage = stages[bounds[i]]
        if fc6:
            # FC06 carries one register, so the "never split" rule cannot hold on such devices: a
            # 2/4-register value goes as one FC06 per word, in ascending address order (the word at
            # the lower address first, whatever the word order), the words of one parameter back to
            # back with nothing in between. No bridges: one request per register saves nothing.
            for u in range(i, j):
                if must[u]:
                    k = bounds[u]
                    writes.extend(WriteRequest(6, addrs[k] + w, (word,), tuple(names[k:bounds[u + 1]]), stage)
                                  for w, word in enumerate(regs[k]))
                    for m in range(k, bounds[u + 1]):
                        if not must_p[m]:
                            actions[m] = "bridge"
        else:
            sizes_u = sizes[i:j] if not fields else [sizes[bounds[u]] for u in range(i, j)]
            for a, b in _plan_run(sizes_u, must[i:j], limit):
                lo, hi = bounds[i + a], bounds[i + b]
                for k in range(lo, hi):
                    if not must_p[k]:
                        actions[k] = "bridge"
                words = tuple(w for u in range(i + a, i + b) for w in regs[bounds[u]])
                writes.append(WriteRequest(16, addrs[lo], words, tuple(names[lo:hi]), stage))
        i = j
    planned = tuple(
        PlannedParameter(names[k], addrs[k], sizes[k], ordered[k].text, regs[k],
                         None if current is None or names[k] not in current else tuple(current[names[k]]),
                         actions[k], stages[k])
        for k in range(n))
    return planned, tuple(writes)


# ---- read planning -------------------------------------------------------------------------


def plan_reads(profile: Profile, names: Iterable[str], *, gaps: bool = True) -> tuple[ReadRequest, ...]:
    """FC03 blocks covering ``names`` with the fewest requests, spanning declared readable registers only.

    A block may only span a maximal run of contiguous declared readable registers (reading an
    undeclared gap or a write-only register can fail the whole read), may cover parameters the
    caller did not ask for, and never cuts a parameter. With the profile's ``max_read_gap`` N > 0
    (and ``gaps``), a run also continues across at most N consecutive undeclared registers (never
    across a declared write-only one): the device answers them, the values are ignored. Greedy per
    run: open a block at the first parameter still to read and stretch it over every needed
    parameter that still fits. Optimal by the interval-covering argument: any cover has a block
    containing that first parameter, which can start no earlier, so it reaches no further than
    greedy's block; induction on the rest. tests/test_planner.py checks it against every partition
    of the needed parameters.
    """
    wanted = set(names)
    limit = profile.limits.read_registers
    max_gap = profile.limits.max_read_gap if gaps else 0
    reads: list[ReadRequest] = []
    # profiles built in code need not be sorted; loaded ones are (cheap to be sure)
    params = sorted((p for p in profile.parameters if p.readable), key=lambda p: p.address)
    missing = wanted - {p.name for p in params}
    if missing:
        raise UsageError(f"not readable in profile {profile.id}: {', '.join(sorted(missing))}")
    barriers: list[int] = []  # start addresses of write-only parameters: a read never spans them
    if max_gap:
        barriers = sorted(p.address for p in profile.parameters if not p.readable)

    def joins(prev: Parameter, nxt: Parameter) -> bool:
        if nxt.address in (prev.end, prev.address):  # adjacent, or bit fields sharing one register
            return True
        if nxt.address - prev.end > max_gap:
            return False
        k = bisect.bisect_left(barriers, prev.end)
        return k == len(barriers) or barriers[k] >= nxt.address

    i = 0
    while i < len(params):
        j = i + 1
        while j < len(params) and joins(params[j - 1], params[j]):
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
    return tuple(reads)


def gap_free_reads(profile: Profile, reads: Sequence[ReadRequest]) -> tuple[ReadRequest, ...]:
    """The blocks that replace ``reads`` on a device that refuses reads across gaps (DESIGN rule 5)."""
    spans = sorted((r.address, r.address + r.count) for r in reads)
    starts = [a for a, _ in spans]
    inside = []
    for p in profile.parameters:
        k = bisect.bisect_right(starts, p.address) - 1
        if p.readable and k >= 0 and p.end <= spans[k][1]:
            inside.append(p.name)
    return plan_reads(profile, inside, gaps=False)


def make_plan(recipe: Recipe, target: Target, current: Mapping[str, tuple[int, ...]] | None = None,
              *, write_all: bool = False) -> Plan:
    """The whole plan; reads cover every readable recipe parameter (snapshot before, read-back after)."""
    prof = recipe.profile
    params, writes = plan_writes(recipe.desired, prof.limits, current, write_all=write_all)
    reads = plan_reads(prof, [d.name for d in recipe.desired if d.parameter.readable])
    return Plan(recipe.path, target, params, writes, reads, recipe_name=recipe.name)


# ---- JSON ------------------------------------------------------------------------------------


def plan_to_json(plan: Plan) -> dict[str, Any]:
    """The plan as DESIGN.md's "Plan JSON".

    Extra keys beyond DESIGN.md (readers ignore them; plan_from_json does not need them):
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
                        "action": p.action, "stage": p.stage} for p in plan.parameters],
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
    from . import yamlsrc

    source = src

    def error(at: yamlsrc.Path_, message: str) -> Diagnostic:
        if source is not None:
            return source.error(at, message)
        where = "".join(f"[{x}]" if isinstance(x, int) else f".{x}" for x in at).lstrip(".")
        return Diagnostic(path, 0, 0, f"{where}: {message}" if where else message)

    if not isinstance(data, dict):
        raise InputError([error((), "a plan must be a JSON object")])
    errors = yamlsrc.validate(data, "plan", source or yamlsrc.Source(path))
    if errors:
        raise InputError(errors if source is not None else [Diagnostic(path, 0, 0, e.message) for e in errors])
    dev = data["device"]
    params = tuple(PlannedParameter(str(p["name"]), int(p["address"]), int(p["count"]), str(p["desired"]),
                                    tuple(int(x) for x in p["desired_raw"]),
                                    None if p.get("current_raw") is None else tuple(int(x) for x in p["current_raw"]),
                                    p["action"], int(p.get("stage", 0))) for p in data["parameters"])
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
        regs: dict[int, int] = {}
        for n in w.parameters:
            pp_ = by_name.get(n)
            if pp_ is None:
                problems.append(error(("writes", k, "parameters"), f"names '{n}', which is not among the parameters"))
                continue
            written.add(n)
            regs.update({pp_.address + i: v for i, v in enumerate(pp_.desired_raw)})
        if w.function == 6:  # one word of one parameter
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

    from . import yamlsrc
    from .profile import resolve_profile
    from .recipe import Desired, DeviceSpec, Recipe

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
        if param is None or param.address != pp.address or param.count != len(pp.desired_raw):
            errors.append(src.error(("parameters", i, "name"),
                                    f"{pp.name} does not match profile {prof.id} (address or size differ)"))
            continue
        if param.is_string:
            try:
                param.text_of(pp.desired_raw)
            except codec.CodecError as e:
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


# ---- cost on the wire --------------------------------------------------------------------------

BAUD = 19200
CHAR_BITS = 11  # 8E1: start + 8 data + parity + stop


def _rtu_request_bytes(function: int, count: int) -> int:
    # unit(1) + PDU + CRC(2); PDU: FC16 fc addr qty bytecount data = 6 + 2n, FC06 and FC03 = 5
    return 9 + 2 * count if function == 16 else 8


def _rtu_response_bytes(function: int, count: int) -> int:
    # FC16 echoes address and quantity, FC06 echoes the request, FC03 carries bytecount + data
    return 5 + 2 * count if function == 3 else 8


def line_cost(plan: Plan, *, framing: str = "rtu", baud: int = BAUD, char_bits: int = CHAR_BITS) -> tuple[int, float]:
    """Characters on a serial line and seconds for the plan's write requests and their answers.

    RTU: binary frames plus the 3.5-character silence that ends each; ASCII: every byte but the CRC
    becomes two hex characters, plus ':', the LRC (two characters) and CR LF (2n + 1 characters for an
    n-byte RTU frame), and no silence. ``char_bits``: start + data + parity + stop bits.
    """
    answers = plan.device.unit != 0
    chars = 0.0
    frames = 0
    for w in plan.writes:
        sizes = [_rtu_request_bytes(w.function, w.count)]
        if answers:
            sizes.append(_rtu_response_bytes(w.function, w.count))
        for n in sizes:
            frames += 1
            chars += 2 * n + 1 if framing == "ascii" else n
    silence = 0.0 if framing == "ascii" else 3.5 * frames
    return int(chars), (chars + silence) * char_bits / baud


def wire_stats(plan: Plan) -> dict[str, float | int]:
    """Bytes and line time of the plan's write requests and their answers on an RTU line.

    ``rtu_bytes`` counts requests plus the answers the device gives (none for unit 0, broadcast);
    ``seconds_19200`` is that at 19200 baud, 8E1 (11 bits a character), plus the 3.5-character
    silent interval that ends every frame. ``read_*`` is the same for the plan's FC03 blocks
    (one pass: snapshot or read-back).
    """
    char = CHAR_BITS / BAUD
    answers = plan.device.unit != 0

    def cost(reqs: Iterable[tuple[int, int]]) -> tuple[int, int]:
        total = frames = 0
        for function, count in reqs:
            total += _rtu_request_bytes(function, count)
            frames += 1
            if answers:
                total += _rtu_response_bytes(function, count)
                frames += 1
        return total, frames

    w_bytes, w_frames = cost((w.function, w.count) for w in plan.writes)
    r_bytes, r_frames = cost((r.function, r.count) for r in plan.reads)
    return {"requests": len(plan.writes), "registers": sum(w.count for w in plan.writes), "rtu_bytes": w_bytes,
            "seconds_19200": round((w_bytes + 3.5 * w_frames) * char, 6),
            "read_requests": len(plan.reads), "read_registers": sum(r.count for r in plan.reads),
            "read_rtu_bytes": r_bytes, "read_seconds_19200": round((r_bytes + 3.5 * r_frames) * char, 6)}
