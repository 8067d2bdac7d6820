"""apply end to end against the simulator over TCP: statuses, request counts, snapshots, rollback."""

from __future__ import annotations

import json
import os
from pathlib import Path

import jsonschema
import pytest

from deployer.errors import UsageError
from deployer.execute.device import apply_device
from deployer.execute.read import read_current
from deployer.execute.session import ApplyOptions
from deployer.load import schema
from deployer.planning.model import Target
from deployer.planning.steps import make_plan
from deployer.profile import builtin_profile
from deployer.recipe.loader import load_recipe
from deployer.report import DeviceResult, Report
from deployer.testing.simulator import Faults, Simulator
from deployer.transport.clients import parse_url
from tests.helpers import count, profile_from, run_with

pytestmark = pytest.mark.timeout(60)

STRICT = """\
profile: dev
parameters:
  a: {register: 100, type: uint16, max: 100}
  b: {register: 101, type: uint32, max: 10}      # the device is stricter than the recipe's profile
  c: {register: 103, type: uint16, max: 100}
  d: {register: 104, type: uint16, max: 100}
"""
LOOSE = STRICT.replace("max: 10}      # the device is stricter than the recipe's profile", "max: 1000}")


def recipe_file(tmp: Path, body: str, profile: str = "example-inverter") -> str:
    p = tmp / "r.yaml"
    p.write_text(f"recipe: r\nprofile: {profile}\nparameters:\n{body}")
    return str(p)


def line3(tmp: Path) -> str:
    return recipe_file(
        tmp,
        "  F07: 10 s\n  F08: 8 s\n  stop_mode: coast\n  base_speed: 1750 rpm\n  pid_gain: 2.5\n"
        "  preset[0]: {speed: 300, time: 2 s}\n  control_mode: sensorless-vector\n",
    )


def apply(
    sim: Simulator, recipe_path: str, tmp: Path, unit: int = 1, url_suffix: str = "?timeout=0.3", **opts: object
) -> DeviceResult:
    rec = load_recipe(recipe_path)

    async def body(s: Simulator) -> DeviceResult:
        url = parse_url(s.url + url_suffix)
        return await apply_device(
            rec,
            url,
            unit,
            options=ApplyOptions(state_dir=str(tmp / ".deployer"), backoff=0.01, **opts),  # type: ignore[arg-type]
        )

    return run_with(sim, body)


def test_full_success_minimal_requests_and_snapshot(tmp_path: Path) -> None:
    prof = builtin_profile("example-inverter")
    path = line3(tmp_path)
    sim = Simulator(prof)
    res = apply(sim, path, tmp_path)
    assert res.status == "ok", res
    assert all(p.status == "ok" for p in res.parameters)
    rec = load_recipe(path)
    for d in rec.desired:
        assert sim.read(d.name) == d.registers
    plan = make_plan(rec, Target(None, 1, "example-inverter"))
    # writes: exactly the plan's minimum; reads: identity, one set for the snapshot, one for the read-back
    store = prof.parameter("eeprom_store").address  # the profile's commit action, after verification
    assert [e.address for e in sim.log if e.function == 16][-1] == store
    assert count(sim.log, 16) - 1 == len(plan.writes) == 4
    assert count(sim.log, 3) == 1 + 2 * len(plan.reads)
    assert res.snapshot and os.path.isfile(res.snapshot)
    # the snapshot is a recipe holding the power-on values, saved before the first write
    snap = load_recipe(res.snapshot)
    assert {d.name: d.text for d in snap.desired}["F07"] == "5 s"
    first_write = next(e.time for e in sim.log if e.function == 16)
    assert os.stat(res.snapshot).st_mtime <= first_write
    # the report validates against its schema
    data = Report("r", [res]).to_json()
    jsonschema.validate(data, schema.schema("report"))
    assert data["summary"]["write_requests"] == 5


def test_second_apply_writes_nothing(tmp_path: Path) -> None:
    prof = builtin_profile("example-inverter")
    path = line3(tmp_path)
    sim = Simulator(prof)

    async def body(s: Simulator) -> tuple[DeviceResult, DeviceResult]:
        url = parse_url(s.url)
        rec = load_recipe(path)
        opts = ApplyOptions(state_dir=str(tmp_path / ".d"))
        first = await apply_device(rec, url, 1, options=opts)
        n = len(s.log)
        second = await apply_device(rec, url, 1, options=opts)
        assert count(s.log[n:], 16) == 0
        return first, second

    first, second = run_with(sim, body)
    assert first.status == "ok" and second.status == "ok"
    assert {p.status for p in second.parameters} == {"unchanged"}
    assert second.snapshot is None  # nothing written, nothing to roll back
    assert Report("r", [second]).exit_code == 0


