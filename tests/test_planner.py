"""Planner: the rules of DESIGN.md, and minimality against brute force (hypothesis)."""

from __future__ import annotations

import itertools
import json
from collections.abc import Sequence

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from deployer.codec import register_count
from deployer.diagnostics import InputError
from deployer.planner import (
    Plan,
    Target,
    make_plan,
    plan_from_json,
    plan_reads,
    plan_to_json,
    plan_writes,
    wire_stats,
)
from deployer.profile import Limits, Parameter, Profile
from deployer.recipe import Desired, Recipe

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
            if groups and groups[-1][-1].parameter.end == d.parameter.address and \
                    groups[-1][-1].parameter.stage == d.parameter.stage:
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
    assert (len(writes), sum(w.count for w in writes)) == brute_force(ds, limits.write_registers,
                                                                       {d.name for d in ds})


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
    prof = Profile(id="t", parameters=tuple(sorted((d.parameter for d in ds), key=lambda p: p.address)),
                   limits=limits)
    recipe = Recipe("r", "r.yaml", prof, tuple(ds))
    plan = make_plan(recipe, Target("tcp://127.0.0.1:502", 3, "t"), current)
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
    data["writes"][0]["registers"] = [8]
    with pytest.raises(InputError, match="does not carry exactly"):
        plan_from_json(data)


def test_wire_stats() -> None:
    ds = [desired(param("a", 0, 2))]
    prof = Profile(id="t", parameters=(ds[0].parameter,))
    plan: Plan = make_plan(Recipe("r", None, prof, tuple(ds)), Target(None, 1, "t"))
    st_ = wire_stats(plan)
    assert st_["rtu_bytes"] == 13 + 8 and st_["requests"] == 1
    assert register_count("uint32") == 2
