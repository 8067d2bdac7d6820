"""Fleet work done once (issue #30): plans shared between devices holding the same values, their digests
made without serialising each plan again, and results of devices that ended ok kept small."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import pytest

import deployer
from deployer.execute.device import _facts, _planned, _shared, plan_digest
from deployer.planning.model import Target
from deployer.planning.planfile import plan_to_json
from deployer.planning.planner import make_plan
from deployer.profile import builtin_profile
from deployer.report import DeviceResult, ParameterResult, RequestRecord
from tests.helpers import cli
from tests.test_fleet import fleet, inventory, names, recipe

pytestmark = pytest.mark.timeout(120)
PROFILE = builtin_profile("example-inverter")


def test_a_shared_plan_is_the_devices_own_plan_and_digest(tmp_path: Path) -> None:
    rec = deployer.load_recipe(recipe(tmp_path))
    shared = _shared(rec)
    held = {"F07": (0, 500), "F08": (0, 1200), "stop_mode": (0,)}
    for url, unit in (("tcp://10.0.0.1:502", 1), ("rtu:///dev/ttyUSB0?baud=9600", 7)):
        target = Target(url, unit, "example-inverter")
        plan, planned = _planned(rec, target, held, False, shared)
        own = make_plan(rec, target, held, reads=shared.reads)
        assert plan == own
        assert planned.digest(target) == plan_digest(own) == hashlib.sha256(
            json.dumps(plan_to_json(own), sort_keys=True).encode()).hexdigest()
        assert planned.facts == _facts(own, rec.profile)
    a, shared_a = _planned(rec, Target("tcp://a:1", 1, "x"), held, False, shared)
    b, shared_b = _planned(rec, Target("tcp://b:1", 1, "x"), held, False, shared)
    assert a.writes is b.writes and shared_a is shared_b  # planned once
    other, _ = _planned(rec, Target("tcp://a:1", 1, "x"), {**held, "F08": (0, 1)}, False, shared)
    assert other.parameters != a.parameters and _planned(rec, other.device, {**held, "F08": (0, 1)}, False, shared)[
        1].digest(other.device) == plan_digest(other)
    assert other == make_plan(rec, Target("tcp://a:1", 1, "x"), {**held, "F08": (0, 1)}, reads=shared.reads)
    assert _planned(rec, Target("tcp://a:1", 1, "x"), held, True, shared)[0] == make_plan(
        rec, Target("tcp://a:1", 1, "x"), held, write_all=True, reads=shared.reads)


def test_a_small_result_keeps_what_the_summary_and_the_journal_need() -> None:
    d = DeviceResult("a", "tcp://127.0.0.1:1", 1, "example-inverter", status="ok")
    d.parameters = [ParameterResult("F07", 0x100, 2, "10 s", (0, 1000), (0, 500), (0, 1000), "ok"),
                    ParameterResult("F08", 0x102, 2, "12 s", (0, 1200), (0, 1200), (0, 1200), "unchanged"),
                    ParameterResult("stop_mode", 0x104, 1, "coast", (1,), (0,), (0,), "mismatch")]
    d.requests = [RequestRecord(3, 0x100, 5), RequestRecord(16, 0x100, 2), RequestRecord(3, 0x100, 5)]
    small = d.small()
    assert small.parameters == [] and small.requests == []
    for attr in ("write_requests", "read_requests", "request_count", "changed_count", "failed_count", "written"):
        assert getattr(small, attr) == getattr(d, attr), attr
    assert small.written == ("F07", "stop_mode") and small.changed_count == 1 and small.failed_count == 1


def test_a_fleet_keeps_ok_devices_small_and_its_report_and_journal_whole(capsys: pytest.CaptureFixture[str],
                                                                         tmp_path: Path) -> None:
    with fleet(3) as sims:
        inv = inventory(tmp_path, {n: s.url for n, s in zip(names(3), sims, strict=True)})
        code, out, err = cli(capsys, "apply", recipe(tmp_path), "--inventory", inv, "--yes", "--report",
                             str(tmp_path / "r.json"), "--state-dir", str(tmp_path / "s"))
    assert code == 0, err
    doc = json.loads((tmp_path / "r.json").read_text())
    assert [len(d["parameters"]) for d in doc["devices"]] == [3, 3, 3]
    assert all(p["status"] == "ok" for d in doc["devices"] for p in d["parameters"])
    lines = [json.loads(x) for x in (tmp_path / "s" / "audit.jsonl").read_text().splitlines()]
    finished = next(x for x in lines if x["event"] == "run-finished")
    assert [d["written"] for d in finished["devices"]] == [["F07", "F08", "stop_mode"]] * 3
    s = doc["summary"]  # the table and the totals, from the small results, say what the file says
    assert f"3 devices: 3 ok; {s['write_requests']} write requests and {s['read_requests']} read requests" in out
    for d in doc["devices"]:
        assert re.search(rf"{d['name']}\s+ok\s+3\s+0\s+{len(d['requests'])}\s", out), out


def test_a_broadcasts_plan_is_not_shared_with_a_device_that_answers(tmp_path: Path) -> None:
    rec = deployer.load_recipe(recipe(tmp_path))
    shared = _shared(rec)
    held = {"F07": (0, 500), "F08": (0, 1200), "stop_mode": (0,)}
    for unit in (1, 0, 1):
        target = Target("tcp://10.0.0.1:502", unit, "example-inverter")
        plan, planned = _planned(rec, target, held, False, shared)
        assert plan == make_plan(rec, target, held, reads=shared.reads)
        assert planned.digest(target) == plan_digest(plan)


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
        report = asyncio.run(apply_many(jobs, keep_results=False, on_done=lambda r: seen.update({r.name: len(
            r.parameters)}), options=ApplyOptions(state_dir=str(tmp_path / "s"))))
    assert seen == {"d00": 3, "d01": 3, "d02": 3}  # whole when the report file takes them
    assert [(d.status, len(d.parameters), d.tally is not None) for d in report.devices] == [
        ("ok", 0, True), ("partial", 3, False), ("ok", 0, True)]  # a device that needs a look keeps its detail
    assert report.summary()["write_requests"] == sum(d.write_requests for d in report.devices) > 0


def test_a_devices_report_line_is_its_json_whatever_its_texts() -> None:
    from deployer.report import device_json

    d = DeviceResult("dé\"v", "tcp://127.0.0.1:1", 1, "p", status="partial", error='"parameters": [] \u2028 x',
                     notices=["ünïcode", "\x00"])
    d.parameters = [
        ParameterResult("F07", 0x100, 2, "10 s", (0, 1000), (0, 500), (0, 1000), "ok"),
        ParameterResult("n\"ame\\", 0, 1, "tëxt \"q\"", [7], None, [7], "mismatch", "reads back \"8\"\n"),  # type: ignore[arg-type]
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

    real_writev = os.writev

    def full_v(fd: int, pieces: list[bytes]) -> int:
        if fd == live._fd and fails[0] > 0:
            return full(fd, b"".join(pieces))
        return real_writev(fd, pieces)

    monkeypatch.setattr(os, "write", full)
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