def test_exception_03_mid_request_marks_exactly_that_parameter(tmp_path: Path) -> None:
    device = profile_from(tmp_path, STRICT, "device.yaml")
    loose = tmp_path / "loose.yaml"
    loose.write_text(LOOSE)
    path = recipe_file(tmp_path, "  a: 1\n  b: 50\n  c: 3\n  d: 4\n", profile="loose.yaml")
    sim = Simulator(device)
    res = apply(sim, path, tmp_path)
    st = {p.name: p.status for p in res.parameters}
    assert st == {"a": "ok", "b": "failed", "c": "ok", "d": "ok"}
    b = next(p for p in res.parameters if p.name == "b")
    assert b.error == "exception 03 (illegal data value)" and b.after_raw == (0, 0)
    assert res.status == "partial" and Report("r", [res]).exit_code == 4
    assert sim.read("a") == (1,) and sim.read("b") == (0, 0) and sim.read("c") == (3,) and sim.read("d") == (4,)
    writes = [(e.address, e.count, e.result) for e in sim.log if e.function == 16]
    assert writes == [(100, 5, "exception 03"), (103, 2, "ok")]  # the follow-up carries c and d


def test_on_error_stop_skips_the_rest(tmp_path: Path) -> None:
    device = profile_from(tmp_path, STRICT, "device.yaml")
    (tmp_path / "loose.yaml").write_text(LOOSE)
    path = recipe_file(tmp_path, "  a: 1\n  b: 50\n  c: 3\n  d: 4\n", profile="loose.yaml")
    sim = Simulator(device)
    res = apply(sim, path, tmp_path, on_error="stop")
    assert {p.name: p.status for p in res.parameters} == {"a": "ok", "b": "failed", "c": "skipped", "d": "skipped"}
    assert count(sim.log, 16) == 1 and sim.read("c") == (0,)


def test_busy_then_success(tmp_path: Path) -> None:
    sim = Simulator(builtin_profile("example-inverter"), faults=Faults(busy_first=2))
    res = apply(sim, recipe_file(tmp_path, "  F07: 10 s\n"), tmp_path)
    assert res.status == "ok"
    w = next(r for r in res.requests if r.function == 16)
    assert w.attempts == 3 and w.result == "ok" and w.exception_code is None
    assert [e.result for e in sim.log if e.function == 16] == ["exception 06", "exception 06", "ok", "ok"]


def test_dropped_answers_then_success(tmp_path: Path) -> None:
    sim = Simulator(builtin_profile("example-inverter"), faults=Faults(drop_every=3))
    res = apply(sim, line3(tmp_path), tmp_path, url_suffix="?timeout=0.2&retries=3")
    assert res.status == "ok", res
    assert any(r.attempts > 1 for r in res.requests)
    assert any(e.result == "dropped" for e in sim.log)


def test_disconnect_mid_plan_reconnects(tmp_path: Path) -> None:
    sim = Simulator(builtin_profile("example-inverter"), faults=Faults(disconnect_after=5))
    res = apply(sim, line3(tmp_path), tmp_path, url_suffix="?timeout=0.3&retries=3")
    assert any(e.result == "disconnected" for e in sim.log)
    assert res.status == "ok", res
    rec = load_recipe(line3(tmp_path))
    for d in rec.desired:
        assert sim.read(d.name) == d.registers


def test_device_stops_answering_mid_plan(tmp_path: Path) -> None:
    """Answers stop after the snapshot: the report says unverified/skipped, not ok."""
    faults = Faults()
    sim = Simulator(builtin_profile("example-inverter"), faults=faults)
    rec = load_recipe(line3(tmp_path))

    async def body(s: Simulator) -> DeviceResult:
        async def confirm(plan: object, res: object) -> bool:
            faults.drop_every = 1  # from now on every request is swallowed
            return True

        return await apply_device(
            rec,
            parse_url(s.url + "?timeout=0.1&retries=1"),
            1,
            options=ApplyOptions(state_dir=str(tmp_path / ".d"), backoff=0.01, confirm=confirm),
        )

    res = run_with(sim, body)
    assert res.status == "partial"
    statuses = [p.status for p in res.parameters]
    assert "unverified" in statuses and "ok" not in statuses
    assert Report("r", [res]).exit_code == 4


def test_unreachable_device_exit_3(tmp_path: Path) -> None:
    from tests.conftest import dead_port

    port = dead_port()
    rec = load_recipe(line3(tmp_path))
    import asyncio

    res = asyncio.run(
        apply_device(
            rec,
            parse_url(f"tcp://127.0.0.1:{port}?timeout=0.2"),
            1,
            options=ApplyOptions(state_dir=str(tmp_path / ".d")),
        )
    )
    assert res.status == "unreachable" and res.requests == [] and res.snapshot is None
    assert Report("r", [res]).exit_code == 3


