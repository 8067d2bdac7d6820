"""Planner: the planning rules of docs/design.md, and minimality against brute force (hypothesis)."""

from __future__ import annotations

import itertools
import json
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from deployer.errors import InputError, UsageError
from deployer.load import schema, yamlsrc
from deployer.planning.model import Pacing, Plan, Step, Target
from deployer.planning.planfile import plan_from_json, plan_to_json
from deployer.planning.planner import plan_reads, plan_writes
from deployer.planning.steps import make_plan
from deployer.planning.wire import plan_cost
from deployer.profile import Limits, Parameter, Profile
from deployer.profile.codec import register_count
from deployer.recipe.loader import Desired, Recipe

TYPES = {1: "uint16", 2: "uint32", 4: "uint64"}


def param(name: str, address: int, count: int = 1, stage: int = 0, access: str = "read-write") -> Parameter:
    return Parameter(name=name, address=address, type=TYPES[count], stage=stage, access=access)  # type: ignore[arg-type]


def desired(p: Parameter, value: int = 7) -> Desired:
    return Desired(p, str(value), tuple([0] * (p.count - 1) + [value]))


# ---- strategies ------------------------------------------------------------------------------


@st.composite
def layouts(draw: st.DrawFn, max_params: int = 8) -> tuple[list[Desired], Limits, dict[str, tuple[int, ...]]]:
    """Random small profiles: gaps, 1/2/4-register values, stages, limits and current values."""
    n = draw(st.integers(1, max_params))
    address = draw(st.integers(0, 50))
    out = []
    current: dict[str, tuple[int, ...]] = {}
    for i in range(n):
        address += draw(st.sampled_from([0, 0, 0, 1, 3]))  # mostly contiguous
        count = draw(st.sampled_from([1, 1, 2, 4]))
        p = param(f"p{i}", address, count, stage=draw(st.sampled_from([0, 0, 0, 1])))
        d = desired(p, draw(st.integers(1, 3)))
        out.append(d)
        if draw(st.booleans()):
            current[p.name] = d.registers  # unchanged
        else:
            current[p.name] = tuple(0 for _ in d.registers)
        address += count
    limit = draw(st.integers(4, 12))
    return out, Limits(max_write_registers=limit), current


def written_registers(writes: Sequence) -> list[int]:  # type: ignore[type-arg]
    return [w.address + i for w in writes for i in range(w.count)]


def brute_force(ds: list[Desired], limit: int, must: set[str]) -> tuple[int, int]:
    """Cheapest (requests, registers) over every choice of bridges and every split of runs."""
    best = (10**9, 10**9)
    optional = [d for d in ds if d.name not in must]
    by_stage = sorted(ds, key=lambda d: (d.parameter.stage, d.parameter.address))
    for mask in itertools.product([False, True], repeat=len(optional)):
        chosen = must | {d.name for d, m in zip(optional, mask, strict=True) if m}
        cost_req, cost_reg = 0, 0
        seq = [d for d in by_stage if d.name in chosen]
        # groups of contiguous chosen parameters in one stage; each group needs the fewest
        # contiguous pieces of at most `limit` registers: try every split
        groups: list[list[Desired]] = []
        for d in seq:
            if (
                groups
                and groups[-1][-1].parameter.end == d.parameter.address
                and groups[-1][-1].parameter.stage == d.parameter.stage
            ):
                groups[-1].append(d)
            else:
                groups.append([d])
        ok = True
        for g in groups:
            sizes = [d.parameter.count for d in g]
            pieces = _min_pieces(sizes, limit)
            if pieces is None:
                ok = False
                break
            cost_req += pieces
            cost_reg += sum(sizes)
        if ok:
            best = min(best, (cost_req, cost_reg))
    return best


def _min_pieces(sizes: list[int], limit: int) -> int | None:
    n = len(sizes)
    best: int | None = None
    for cuts in itertools.product([False, True], repeat=n - 1):
        pieces, acc = 1, sizes[0]
        for s, cut in zip(sizes[1:], cuts, strict=True):
            if cut:
                pieces, acc = pieces + 1, s
            else:
                acc += s
            if acc > limit:
                break
        else:
            if acc <= limit and (best is None or pieces < best):
                best = pieces
    return best


