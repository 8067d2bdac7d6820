"""Fleet work done once (issue #30): plans shared between devices holding the same values, their digests
made without serialising each plan again, and results of devices that ended ok kept small."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import pytest

import deployer
from deployer.execute.device import Planners, Shared, parameter_results, plan_digest
from deployer.planning.model import Pacing, Target
from deployer.planning.planfile import plan_to_json
from deployer.planning.steps import Planner, make_plan
from deployer.profile import builtin_profile
from deployer.report import DeviceResult, ParameterResult, RequestRecord
from tests.helpers import cli
from tests.test_fleet import fleet, inventory, names, recipe

pytestmark = pytest.mark.timeout(120)
PROFILE = builtin_profile("example-inverter")


def test_a_shared_plan_is_the_devices_own_plan_and_digest(tmp_path: Path) -> None:
    rec = deployer.load_recipe(recipe(tmp_path))
    shared = Shared(Planner(rec))
    held = {"F07": (0, 500), "F08": (0, 1200), "stop_mode": (0,)}
    for url, unit in (("tcp://10.0.0.1:502", 1), ("rtu:///dev/ttyUSB0?baud=9600", 7)):
        target = Target(url, unit, "example-inverter")
        plan, entry = shared.plan(target, held, False)
        own = make_plan(rec, target, held)
        assert plan == own
        assert (
            entry.digest(target)
            == plan_digest(own)
            == hashlib.sha256(
                json.dumps(plan_to_json(own), sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode()
            ).hexdigest()
        )
    a, entry_a = shared.plan(Target("tcp://a:1", 1, "x"), held, False)
    b, entry_b = shared.plan(Target("tcp://b:1", 1, "x"), held, False)
    assert a.steps is b.steps and entry_a is entry_b  # planned once
    other, _ = shared.plan(Target("tcp://a:1", 1, "x"), {**held, "F08": (0, 1)}, False)
    assert other.parameters != a.parameters and shared.plan(other.device, {**held, "F08": (0, 1)}, False)[1].digest(
        other.device
    ) == plan_digest(other)
    assert other == make_plan(rec, Target("tcp://a:1", 1, "x"), {**held, "F08": (0, 1)})
    assert Shared(Planner(rec, write_all=True)).plan(Target("tcp://a:1", 1, "x"), held, False)[0] == make_plan(
        rec, Target("tcp://a:1", 1, "x"), held, write_all=True
    )


def test_a_small_result_keeps_what_the_summary_and_the_journal_need() -> None:
    d = DeviceResult("a", "tcp://127.0.0.1:1", 1, "example-inverter", status="ok")
    d.parameters = [
        ParameterResult("F07", 0x100, 2, "10 s", (0, 1000), (0, 500), (0, 1000), "ok"),
        ParameterResult("F08", 0x102, 2, "12 s", (0, 1200), (0, 1200), (0, 1200), "unchanged"),
        ParameterResult("stop_mode", 0x104, 1, "coast", (1,), (0,), (0,), "mismatch"),
    ]
    d.requests = [RequestRecord(3, 0x100, 5), RequestRecord(16, 0x100, 2), RequestRecord(3, 0x100, 5)]
    small = d.small()
    assert small.parameters == [] and small.requests == []
    for attr in ("write_requests", "read_requests", "request_count", "changed_count", "failed_count", "written"):
        assert getattr(small, attr) == getattr(d, attr), attr
    assert small.written == ("F07", "stop_mode") and small.changed_count == 1 and small.failed_count == 1


def test_a_fleet_keeps_ok_devices_small_and_its_report_and_journal_whole(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    with fleet(3) as sims:
        inv = inventory(tmp_path, {n: s.url for n, s in zip(names(3), sims, strict=True)})
        code, out, err = cli(
            capsys,
            "apply",
            recipe(tmp_path),
            "--inventory",
            inv,
            "--yes",
            "--report",
            str(tmp_path / "r.json"),
            "--state-dir",
            str(tmp_path / "s"),
        )
    assert code == 0, err
    doc = json.loads((tmp_path / "r.json").read_text())
    assert [len(d["parameters"]) for d in doc["devices"]] == [3, 3, 3]
    assert all(p["status"] == "ok" for d in doc["devices"] for p in d["parameters"])
    lines = [json.loads(x) for x in (tmp_path / "s" / "audit.jsonl").read_text().splitlines()]
    finished = next(x for x in lines if x["event"] == "run-finished")
    assert [d["written"] for d in finished["devices"]] == [["F07", "F08", "stop_mode"]] * 3
    s = doc["summary"]  # the table and the totals, from the small results, say what the file says
    ids = s["requests"] - s["write_requests"] - s["read_requests"]
    assert (
        f"3 devices: 3 ok; {s['requests']} requests ({s['read_requests']} reads, {s['write_requests']} writes, "
        f"{ids} device identification)"
        in out
        and ids == 3
    )
    for d in doc["devices"]:
        assert re.search(rf"{d['name']}\s+ok\s+3\s+0\s+{len(d['requests'])}\s", out), out


def test_a_broadcasts_plan_is_not_shared_with_a_device_that_answers(tmp_path: Path) -> None:
    rec = deployer.load_recipe(recipe(tmp_path))
    shared = Shared(Planner(rec))
    held = {"F07": (0, 500), "F08": (0, 1200), "stop_mode": (0,)}
    for unit in (1, 0, 1):
        target = Target("tcp://10.0.0.1:502", unit, "example-inverter")
        plan, entry = shared.plan(target, held, False)
        assert plan == make_plan(rec, target, held)
        assert entry.digest(target) == plan_digest(plan)
        assert all(s.kind == "write" for s in plan.steps) == (unit == 0)  # nobody answers a broadcast's reads


def test_apply_many_keeps_ok_devices_small_when_asked(tmp_path: Path) -> None:
    import asyncio

    from deployer.execute.session import ApplyOptions
    from deployer.fleet.inventory import fleet_jobs, load_inventory
    from deployer.fleet.rollout import apply_many
    from deployer.testing.simulator import Faults

    seen: dict[str, int] = {}
    with fleet(3, {1: Faults(fail_registers=frozenset({PROFILE.parameter("F08").address}))}) as sims:
        inv = inventory(tmp_path, {n: s.url for n, s in zip(names(3), sims, strict=True)})
        jobs = fleet_jobs(load_inventory(inv), deployer.load_recipe(recipe(tmp_path)), None)
        report = asyncio.run(
            apply_many(
                jobs,
                keep_results=False,
                on_done=lambda r: seen.update({r.name: len(r.parameters)}),
                options=ApplyOptions(state_dir=str(tmp_path / "s")),
            )
        )
    assert seen == {"d00": 3, "d01": 3, "d02": 3}  # whole when the report file takes them
    assert [(d.status, len(d.parameters), d.tally is not None) for d in report.devices] == [
        ("ok", 0, True),
        ("partial", 3, False),
        ("ok", 0, True),
    ]  # a device that needs a look keeps its detail
    assert report.summary()["write_requests"] == sum(d.write_requests for d in report.devices) > 0


def test_a_devices_report_line_is_its_json_whatever_its_texts() -> None:
    from deployer.report import device_json

    d = DeviceResult(
        'dé"v',
        "tcp://127.0.0.1:1",
        1,
        "p",
        status="partial",
        error='"parameters": [] \u2028 x',
        notices=["ünïcode", "\x00"],
    )
    d.parameters = [
        ParameterResult("F07", 0x100, 2, "10 s", (0, 1000), (0, 500), (0, 1000), "ok"),
        ParameterResult('n"ame\\', 0, 1, 'tëxt "q"', [7], None, [7], "mismatch", 'reads back "8"\n'),  # type: ignore[arg-type]
        ParameterResult("c", 5, 1, "on", (1,), (0,), None, "unverified", "x", register_type="coil"),
        ParameterResult("s", 6, 1, "5", (), (), (), "skipped", None, register_type="input"),
    ]
    d.requests = [RequestRecord(3, 0, 5, "exception", 2, 2)]
    for _ in range(2):  # the second time from the caches
        assert device_json(d) == json.dumps(d.to_json()).encode()
    assert device_json(d.small()) == json.dumps(d.small().to_json()).encode()


def test_a_stream_the_disk_refused_for_a_while_ends_whole(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Appends that fail (a full disk) leave no line cut short and are written again once the disk takes them."""
    import errno
    import os

    from deployer.fleet import livereport
    from deployer.fleet.inventory import fleet_jobs, load_inventory
    from deployer.report import Report, read_report

    inv = inventory(tmp_path, {n: f"tcp://127.0.0.1:{1000 + i}" for i, n in enumerate(names(3))})
    jobs = fleet_jobs(load_inventory(inv), deployer.load_recipe(recipe(tmp_path)), None)
    path = str(tmp_path / "r.json")
    live = livereport.LiveReport(path, "r.yaml", jobs, run={"id": "x"})
    real_write, fails = os.write, [2]

    def full(fd: int, data: bytes | memoryview) -> int:
        if fd == live._fd and fails[0] > 0:
            fails[0] -= 1
            real_write(fd, bytes(data[:7]))  # part of it went out before the disk was full
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    real_writev = getattr(os, "writev", None)  # Windows has none: the stream writes with os.write there

    def full_v(fd: int, pieces: list[bytes]) -> int:
        if fd == live._fd and fails[0] > 0:
            return full(fd, b"".join(pieces))
        assert real_writev is not None
        return int(real_writev(fd, pieces))

    monkeypatch.setattr(os, "write", full)
    if real_writev is not None:
        monkeypatch.setattr(os, "writev", full_v)  # the stream writes its lines with os.writev
    results = []
    for j in jobs:
        r = DeviceResult(j.name, "u", 1, "example-inverter", status="ok")
        r.parameters = [ParameterResult("F07", 0x100, 2, "10 s", (0, 1000), (0, 500), (0, 1000), "ok")]
        results.append(r)
        live.finished(r)
    live.stop()  # what is pending is written: the disk takes it the third time
    doc = read_report(path)
    assert [d["status"] for d in doc["devices"]] == ["ok"] * 3 and fails == [0]
    live.close(Report("r.yaml", results))  # (stop twice is fine)
    assert json.loads(Path(path).read_text())["devices"] == [r.to_json() for r in results]


