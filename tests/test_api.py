"""The public API's operations against simulators: plan makes a plan, apply executes exactly it (or plans and
executes a recipe), for one device and for an inventory; rollback, diff, pull, confirm and status; the async twins."""

from __future__ import annotations

import asyncio
import json
import threading
from pathlib import Path

import pytest

import deployer
import deployer.aio
from deployer.profile import builtin_profile
from deployer.testing.simulator import Simulator, SimulatorThread
from tests import contract
from tests.helpers import Simulators, wait_for

PROFILE = builtin_profile("example-inverter")
EXAMPLES = Path(__file__).resolve().parent.parent / "recipes" / "examples"


def recipe(**values: str) -> deployer.Recipe:
    return deployer.recipe_from("example-inverter", values or {"F07": "10 s", "base_speed": "1750 rpm"})


def devices(sims: list[Simulator], groups: tuple[str, ...] = ()) -> list[dict[str, object]]:
    return [
        {"name": f"d{i}", "url": s.url, **({"groups": [groups[i - 1]]} if groups else {})}
        for i, s in enumerate(sims, 1)
    ]


def test_apply_executes_exactly_the_plan_it_is_given(tmp_path: Path) -> None:
    drive = deployer.load_recipe(EXAMPLES / "example-drive-axis1.yaml")
    with SimulatorThread(builtin_profile("example-drive")) as sim:
        plan = deployer.plan(drive, sim.url, state_dir=tmp_path)
        assert isinstance(plan, deployer.Plan) and plan.changes
        assert [s.kind for s in plan.steps][-2:] == ["commit", "lock"]
        n = len(sim.log)
        report = deployer.apply(plan, state_dir=tmp_path)
        assert report.exit_code == 0 and report.devices[0].status == "ok"
        contract.check(plan.to_json(), report.devices[0].to_json(), sim.log[n:])
        assert report.run is not None and report.run["command"] == "Python API: apply"
        assert '"via": "api"' in (tmp_path / "audit.jsonl").read_text()
        assert deployer.diff(drive, sim.url) == []


def test_a_plan_the_device_no_longer_matches_is_refused_before_any_write(tmp_path: Path) -> None:
    with SimulatorThread(PROFILE) as sim:
        plan = deployer.plan(recipe(), sim.url, state_dir=tmp_path)
        sim.write("F07", (0, 550))  # someone else changed it since
        n = len(sim.log)
        with pytest.raises(deployer.StalePlan, match=r"F07: now 5\.5 s"):
            deployer.apply(plan, state_dir=tmp_path)
        assert not [e for e in sim.log[n:] if e.function in (6, 16)]


def test_a_saved_plan_loads_and_runs(tmp_path: Path) -> None:
    with SimulatorThread(PROFILE) as sim:
        plan = deployer.plan(recipe(), sim.url, state_dir=tmp_path)
        saved = tmp_path / "plan.json"
        saved.write_text(json.dumps(plan.to_json()))
        loaded = deployer.load_plan(saved)
        assert loaded == plan
        report = deployer.apply(loaded, state_dir=tmp_path, report_path=tmp_path / "run.json")
        assert report.exit_code == 0
        assert [d.status for d in deployer.load_report(tmp_path / "run.json").devices] == ["ok"]
        with pytest.raises(deployer.UsageError, match="a Plan is one device's and runs unchanged"):
            deployer.apply(loaded, write_all=True)


def test_an_offline_plan_names_the_device_and_its_pacing() -> None:
    plan = deployer.plan(recipe(), "tcp://10.0.0.11:502?pause_between_requests=50ms", offline=True, state_dir=None)
    # the URL as the plan runs it again: its pause kept (a secret would not be)
    assert plan.device.url == "tcp://10.0.0.11:502?pause_between_requests=50ms" and plan.pacing.between_requests == 0.05
    assert [pp.current_raw for pp in plan.parameters] == [None, None]