# ---- properties ----------------------------------------------------------------------------------


@settings(max_examples=300, deadline=None)
@given(layouts())
def test_every_named_register_written_once_and_nothing_else(case) -> None:  # type: ignore[no-untyped-def]
    ds, limits, _ = case
    _, writes = plan_writes(ds, limits)
    named = sorted(a for d in ds for a in range(d.parameter.address, d.parameter.end))
    assert sorted(written_registers(writes)) == named
    by_addr = {d.parameter.address: d for d in ds}
    for w in writes:
        assert 1 <= w.count <= limits.write_registers
        # whole parameters only, contiguous, values equal to the desired ones
        regs: list[int] = []
        for n in w.parameters:
            d = next(x for x in ds if x.name == n)
            regs.extend(d.registers)
        assert tuple(regs) == w.registers
        assert by_addr[w.address].name == w.parameters[0]


@settings(max_examples=300, deadline=None)
@given(layouts())
def test_request_count_is_the_brute_force_minimum(case) -> None:  # type: ignore[no-untyped-def]
    ds, limits, _ = case
    _, writes = plan_writes(ds, limits)
    assert (len(writes), sum(w.count for w in writes)) == brute_force(ds, limits.write_registers, {d.name for d in ds})


@settings(max_examples=300, deadline=None)
@given(layouts())
def test_diff_aware_plan_is_minimal_and_writes_only_changes_or_bridges(case) -> None:  # type: ignore[no-untyped-def]
    ds, limits, current = case
    params, writes = plan_writes(ds, limits, current)
    changed = {d.name for d in ds if current[d.name] != d.registers}
    in_writes = {n for w in writes for n in w.parameters}
    assert changed <= in_writes
    for p in params:
        if p.name in changed:
            assert p.action == "write"
        elif p.name in in_writes:
            assert p.action == "bridge"
        else:
            assert p.action == "unchanged"
    if changed:
        assert (len(writes), sum(w.count for w in writes)) == brute_force(ds, limits.write_registers, changed)
    else:
        assert writes == ()


@settings(max_examples=200, deadline=None)
@given(layouts())
def test_stages_in_order_and_ascending_within_a_stage(case) -> None:  # type: ignore[no-untyped-def]
    ds, limits, _ = case
    _, writes = plan_writes(ds, limits)
    keys = [(w.stage, w.address) for w in writes]
    assert keys == sorted(keys)


@settings(max_examples=200, deadline=None)
@given(layouts())
def test_json_round_trip_is_identity(case) -> None:  # type: ignore[no-untyped-def]
    ds, limits, current = case
    ps = tuple(sorted((d.parameter for d in ds), key=lambda p: p.address))
    for lim in (limits, Limits(write_function=6)):  # FC16 and FC06 plans
        recipe = Recipe("r", "r.yaml", Profile(id="t", parameters=ps, limits=lim), tuple(ds))
        for cur in (None, current):
            plan = make_plan(recipe, Target("tcp://127.0.0.1:502", 3, "t"), cur)
            again = plan_from_json(json.loads(json.dumps(plan_to_json(plan))))
            assert again == plan


# ---- rules, one by one --------------------------------------------------------------------------


def test_never_split_a_parameter_even_when_the_limit_is_odd() -> None:
    ds = [desired(param(f"p{i}", 2 * i, 2)) for i in range(5)]  # 10 registers of 32-bit values
    _, writes = plan_writes(ds, Limits(max_write_registers=5))
    assert [w.count for w in writes] == [4, 4, 2]


def test_frame_bytes_limit() -> None:
    """max_frame_bytes 64 -> (64 - 9) // 2 = 27 registers per request: 60 registers in 3 requests."""
    limits = Limits(max_frame_bytes=64)
    assert limits.write_registers == 27
    ds = [desired(param(f"p{i}", i)) for i in range(60)]
    _, writes = plan_writes(ds, limits)
    assert [w.count for w in writes] == [27, 27, 6]