# ---- the fast paths of a fleet's device, each against the slow path it stands for ----------------------------


def _varied() -> DeviceResult:
    """A device's result with one parameter of every kind and outcome."""
    d = DeviceResult(
        'dev "1"',
        "tcp://127.0.0.1:1",
        1,
        "example-drive",
        status="partial",
        error="x; y",
        notices=["motor_poles takes effect after a power cycle"],
        profile_ref="example-drive",
        recipe="/r.yaml",
        batch=2,
        seen="2024-01-01T00:00:00Z",
        identity={"vendor": "ACME"},
    )
    d.parameters = [
        ParameterResult("u16", 0x100, 1, "10 s", (1000,), (500,), (1000,), "ok"),
        ParameterResult("u32", 0x101, 2, "100000 count", (1, 34464), (0, 0), (1, 34464), "ok"),
        ParameterResult(
            "f32",
            0x103,
            2,
            "2500.5 rpm",
            (0x4000, 0x451C),
            (0, 0x453B),
            (0, 0x453B),
            "mismatch",
            "reads back 3000 rpm (0000h 453Bh)",
        ),
        ParameterResult("field", 0x200, 1, "ccw", (0x0002,), (0x0030,), (0x0032,), "ok"),
        ParameterResult(
            "name",
            0x201,
            8,
            'X "1" #',
            (0x5820, 0x2231, 0x2220, 0x2320, 0x2020, 0x2020, 0x2020, 0x2020),
            (0x4158,) * 8,
            (0x4158,) * 8,
            "failed",
            "exception 04 (server device failure)",
        ),
        ParameterResult("relay", 19, 1, "true", (1,), (0,), (1,), "ok", register_type="coil"),
        ParameterResult("temp", 8, 1, "21.5 degC", (215,), (215,), (215,), "unchanged", register_type="input"),
        ParameterResult("password", 0x20, 1, "4", (4,), None, None, "unverified", "write-only: cannot be read back"),
        ParameterResult("later", 0x21, 1, "1", (1,), (0,), None, "skipped"),
        ParameterResult("same", 0x23, 1, "3", (3,), (3,), (3,), "ok"),  # written, the value it held already
    ]
    d.requests = [
        RequestRecord(3, 0x100, 60),
        RequestRecord(16, 0x201, 8, "exception", 4),
        RequestRecord(43, 0, 1, "no response", None, 2),
        RequestRecord(15, 19, 1),
    ]
    return d