def test_a_fleet_plan_keeps_every_device_and_why_not(tmp_path: Path) -> None:
    with Simulators([Simulator(PROFILE) for _ in range(3)]) as sims:
        gone: dict[str, object] = {"name": "gone", "url": "tcp://127.0.0.1:9?timeout=0.2&retries=0"}
        inv = [*devices(sims, ("a", "b", "a")), gone]
        sims[1].write("F07", (0, 1000))  # d2 already holds it
        fleet = deployer.plan(recipe(), inventory=inv, state_dir=tmp_path)
        assert isinstance(fleet, deployer.FleetPlan)
        assert list(fleet) == ["d1", "d2", "d3", "gone"] and len(fleet) == 4
        assert set(fleet.plans) == {"d1", "d2", "d3"} and isinstance(fleet.errors["gone"], deployer.TransportError)
        assert [pp.action for pp in fleet["d2"].parameters] == ["unchanged", "write"]
        assert fleet.profile("d1").id == "example-inverter" and fleet.device("d3") == (sims[2].url, 1)
        with pytest.raises(deployer.TransportError):
            fleet["gone"]
        doc = fleet.to_json()
        assert [d["name"] for d in doc["devices"]] == ["d1", "d2", "d3", "gone"] and "error" in doc["devices"][3]
        with pytest.raises(deployer.UsageError, match=r"the fleet plan has no plan for 1 device \(gone: "):
            deployer.apply(fleet, state_dir=tmp_path)
        assert not [e for s in sims for e in s.log if e.function in (6, 16)]
        started: list[str] = []
        report = deployer.apply(
            fleet.without_errors(), state_dir=tmp_path, batch="1,100%", batch_by="group", on_start=started.append
        )
        assert sorted(started) == ["d1", "d2", "d3"] and report.exit_code == 0
        # the inventory's groups kept: the first batch takes one device of each group
        assert {d.name: d.batch for d in report.devices} == {"d1": 1, "d2": 1, "d3": 2}
        assert all(s.read("F07") == (0, 1000) for s in sims)


def test_a_fleet_plan_is_applied_under_the_stale_plan_rule(tmp_path: Path) -> None:
    """Each device is refused before its first write when it changed since the plan: in a fleet that device is
    skipped (nothing written to it, said why), the others written as planned; one device alone raises."""
    with Simulators([Simulator(PROFILE) for _ in range(2)]) as sims:
        fleet = deployer.plan(recipe(), inventory=devices(sims), state_dir=tmp_path)
        sims[1].write("base_speed", (1234,))
        report = deployer.apply(fleet, state_dir=tmp_path)
        assert [d.status for d in report.devices] == ["ok", "skipped"] and report.exit_code == 4
        assert "not written: the device changed since the plan was made (base_speed: now 1234 rpm)" in (
            report.devices[1].error or ""
        )
        assert not [e for e in sims[1].log if e.function in (6, 16)]
        # the skipped device says what it was found holding, each parameter's value read
        base = next(p for p in report.devices[1].parameters if p.name == "base_speed")
        assert base.status == "skipped" and base.before_raw == (1234,)
        with pytest.raises(deployer.UsageError, match="a FleetPlan runs in this process"):
            deployer.apply(fleet, workers=2)
        one = deployer.plan(recipe(), inventory=devices(sims)[1:], state_dir=tmp_path)
        sims[1].write("base_speed", (1235,))
        with pytest.raises(deployer.StalePlan, match="base_speed") as refused:
            deployer.apply(one, state_dir=tmp_path)
        (alone,) = refused.value.report.devices  # the refused run's report: the device as it was found
        assert refused.value.report.exit_code == 1  # as the command line exits: refused, nothing written
        assert refused.value.report.refused == str(refused.value)
        assert alone.status == "skipped" and alone.error.startswith("not written: the device changed")
        assert next(p.before_raw for p in alone.parameters if p.name == "base_speed") == (1235,)