def test_gap_means_a_new_request() -> None:
    ds = [desired(param("a", 10)), desired(param("b", 12))]
    _, writes = plan_writes(ds, Limits())
    assert [(w.address, w.count) for w in writes] == [(10, 1), (12, 1)]


def test_bridge_saves_a_request() -> None:
    ds = [desired(param(n, i)) for i, n in enumerate("abc")]
    current = {"a": (0,), "b": ds[1].registers, "c": (0,)}
    params, writes = plan_writes(ds, Limits(), current)
    assert [(w.address, w.count, w.parameters) for w in writes] == [(0, 3, ("a", "b", "c"))]
    assert [p.action for p in params] == ["write", "bridge", "write"]


def test_no_bridge_when_it_saves_nothing() -> None:
    ds = [desired(param(n, i)) for i, n in enumerate("abc")]
    current = {"a": (0,), "b": ds[1].registers, "c": ds[2].registers}
    params, writes = plan_writes(ds, Limits(), current)
    assert [(w.address, w.count) for w in writes] == [(0, 1)]
    assert [p.action for p in params] == ["write", "unchanged", "unchanged"]


def test_write_all() -> None:
    ds = [desired(param(n, i)) for i, n in enumerate("ab")]
    params, writes = plan_writes(ds, Limits(), {"a": ds[0].registers, "b": ds[1].registers}, write_all=True)
    assert [p.action for p in params] == ["write", "write"] and len(writes) == 1


def test_fc06_devices_get_one_request_per_register() -> None:
    ds = [desired(param("a", 0, 2)), desired(param("b", 2))]
    _, writes = plan_writes(ds, Limits(write_function=6))
    assert [(w.function, w.address, w.registers) for w in writes] == [(6, 0, (0,)), (6, 1, (7,)), (6, 2, (7,))]


def test_plan_reads_skip_gaps_and_write_only_registers() -> None:
    ps = (param("a", 0), param("b", 1, 2), param("wo", 3, access="write-only"), param("c", 4), param("d", 10))
    prof = Profile(id="t", parameters=ps, limits=Limits(max_read_registers=125))
    reads = plan_reads(prof, ["a", "c", "d"])
    assert [(r.address, r.count) for r in reads] == [(0, 1), (4, 1), (10, 1)]
    # a block may span a declared parameter the recipe does not name
    assert [(r.address, r.count) for r in plan_reads(prof, ["a", "c"])] == [(0, 1), (4, 1)]
    prof2 = Profile(id="t", parameters=(param("a", 0), param("b", 1, 2), param("c", 3)), limits=Limits())
    assert [(r.address, r.count) for r in plan_reads(prof2, ["a", "c"])] == [(0, 4)]


def test_plan_reads_respect_the_read_limit() -> None:
    ps = tuple(param(f"p{i}", 2 * i, 2) for i in range(10))
    prof = Profile(id="t", parameters=ps, limits=Limits(max_read_registers=5))
    reads = plan_reads(prof, [p.name for p in ps])
    assert [r.count for r in reads] == [4, 4, 4, 4, 4]


def test_saved_plan_that_does_not_carry_its_values_is_refused() -> None:
    ds = [desired(param("a", 0))]
    prof = Profile(id="t", parameters=(ds[0].parameter,))
    data = plan_to_json(make_plan(Recipe("r", None, prof, tuple(ds)), Target(None, 1, "t")))
    next(s for s in data["steps"] if s["kind"] == "write")["values"] = [8]
    with pytest.raises(InputError, match="does not carry exactly"):
        plan_from_json(data)


def test_plan_cost_counts_every_step() -> None:
    ds = [desired(param("a", 0, 2))]
    prof = Profile(id="t", parameters=(ds[0].parameter,))
    plan: Plan = make_plan(Recipe("r", None, prof, tuple(ds)), Target(None, 1, "t"))
    # snapshot FC03 (8 + 9 bytes), device identification (7 + 16), the FC16 (13 + 8), the read-back (8 + 9)
    c = plan_cost(plan, prof)
    assert [s.kind for s in plan.steps] == ["snapshot", "device-id", "write", "verify"]
    assert (c.requests, c.reads, c.writes, c.bytes) == (4, 3, 1, 17 + 23 + 21 + 17)
    assert register_count("uint32") == 2