def test_a_report_line_follows_every_field_of_its_parameters_and_requests(monkeypatch: pytest.MonkeyPatch) -> None:
    """The line's entries are kept by all they say: a field changed after an entry was kept makes a new entry."""
    import dataclasses

    from deployer import report
    from deployer.report import device_json

    d = _varied()
    for _ in range(2):  # the second time from the kept entries
        assert device_json(d) == json.dumps(d.to_json()).encode()
    changed: dict[type, object] = {int: 7, str: "changed", tuple: (9, 9)}
    for i in range(len(d.parameters)):
        for f in dataclasses.fields(ParameterResult):
            if f.name == "parameter":
                continue
            e = _varied()
            old = getattr(e.parameters[i], f.name)
            new = (
                "mismatch"
                if f.name == "status"
                else "coil"
                if f.name == "register_type"
                else changed.get(type(old), "an error")
            )
            setattr(e.parameters[i], f.name, new)
            assert device_json(e) == json.dumps(e.to_json()).encode(), (i, f.name)
    for f in dataclasses.fields(RequestRecord):
        e = _varied()
        setattr(e.requests[1], f.name, "no response" if f.name == "result" else 5)
        assert device_json(e) == json.dumps(e.to_json()).encode(), f.name
    e = _varied()  # registers as lists, as code may give them: not kept, the same line
    e.parameters.append(ParameterResult("listed", 0x22, 1, "7", [7], [6], [7], "ok"))  # type: ignore[arg-type]
    assert device_json(e) == json.dumps(e.to_json()).encode()
    monkeypatch.setattr(report, "_ROWS_KEPT", 4)  # the table starts again when full
    e = _varied()
    e.parameters[0].after_raw = (4242,)
    assert device_json(e) == json.dumps(e.to_json()).encode() and len(report._ROWS) <= 4 + len(e.parameters)
    assert device_json(d.small()) == json.dumps(d.small().to_json()).encode()


