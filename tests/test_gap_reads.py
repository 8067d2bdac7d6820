"""Reads across gaps (issue #9): opt-in per profile, fewer FC03s, never a write to a gap, fallback on 02."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks import drive
from deployer.errors import InputError
from deployer.execute.device import apply_device
from deployer.execute.read import read_current
from deployer.execute.session import ApplyOptions
from deployer.planning.model import Target
from deployer.planning.planfile import plan_to_json
from deployer.planning.planner import plan_reads
from deployer.planning.steps import make_plan
from deployer.recipe.loader import load_recipe
from deployer.report import DeviceResult
from deployer.testing.simulator import Simulator
from deployer.transport.clients import parse_url
from tests import contract
from tests.helpers import profile_from, run_with

pytestmark = pytest.mark.timeout(60)


def _drive(tmp: Path, gap: int, salt: int = 0) -> str:
    return str(drive.write(str(tmp), 500, max_read_gap=gap, salt=salt)["recipe"])


def test_plan_reads_span_one_register_gaps_of_the_drive(tmp_path: Path) -> None:
    """13 blocks per pass over the 679 registers without gap reads, 6 with them (125 registers each at most)."""
    plain = make_plan(load_recipe(_drive(tmp_path / "a", 0)), Target(None, 1, "d"))
    gaps = make_plan(load_recipe(_drive(tmp_path / "b", 1)), Target(None, 1, "d"))
    assert (len(plain.writes), len(plain.reads)) == (13, 13)
    assert (len(gaps.writes), len(gaps.reads)) == (13, 6)
    assert gaps.writes == plain.writes  # writes never span a gap
    assert all(r.count <= 125 for r in gaps.reads)
    covered = {a for r in gaps.reads for a in range(r.address, r.address + r.count)}
    assert all(a in covered for d in plain.parameters for a in range(d.address, d.address + d.count))


def test_gap_limit_and_write_only_registers_bound_a_read(tmp_path: Path) -> None:
    prof = profile_from(
        tmp_path,
        """\
profile: dev
limits: {max_read_gap: 2}
parameters:
  a: {register: 0, type: uint16}
  b: {register: 3, type: uint16}     # a gap of 2: joined
  c: {register: 7, type: uint16}     # a gap of 3: a new block
  w: {register: 9, type: uint16, access: write-only}
  d: {register: 10, type: uint16}    # a write-only register in the gap: a new block
""",
    )
    reads = plan_reads(prof, ["a", "b", "c", "d"])
    assert [(r.address, r.count) for r in reads] == [(0, 4), (7, 1), (10, 1)]
    assert [(r.address, r.count) for r in plan_reads(prof, ["a", "b"], gaps=False)] == [(0, 1), (3, 1)]


def test_max_read_gap_is_checked_by_the_schema(tmp_path: Path) -> None:
    with pytest.raises(InputError) as err:
        profile_from(
            tmp_path, "profile: dev\nlimits: {max_read_gap: -1}\nparameters:\n  a: {register: 0, type: uint16}\n"
        )
    assert "max_read_gap" in str(err.value)


def _apply(sim: Simulator, path: str, tmp: Path) -> DeviceResult:
    rec = load_recipe(path)

    async def body(s: Simulator) -> DeviceResult:
        return await apply_device(
            rec,
            parse_url(s.url + "?timeout=0.5"),
            1,
            options=ApplyOptions(state_dir=str(tmp / ".deployer"), backoff=0.01),
        )

    return run_with(sim, body)


def test_apply_with_gap_reads_on_a_device_that_answers_them(tmp_path: Path) -> None:
    path = _drive(tmp_path, 1)
    rec = load_recipe(path)
    sim = Simulator(rec.profile, gap_reads=True)
    res = _apply(sim, path, tmp_path)
    assert res.status == "ok"
    reads = [r for r in res.requests if r.function == 3]
    assert len(reads) == 12 and all(r.result == "ok" for r in reads)  # 6 snapshot + 6 read-back (was 26)
    assert not res.notices
    assert sum(1 for r in res.requests if r.function == 16) == 13
    assert all(e.function == 3 for e in sim.log if e.count > 123)  # only reads are that long
    assert all(p.status in ("ok", "unchanged") for p in res.parameters)


def test_fallback_on_a_device_that_refuses_gap_reads(tmp_path: Path) -> None:
    """The first read across a gap answers 02: that block and every later read go gap-free."""
    path = _drive(tmp_path, 1)
    rec = load_recipe(path)
    sim = Simulator(rec.profile)  # only declared registers exist
    res = _apply(sim, path, tmp_path)
    assert res.status == "ok", res.error
    reads = [(r.address, r.count, r.result, r.exception_code) for r in res.requests if r.function == 3]
    assert reads[0] == (0, 125, "exception", 2)  # the refused read is in the report ...
    assert all(r[2] == "ok" for r in reads[1:])  # ... followed by the gap-free reads
    assert len(reads) == 1 + 13 + 13
    assert any("refused a read across undeclared registers" in n for n in res.notices)
    assert all(p.status in ("ok", "unchanged") for p in res.parameters)
    # the refused block and the gap-free ones that stand in for the rest of the snapshot's and the read-back's
    # blocks are named deviations of the plan (tests/contract.py): the plan made against what it held before
    plan = plan_to_json(
        make_plan(rec, Target(res.url, 1, "x"), {p.name: tuple(p.before_raw or ()) for p in res.parameters})
    )
    contract.check(plan, res.to_json(), sim.log)
    assert {r.deviation for r in res.requests} == {None, "gap-free"}
    # the device never saw a write to an undeclared register
    declared = {a for p in rec.profile.parameters for a in range(p.address, p.end)}
    assert all(set(range(e.address, e.address + e.count)) <= declared for e in sim.log if e.function == 16)


def test_read_current_falls_back_too(tmp_path: Path) -> None:
    path = _drive(tmp_path, 1)
    rec = load_recipe(path)
    names = [d.name for d in rec.desired]

    async def body(s: Simulator) -> dict[str, tuple[int, ...]]:
        return await read_current(rec.profile, names, parse_url(s.url + "?timeout=0.5"), 1)

    values = run_with(Simulator(rec.profile), body)
    assert set(values) == set(names)


def test_simulator_gap_reads_answer_zeros_and_refuse_writes(tmp_path: Path) -> None:
    prof = profile_from(
        tmp_path,
        "profile: dev\nparameters:\n  a: {register: 0, type: uint16, default: 7}\n"
        "  b: {register: 2, type: uint16, default: 9}\n",
    )
    from deployer.errors import ExceptionResponse
    from deployer.transport.clients import open_transport

    async def body(s: Simulator) -> tuple[list[int], int]:
        t = open_transport(s.url)
        await t.connect()
        try:
            regs = await t.read_holding_registers(0, 3, 1)
            with pytest.raises(ExceptionResponse) as err:
                await t.write_registers(0, [1, 2, 3], 1)
            return regs, err.value.code
        finally:
            await t.close()

    regs, code = run_with(Simulator(prof, gap_reads=True), body)
    assert regs == [7, 0, 9] and code == 2