# ---- FC06 devices, partial knowledge, refusals ----------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(layouts())
def test_fc06_plans_write_each_named_register_once_in_order(case) -> None:  # type: ignore[no-untyped-def]
    ds, _, current = case
    params, writes = plan_writes(ds, Limits(write_function=6), current)
    changed = [d for d in ds if current[d.name] != d.registers]
    assert all(w.function == 6 and w.count == 1 and len(w.parameters) == 1 for w in writes)
    # exactly the changed parameters' registers, whole parameters, with their values
    assert [(w.address, w.registers[0]) for w in writes] == [
        (d.parameter.address + k, v)
        for d in sorted(changed, key=lambda d: (d.parameter.stage, d.parameter.address))
        for k, v in enumerate(d.registers)
    ]
    assert {p.name for p in params if p.action == "write"} == {d.name for d in changed}
    assert all(p.action != "bridge" for p in params)  # one request per register: bridging saves nothing


def test_unknown_current_value_is_written() -> None:
    ds = [desired(param(n, i)) for i, n in enumerate("abc")]
    params, writes = plan_writes(ds, Limits(), {"a": ds[0].registers, "c": ds[2].registers})
    assert [p.action for p in params] == ["unchanged", "write", "unchanged"]
    assert [p.current_raw for p in params] == [ds[0].registers, None, ds[2].registers]
    assert [(w.address, w.parameters) for w in writes] == [(1, ("b",))]


def test_bridge_is_not_used_when_it_would_overflow_the_limit() -> None:
    # a, b, c of 2 registers each; limit 4: a+b+c (6) does not fit, so a and c go separately
    ds = [desired(param(n, 2 * i, 2)) for i, n in enumerate("abc")]
    current = {"a": (0, 0), "b": ds[1].registers, "c": (0, 0)}
    params, writes = plan_writes(ds, Limits(max_write_registers=4), current)
    assert [(w.address, w.parameters) for w in writes] == [(0, ("a",)), (4, ("c",))]
    assert [p.action for p in params] == ["write", "unchanged", "write"]


def test_bridge_chooses_the_cheaper_of_equal_request_counts() -> None:
    # changed a, d; unchanged b (1 register), c (1 register): one request a..d (4) beats nothing else
    ds = [desired(param(n, i)) for i, n in enumerate("abcd")]
    current = {"a": (0,), "b": ds[1].registers, "c": ds[2].registers, "d": (0,)}
    params, writes = plan_writes(ds, Limits(max_write_registers=4), current)
    assert [(w.address, w.count) for w in writes] == [(0, 4)]
    assert [p.action for p in params] == ["write", "bridge", "bridge", "write"]
    # limit 3: a..d does not fit; two requests, and no bridge register is written for nothing
    params, writes = plan_writes(ds, Limits(max_write_registers=3), current)
    assert [(w.address, w.count) for w in writes] == [(0, 1), (3, 1)]
    assert [p.action for p in params] == ["write", "unchanged", "unchanged", "write"]


def test_stages_are_written_in_order_even_when_addresses_are_not() -> None:
    ds = [desired(param("late", 0, stage=1)), desired(param("early", 1, stage=0))]
    params, writes = plan_writes(ds, Limits())
    assert [(w.stage, w.parameters) for w in writes] == [(0, ("early",)), (1, ("late",))]
    assert [p.name for p in params] == ["early", "late"]


def test_contiguous_parameters_in_different_stages_are_not_merged() -> None:
    ds = [desired(param("a", 0, stage=0)), desired(param("b", 1, stage=1))]
    _, writes = plan_writes(ds, Limits())
    assert len(writes) == 2