def test_silent_device_is_unreachable_and_nothing_is_written(tmp_path: Path) -> None:
    sim = Simulator(builtin_profile("example-inverter"), faults=Faults(drop_every=1))
    res = apply(sim, line3(tmp_path), tmp_path, url_suffix="?timeout=0.1&retries=1")
    assert res.status == "unreachable" and count(sim.log, 16) == 0
    assert Report("r", [res]).exit_code == 3


def test_broadcast_refused_without_the_flag(tmp_path: Path) -> None:
    sim = Simulator(builtin_profile("example-inverter"))
    with pytest.raises(UsageError, match="broadcast"):
        apply(sim, line3(tmp_path), tmp_path, unit=0)
    assert sim.log == []


def test_broadcast_with_the_flag_is_sent_unverified_and_exit_0(tmp_path: Path) -> None:
    sim = Simulator(builtin_profile("example-inverter"))
    res = apply(sim, recipe_file(tmp_path, "  F07: 10 s\n"), tmp_path, unit=0, allow_broadcast=True)
    assert res.status == "sent" and res.error is None
    assert [(p.status, p.error) for p in res.parameters] == [("unverified", "broadcast: no device answers")]
    assert sim.read("F07") == (0, 1000)
    assert [e.result for e in sim.log] == ["broadcast"]
    report = Report("r", [res])
    assert report.exit_code == 0
    data = report.to_json()
    assert data["summary"]["sent"] == 1 and data["summary"]["ok"] == 0
    jsonschema.validate(data, schema.schema("report"))


def test_broadcast_that_cannot_be_sent_fails_with_exit_4(tmp_path: Path) -> None:
    # three requests (gaps between the registers); the simulator drops the connection at the second,
    # so the third finds no connection and, with no retries, cannot be sent
    prof = profile_from(
        tmp_path,
        "profile: dev\nparameters:\n  a: {register: 0, type: uint16}\n"
        "  b: {register: 10, type: uint16}\n  c: {register: 20, type: uint16}\n",
    )
    sim = Simulator(prof, faults=Faults(disconnect_after=1))
    path = recipe_file(tmp_path, "  a: 1\n  b: 2\n  c: 3\n", profile=str(tmp_path / "dev.yaml"))
    res = apply(sim, path, tmp_path, unit=0, allow_broadcast=True, url_suffix="?timeout=0.3&retries=0")
    assert res.status == "failed"
    assert (res.error or "").startswith("broadcast request at 0x0014 could not be sent: connection lost")
    assert [r.result for r in res.requests] == ["broadcast", "broadcast", "connection lost"]
    by_name = {p.name: p for p in res.parameters}
    assert by_name["a"].status == by_name["b"].status == "unverified"
    assert by_name["c"].status == "unverified"
    assert (by_name["c"].error or "").startswith("broadcast may not have gone out: connection lost")
    # the device saw the first broadcast; the second went into a closing connection (the sender cannot
    # know: nobody answers a broadcast), the third never left
    assert [e.result for e in sim.log] == ["broadcast", "disconnected"]
    assert sim.read("a") == (1,) and sim.read("c") == (0,)
    assert Report("r", [res]).exit_code == 4


def test_identity_mismatch_writes_nothing(tmp_path: Path) -> None:
    prof = builtin_profile("example-inverter")
    sim = Simulator(prof, init={prof.parameter("model_code").address: 0x0311})
    res = apply(sim, line3(tmp_path), tmp_path)
    assert res.status == "failed" and "identity check failed" in (res.error or "")
    assert count(sim.log, 16) == 0


def test_rollback_restores_every_register(tmp_path: Path) -> None:
    prof = builtin_profile("example-inverter")
    sim = Simulator(prof)
    path = line3(tmp_path)

    async def body(s: Simulator) -> None:
        before = s.registers()
        url = parse_url(s.url)
        opts = ApplyOptions(state_dir=str(tmp_path / ".d"))
        res = await apply_device(load_recipe(path), url, 1, options=opts)
        assert res.status == "ok" and s.registers() != before
        assert res.snapshot is not None
        back = await apply_device(load_recipe(res.snapshot), url, 1, options=opts)
        assert back.status == "ok"
        store = prof.parameter("eeprom_store").address  # written by the commit action, by design
        assert {a: v for a, v in s.registers().items() if a != store} == {a: v for a, v in before.items() if a != store}

    run_with(sim, body)


def test_commit_runs_only_after_full_verification(tmp_path: Path) -> None:
    prof = builtin_profile("example-inverter")
    sim = Simulator(prof)
    apply(sim, recipe_file(tmp_path, "  F07: 10 s\n"), tmp_path)
    store = prof.parameter("eeprom_store").address
    assert [e.address for e in sim.log if e.function == 16][-1] == store