def test_apply_a_recipe_to_an_inventory_and_roll_it_back(tmp_path: Path) -> None:
    with Simulators([Simulator(PROFILE) for _ in range(2)]) as sims:
        before = [s.read("F07") for s in sims]
        done: list[str] = []
        report = deployer.apply(
            recipe(),
            inventory=devices(sims),
            limit="d*",
            parallel=2,
            state_dir=tmp_path,
            report_path=tmp_path / "run.json",
            on_done=lambda r: done.append(r.status),
            caller="ansible deployer.modbus.apply",
        )
        assert report.exit_code == 0 and done == ["ok", "ok"]
        assert '"via": "ansible"' in (tmp_path / "audit.jsonl").read_text()
        assert all(s.read("F07") == (0, 1000) for s in sims)
        back = deployer.rollback(tmp_path / "run.json", state_dir=tmp_path)
        assert [d.status for d in back.devices] == ["ok", "ok"]
        assert [s.read("F07") for s in sims] == before
        snapshot = report.devices[0].snapshot
        assert snapshot is not None
        with pytest.raises(
            deployer.UsageError,
            match="restoring a snapshot to another device needs to_other_device=True; nothing was sent",
        ):
            deployer.rollback(snapshot, sims[1].url, state_dir=tmp_path)
        deployer.apply(recipe(), sims[0].url, state_dir=tmp_path)
        one = deployer.rollback(snapshot, state_dir=tmp_path)  # the snapshot of the first run: back to before it
        assert [d.status for d in one.devices] == ["ok"] and sims[0].read("F07") == before[0]


def test_diff_and_pull_one_device_and_an_inventory(tmp_path: Path) -> None:
    with Simulators([Simulator(PROFILE) for _ in range(2)]) as sims:
        drift = deployer.diff(recipe(), sims[0].url)
        assert [d.name for d in drift] == ["F07", "base_speed"] and drift[0].desired == "10 s"
        fleet = deployer.diff(recipe(), inventory=devices(sims))
        assert list(fleet) == ["d1", "d2"] and fleet["d1"] == drift
        pulled = deployer.pull("example-inverter", sims[0].url, names=["F07"])
        assert pulled == {"F07": sims[0].read("F07")} and pulled.texts() == {"F07": "5 s"}
        text = pulled.recipe_text(name="copy")
        (tmp_path / "copy.yaml").write_text(text)
        copy = deployer.load_recipe(tmp_path / "copy.yaml")
        assert copy.name == "copy" and deployer.diff(copy) == []  # the recipe names its device
        every = deployer.pull(None, inventory=[{**d, "profile": "example-inverter"} for d in devices(sims)])
        assert set(every) == {"d1", "d2"}
        one = every["d2"]
        assert isinstance(one, dict) and one.device == sims[1].url and len(one) > 5


def test_confirm_and_status(tmp_path: Path) -> None:
    prof = builtin_profile("example-drive")
    drive = deployer.load_recipe(EXAMPLES / "example-drive-axis1.yaml")
    assert deployer.status(tmp_path).runs == []
    with SimulatorThread(prof) as sim:
        waiting: list[str] = []
        result: list[deployer.Report] = []
        run = threading.Thread(
            target=lambda: result.append(
                deployer.apply(
                    drive,
                    sim.url,
                    state_dir=tmp_path,
                    confirm_within="60s",
                    on_confirm_wait=lambda run, deadline: waiting.append(run),
                )
            )
        )
        run.start()
        wait_for(lambda: bool(waiting), "the run to wait")
        assert set(deployer.status(tmp_path).awaiting) == set(waiting)
        assert deployer.confirm(state_dir=tmp_path, wait=True) == waiting[0]
        run.join(timeout=60)
        assert result[0].exit_code == 0 and result[0].devices[0].status == "ok"


def test_the_async_twins_run_in_the_callers_loop(tmp_path: Path) -> None:
    with SimulatorThread(PROFILE) as sim:

        async def inside() -> deployer.Report:
            plan = await deployer.aio.plan(recipe(), sim.url, state_dir=tmp_path)
            return await deployer.aio.apply(plan, state_dir=tmp_path)

        assert asyncio.run(inside()).exit_code == 0
        assert asyncio.run(deployer.aio.diff(recipe(), sim.url)) == []
        assert asyncio.run(deployer.aio.status(tmp_path)).runs == []