def test_refusals_are_user_errors() -> None:
    with pytest.raises(UsageError, match="needs 4 registers"):
        plan_writes([desired(param("big", 0, 4))], Limits(max_write_registers=3))
    with pytest.raises(UsageError, match="overlaps"):
        plan_writes([desired(param("a", 0, 2)), desired(param("b", 1))], Limits())
    with pytest.raises(UsageError, match="overlaps"):
        d = desired(param("a", 0))
        plan_writes([d, d], Limits())
    with pytest.raises(UsageError, match="register values"):
        plan_writes([Desired(param("a", 0, 2), "1", (1,))], Limits())
    prof = Profile(id="t", parameters=(param("a", 0), param("wo", 1, access="write-only")))
    with pytest.raises(UsageError, match="not readable.*nope.*wo"):
        plan_reads(prof, ["a", "wo", "nope"])


# ---- reads: against every partition of the needed parameters ---------------------------------------


@st.composite
def read_layouts(draw: st.DrawFn) -> tuple[Profile, list[str]]:
    n = draw(st.integers(1, 8))
    address = draw(st.integers(0, 20))
    ps = []
    for i in range(n):
        address += draw(st.sampled_from([0, 0, 0, 2]))
        count = draw(st.sampled_from([1, 1, 2, 4]))
        access = draw(st.sampled_from(["read-write", "read-write", "read-only", "write-only"]))
        ps.append(param(f"p{i}", address, count, access=access))
        address += count
    readable = [p.name for p in ps if p.readable]
    names = draw(st.lists(st.sampled_from(readable), unique=True)) if readable else []
    limits = Limits(max_read_registers=draw(st.integers(4, 10)))
    draw(st.randoms()).shuffle(ps)  # plan_reads must not rely on the profile's order
    return Profile(id="t", parameters=tuple(ps), limits=limits), names


def brute_force_reads(prof: Profile, names: list[str]) -> int:
    """Fewest blocks: try every split of the needed parameters (in address order) into groups."""
    ps = sorted(prof.parameters, key=lambda p: p.address)
    need = sorted((p for p in ps if p.name in names), key=lambda p: p.address)
    if not need:
        return 0

    def one_block(group: list[Parameter]) -> bool:
        lo, hi = group[0].address, group[-1].end
        if hi - lo > prof.limits.read_registers:
            return False
        covered = [p for p in ps if lo <= p.address < hi]  # must tile [lo, hi) with readable ones
        return all(p.readable for p in covered) and sum(p.count for p in covered) == hi - lo

    best = len(need) + 1
    for cuts in itertools.product([False, True], repeat=len(need) - 1):
        groups, cur = [], [need[0]]
        for p, cut in zip(need[1:], cuts, strict=True):
            if cut:
                groups.append(cur)
                cur = [p]
            else:
                cur.append(p)
        groups.append(cur)
        if all(one_block(g) for g in groups):
            best = min(best, len(groups))
    return best


@settings(max_examples=300, deadline=None)
@given(read_layouts())
def test_reads_cover_only_declared_readable_registers_with_the_fewest_blocks(case) -> None:  # type: ignore[no-untyped-def]
    prof, names = case
    reads = plan_reads(prof, names)
    by_addr = {p.address: p for p in prof.parameters}
    starts_ends = {p.address for p in prof.parameters} | {p.end for p in prof.parameters}
    covered: set[str] = set()
    for r in reads:
        assert r.function == 3 and 1 <= r.count <= prof.limits.read_registers
        assert r.address in starts_ends and r.address + r.count in starts_ends  # never cuts a parameter
        a = r.address
        while a < r.address + r.count:  # the block is tiled by declared readable parameters
            p = by_addr[a]
            assert p.readable
            covered.add(p.name)
            a = p.end
        assert a == r.address + r.count
    assert set(names) <= covered
    assert len(reads) == brute_force_reads(prof, names)
    keys = [r.address for r in reads]
    assert keys == sorted(keys)


def test_reads_with_a_small_frame_limit() -> None:
    """max_frame_bytes 64 -> the answer (5 + 2n bytes) allows 29 registers per FC03."""
    ps = tuple(param(f"p{i}", i) for i in range(60))
    prof = Profile(id="t", parameters=ps, limits=Limits(max_frame_bytes=64))
    assert [r.count for r in plan_reads(prof, [p.name for p in ps])] == [29, 29, 2]