def test_a_small_result_counts_every_outcome_as_the_full_one() -> None:
    d = _varied()
    small = d.small()
    for attr in ("write_requests", "read_requests", "request_count", "changed_count", "failed_count", "written"):
        assert getattr(small, attr) == getattr(d, attr), attr
    assert small.written == ("u16", "u32", "f32", "field", "name", "relay", "password", "same")
    assert (small.changed_count, small.failed_count) == (4, 3)
    again = small.small()
    assert again.tally == small.tally and again.parameters == [] and again.requests == []
    assert {f: getattr(small, f) for f in ("name", "status", "notices", "identity", "batch", "seen")} == {
        f: getattr(d, f) for f in ("name", "status", "notices", "identity", "batch", "seen")
    }


def test_a_recipes_results_are_made_as_their_fields_say(tmp_path: Path) -> None:
    """The shared positional arguments follow ParameterResult's fields (a field moved would shift them)."""
    (tmp_path / "d.yaml").write_text(
        "recipe: d\nprofile: example-drive\nparameters:\n  control_mode: speed\n"
        "  encoder_resolution: 262144 count\n  direction: ccw\n  brake_mode: dynamic\n"
        "  axis_name: X1\n  speed_limit: 2500.5 rpm\n"
    )
    rec = deployer.load_recipe(str(tmp_path / "d.yaml"))
    got = parameter_results(rec)
    assert list(got) == [d.name for d in rec.desired]
    for d in rec.desired:
        r = got[d.name]
        assert r == ParameterResult(
            name=d.name,
            address=d.parameter.address,
            count=d.parameter.count,
            desired=d.text,
            desired_raw=d.registers,
            register_type=d.parameter.register_type,
        )
        assert r.parameter is d.parameter and r.status == "skipped"
        assert r.before_raw is None and r.after_raw is None and r.error is None
    assert parameter_results(rec)[rec.desired[0].name] is not got[rec.desired[0].name]  # each device its own


def test_verify_compares_the_registers_then_the_fields_bits() -> None:
    from deployer.execute.verify import PENDING, _verify

    prof = builtin_profile("example-drive")
    brake = prof.parameter("brake_mode")  # bits 4..5 of its register

    def outcome(desired: object, got: tuple[int, ...], name: str = "brake_mode") -> tuple[str, str | None]:
        p = prof.parameter(name)
        r = ParameterResult(name, p.address, 1, "x", desired, status="unverified", error=PENDING)  # type: ignore[arg-type]
        _verify({name: r}, prof, {name: got}, {name})
        return r.status, r.error

    assert brake.mask == 0x30
    assert outcome((0x0020,), (0x0020,)) == ("ok", None)
    assert outcome((0x0020,), (0x0121,)) == ("ok", None)  # other bits of the register are not the field's
    assert outcome((0x0020,), (0x0010,))[0] == "mismatch"
    assert outcome([8], (8,), "motor_poles") == ("ok", None)  # registers as a list
    assert outcome((8,), (9,), "motor_poles") == ("mismatch", "reads back 9 (0009h)")


def test_devices_holding_other_values_get_their_own_plan_and_snapshot(tmp_path: Path) -> None:
    from deployer.state.snapshot import snapshot_values

    rec = deployer.load_recipe(recipe(tmp_path))
    shared = Shared(Planner(rec))
    held = {"F07": (0, 500), "F08": (0, 1200), "stop_mode": (0,)}
    other = {**held, "F07": (0, 700)}
    _, a = shared.plan(Target("tcp://a:1", 1, "x"), held, False)
    assert a.snapshot_values(rec.profile, held) == snapshot_values(rec.profile, held)
    _, b = shared.plan(Target("tcp://b:1", 1, "x"), other, False)
    assert b is not a and b.snapshot_values(rec.profile, other) == snapshot_values(
        rec.profile, other
    ) != a.snapshot_values(rec.profile, held)
    assert shared.plan(Target("tcp://c:1", 1, "x"), dict(held), False)[1] is a