def test_read_current_and_pull_round_trip(tmp_path: Path) -> None:
    from deployer.recipe.model import DeviceSpec
    from deployer.recipe.text import recipe_text

    prof = builtin_profile("example-inverter")
    sim = Simulator(prof)

    async def body(s: Simulator) -> None:
        url = parse_url(s.url)
        names = [p.name for p in prof.parameters if p.readable and p.writable]
        cur = await read_current(prof, names, url, 1)
        text = recipe_text(
            "example-inverter",
            {prof.parameter(n): v for n, v in cur.items()},
            name="pulled",
            device=DeviceSpec(s.url, 1),
        )
        f = tmp_path / "pulled.yaml"
        f.write_text(text)
        n = len(s.log)
        res = await apply_device(load_recipe(str(f)), url, 1, options=ApplyOptions(state_dir=str(tmp_path / ".d")))
        assert res.status == "ok" and count(s.log[n:], 16) == 0  # applies back as a no-op

    run_with(sim, body)


def test_audit_and_report_files_from_the_cli(tmp_path: Path) -> None:
    from deployer.cli import main
    from deployer.testing.simulator import SimulatorThread

    with SimulatorThread(builtin_profile("example-inverter")) as sim:
        report = tmp_path / "report.json"
        with pytest.raises(SystemExit) as exc:
            main(
                [
                    "apply",
                    line3(tmp_path),
                    "--device",
                    sim.url,
                    "--yes",
                    "--report",
                    str(report),
                    "--state-dir",
                    str(tmp_path / ".d"),
                ]
            )
    assert exc.value.code == 0
    data = json.loads(report.read_text())
    jsonschema.validate(data, schema.schema("report"))
    assert data["devices"][0]["status"] == "ok"
    events = [json.loads(line) for line in (tmp_path / ".d" / "audit.jsonl").read_text().splitlines()]
    # the journal: the run, the device before its first write (with its snapshot), its outcome, the run's end
    assert [e["event"] for e in events] == ["run-started", "device-started", "device-finished", "run-finished"]
    assert len({e["run"] for e in events}) == 1
    assert events[1]["snapshot"] == data["devices"][0]["snapshot"] and len(events[1]["plan_sha256"]) == 64
    assert events[2]["status"] == "ok" and events[-1]["exit_code"] == 0
    assert events[0]["user"] == events[-1]["user"] != str(os.getuid())  # a name, not the uid


def test_device_without_fc16_gets_one_fc06_per_register(tmp_path: Path) -> None:
    prof = profile_from(
        tmp_path,
        "profile: old\nlimits: {write_function: 6}\nparameters:\n"
        "  speed: {register: 10, type: uint16}\n  ramp: {register: 11, type: uint32}\n",
        "old.yaml",
    )
    path = recipe_file(tmp_path, "  speed: 5\n  ramp: 70000\n", profile="old.yaml")
    sim = Simulator(prof)
    res = apply(sim, path, tmp_path)
    assert res.status == "ok", res
    assert [(e.function, e.address, e.values) for e in sim.log if e.function in (6, 16)] == [
        (6, 10, [5]),
        (6, 11, [1]),
        (6, 12, [4464]),
    ]
    assert sim.read("ramp") == (1, 4464)


def test_silence_mid_plan_then_the_read_back_tells_what_took(tmp_path: Path) -> None:
    """The 2nd write gets no answer (no retries): the 1st is verified ok, the 2nd unverified, the rest skipped."""
    faults = Faults()
    sim = Simulator(builtin_profile("example-inverter"), faults=faults)
    rec = load_recipe(line3(tmp_path))

    async def body(s: Simulator) -> DeviceResult:
        async def confirm(plan: object, res: object) -> bool:
            faults.drop_every = len(s.log) + 2  # the request after the first write
            return True

        return await apply_device(
            rec,
            parse_url(s.url + "?timeout=0.2&retries=0"),
            1,
            options=ApplyOptions(state_dir=str(tmp_path / ".d"), confirm=confirm),
        )

    res = run_with(sim, body)
    plan = make_plan(
        rec,
        Target(None, 1, "example-inverter"),
        {p.name: p.before_raw for p in res.parameters if p.before_raw is not None},
    )
    first, second, *rest = plan.writes
    st = {p.name: p for p in res.parameters}
    assert all(st[n].status == "ok" for n in first.parameters)
    assert all(
        st[n].status == "unverified"
        and "device stopped answering" in (st[n].error or "")
        and "reads back" in (st[n].error or "")
        for n in second.parameters
    )
    assert all(st[n].status == "skipped" and st[n].after_raw is not None for r in rest for n in r.parameters)
    assert res.status == "partial" and Report("r", [res]).exit_code == 4