def test_make_plan_reads_only_readable_recipe_parameters() -> None:
    ps = (param("a", 0), param("wo", 1, access="write-only"), param("b", 2), param("other", 3))
    prof = Profile(id="t", parameters=ps)
    rec = Recipe("r", None, prof, (desired(ps[0]), desired(ps[1]), desired(ps[2])))
    plan = make_plan(rec, Target(None, 1, "t"))
    assert [(r.address, r.count) for r in plan.reads] == [(0, 1), (2, 1)]
    assert [(w.address, w.count) for w in plan.writes] == [(0, 3)]  # write-only is written, not read


# ---- plan JSON ------------------------------------------------------------------------------------


def _plan() -> Plan:
    ds = [desired(param("a", 0, 2)), desired(param("b", 2)), desired(param("c", 3))]
    prof = Profile(id="t", parameters=tuple(d.parameter for d in ds))
    return make_plan(
        Recipe("r", "r.yaml", prof, tuple(ds)),
        Target("tcp://h:502", 1, "t"),
        {"a": (0, 0), "b": ds[1].registers, "c": (0,)},
    )


def test_plan_json_has_the_design_shape_and_validates() -> None:
    data = json.loads(json.dumps(plan_to_json(_plan())))
    jsonschema.Draft202012Validator(schema.schema("plan")).validate(data)
    assert set(data) == {"schema", "recipe", "device", "profile_sha256", "pacing", "parameters", "steps", "recipe_name"}
    assert data["parameters"][0] == {
        "name": "a",
        "address": 0,
        "count": 2,
        "desired": "7",
        "desired_raw": [0, 7],
        "current_raw": [0, 0],
        "action": "write",
        "stage": 0,
    }
    assert data["steps"] == [
        {"kind": "snapshot", "function": 3, "address": 0, "count": 4, "parameters": ["a", "b", "c"]},
        {"kind": "device-id", "function": 43, "address": 0, "count": 1, "note": "vendor, product code, revision"},
        {
            "kind": "write",
            "function": 16,
            "address": 0,
            "count": 4,
            "values": [0, 7, 7, 7],
            "parameters": ["a", "b", "c"],
            "stage": 0,
        },
        {"kind": "verify", "function": 3, "address": 0, "count": 4, "parameters": ["a", "b", "c"]},
    ]
    assert [p["action"] for p in data["parameters"]] == ["write", "bridge", "write"]


def _write(d: dict[str, Any]) -> dict[str, Any]:
    return next(s for s in d["steps"] if s["kind"] == "write")


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: _write(d)["values"].__setitem__(0, 65536), "65536 is greater than the maximum"),
        (lambda d: d.pop("steps"), "'steps' is a required property"),
        (lambda d: _write(d).__setitem__("count", 3), "count 3 but 4 values"),
        (lambda d: d["parameters"][1].__setitem__("action", "unchanged"), "b is 'unchanged' but is in a write"),
        (lambda d: _write(d).__setitem__("parameters", ["a", "b"]), "does not carry exactly"),
        (lambda d: _write(d).__setitem__("parameters", ["a", "b", "zz"]), "names 'zz'"),
        (lambda d: d["parameters"][0].__setitem__("desired_raw", [7]), "1 registers for count 2"),
        (lambda d: _write(d).__setitem__("function", 6), "does not carry exactly"),
        (lambda d: _write(d).__setitem__("function", 3), "function 3 does not fit a write step"),
        (lambda d: d["steps"][0].__setitem__("count", 126), "function 3 carries at most 125 in one request"),
        (lambda d: d["steps"][0].__setitem__("values", [1, 2, 3, 4]), "a snapshot step reads: it carries no values"),
        (lambda d: d["steps"].insert(0, dict(_write(d))), "a snapshot step after a later kind of step"),
        (
            lambda d: d["steps"].append(
                {"kind": "unlock", "function": 16, "address": 9, "count": 1, "values": [1], "parameters": ["a"]}
            ),
            "an unlock step after a later kind of step",
        ),
        (lambda d: d["steps"][0].__setitem__("expect", {"equals": 1}), "only identity and precondition steps"),
        (
            lambda d: d.__setitem__("schema", "deployer.plan/1"),
            "make it again with: deployer plan r.yaml --device tcp://h:502 --out p.json",
        ),
    ],
)
def test_inconsistent_plans_are_refused_at_file_0_0(edit, message) -> None:  # type: ignore[no-untyped-def]
    data = json.loads(json.dumps(plan_to_json(_plan())))
    edit(data)
    with pytest.raises(InputError) as e:
        plan_from_json(data, "p.json")
    text = str(e.value)
    assert message in text and text.startswith("p.json:0:0: error: ")