def test_a_fleets_snapshots_are_what_each_device_held(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Devices holding the same values share their snapshot's values text: each file is still its device's own,
    as ``snapshot_text`` makes it from the values the report says the device held before."""
    import time

    from deployer.state.snapshot import snapshot_text
    from deployer.testing.simulator import Simulator
    from tests.helpers import Simulators

    prof = builtin_profile("example-drive")
    (tmp_path / "d.yaml").write_text(
        "recipe: d\nprofile: example-drive\nparameters:\n  control_mode: speed\n"
        "  encoder_resolution: 262144 count\n  enable_on_power_up: true\n"
        "  direction: ccw\n  brake_mode: dynamic\n  jog_steps: 3.5 mm\n"
        "  axis_name: X1\n  speed_limit: 2500.5 rpm\n"
    )

    def holding(name: str, words: list[int]) -> dict[int, int]:
        return {prof.parameter(name).key + i: w for i, w in enumerate(words)}

    sims = [
        Simulator(prof),
        Simulator(prof, init=holding("axis_name", [0x5932] + [0x2020] * 7)),  # "Y2"
        Simulator(prof),
        Simulator(prof, init=holding("speed_limit", [0, 0x4500])),
    ]  # 2048 rpm, CDAB
    with Simulators(sims):
        inv = inventory(tmp_path, {n: s.url for n, s in zip(names(4), sims, strict=True)})
        code, _, err = cli(
            capsys,
            "apply",
            str(tmp_path / "d.yaml"),
            "--inventory",
            inv,
            "--yes",
            "--report",
            str(tmp_path / "r.json"),
            "--state-dir",
            str(tmp_path / "s"),
        )
    assert code == 0, err
    texts = []
    for dev in json.loads((tmp_path / "r.json").read_text())["devices"]:
        held = {p["name"]: tuple(p["before_raw"]) for p in dev["parameters"]}
        path = dev["snapshot"]
        text = Path(path).read_text()
        taken = re.search(r'^  taken: "(.*)"$', text, re.M)
        assert taken is not None
        assert text == snapshot_text(
            prof,
            held,
            name=dev["name"],
            url=dev["url"] + "?retries=0",  # the inventory's retries: a rollback talks to it as the run did
            unit=1,
            taken=time.strptime(taken[1], "%Y-%m-%dT%H:%M:%SZ"),
            applied=str(tmp_path / "d.yaml"),
            label="d",
            path=path,
        )
        texts.append(text.split("  registers:", 1)[1])
    assert texts[0] == texts[2] and len({texts[0], texts[1], texts[3]}) == 3


def test_devices_that_taught_the_same_limits_share_one_recipe_and_its_plans(tmp_path: Path) -> None:
    from deployer.profile import profile_ref
    from deployer.state import learned

    rec = deployer.load_recipe(recipe(tmp_path))
    state = str(tmp_path / "s")
    for device, limits in (
        ("a#unit1", {"max_write_registers": 2}),
        ("b#unit1", {"max_write_registers": 2}),
        ("c#unit1", {"write_function": 6}),
        ("d#unit1", {"max_write_registers": 123}),
    ):
        learned.remember(state, learned.Entry(profile_ref(rec.profile), device, limits, "refused", "2024-01-01"))
    planners = Planners()

    def taught(device: str) -> deployer.Recipe:
        entry = learned.lookup(state, profile_ref(rec.profile), device)
        return rec if entry is None else planners.over_limits(rec, entry)

    a, b, c = taught("a#unit1"), taught("b#unit1"), taught("c#unit1")
    assert a is b is not rec and c is not a
    assert a.profile.limits.max_write_registers == 2 and c.profile.limits.write_function == 6
    assert taught("d#unit1") is rec and taught("e#unit1") is rec  # nothing tighter, nothing taught
    held = {"F07": (0, 500), "F08": (0, 1), "stop_mode": (0,)}
    none = Pacing()
    plan, entry = planners.shared(a, write_all=False, commit=True, pacing=none).plan(
        Target("tcp://a:1", 1, "x"), held, False
    )
    assert plan == make_plan(a, Target("tcp://a:1", 1, "x"), held)
    assert all(w.count <= 2 for w in plan.writes)
    assert (
        planners.shared(b, write_all=False, commit=True, pacing=none).plan(Target("tcp://b:1", 1, "x"), held, False)[1]
        is entry
    )