def test_a_saved_plan_of_a_function_06_device_with_bit_fields_loads() -> None:
    """A device that takes only Function 06 (its profile says so, or it taught it): the word its bit fields share goes
    as one request naming them all, and the saved plan of it loads as the planner made it (it was refused)."""
    from deployer.profile import builtin_profile
    from deployer.recipe.loader import load_recipe

    prof = builtin_profile("example-drive")
    rec = load_recipe(str(Path(__file__).resolve().parent.parent / "recipes" / "examples" / "example-drive-axis1.yaml"))
    rec = replace(rec, profile=replace(prof, limits=replace(prof.limits, write_function=6)))
    current = {d.name: tuple(0 for _ in d.registers) for d in rec.desired}
    plan = make_plan(rec, Target("tcp://h:502", 1, "example-drive"), current)
    shared = [s for s in plan.steps if s.kind == "write" and len(s.parameters) > 1]
    assert shared and all(s.function == 6 and s.count == 1 for s in shared)
    assert plan_from_json(json.loads(json.dumps(plan_to_json(plan))), "p.json") == plan


def test_plan_errors_carry_positions_with_a_source(tmp_path) -> None:  # type: ignore[no-untyped-def]
    data = plan_to_json(_plan())
    _write(data)["values"][1] = 8
    f = tmp_path / "p.json"
    f.write_text(json.dumps(data, indent=1))
    loaded, src = yamlsrc.load(str(f))
    with pytest.raises(InputError) as e:
        plan_from_json(loaded, str(f), src=src)
    (d,) = e.value.diagnostics
    lines = f.read_text().splitlines()
    assert d.line > 1 and '"values"' in lines[d.line - 1]
    assert plan_from_json(yamlsrc.load(str(tmp_path / "ok.json"), json.dumps(plan_to_json(_plan())))[0]) == _plan()


def test_not_a_plan() -> None:
    with pytest.raises(InputError, match="p.json:0:0: error: a plan must be a JSON object"):
        plan_from_json([1], "p.json")


# ---- wire statistics --------------------------------------------------------------------------------


def test_plan_cost_numbers() -> None:
    plan = _plan()  # snapshot FC03 of 4, device identification, one FC16 of 4, the read-back FC03 of 4
    char = 11 / 19200
    c = plan_cost(plan)
    rtu = (8 + 13) + (7 + 16) + (17 + 8) + (8 + 13)
    assert (c.requests, c.reads, c.writes, c.bytes, c.framing, c.line) == (4, 3, 1, rtu, "rtu", "19200 baud 8E1")
    assert c.seconds == pytest.approx((rtu + 8 * 3.5) * char, abs=1e-6) and c.waits == 0
    broadcast = plan_cost(
        replace(plan, device=Target(None, 0, "t"), steps=tuple(s for s in plan.steps if s.kind == "write"))
    )
    assert broadcast.bytes == 17  # unit 0: nobody answers, nothing is read
    assert broadcast.seconds == pytest.approx((17 + 3.5) * char, abs=1e-6)
    fc6 = replace(plan, steps=(Step("write", 6, 0, 1, (1,), ("a",)),))
    assert plan_cost(fc6).bytes == 16
    paced = replace(plan, pacing=Pacing(0.5, 0.1))
    assert plan_cost(paced).waits == pytest.approx(0.5 + 3 * 0.1)  # after connecting, then between 4 requests
