"""Fleets against many simulated devices on loopback: staged rollouts, failure budgets, retries, fleet reads."""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import jsonschema
import pytest

from deployer.errors import UsageError
from deployer.fleet.inventory import FleetDevice, Inventory, not_ok, select
from deployer.fleet.rollout import batch_sizes, failure_budget
from deployer.load import schema
from deployer.profile import builtin_profile
from deployer.report import read_report
from deployer.testing.simulator import Faults, Simulator
from tests.conftest import dead_port
from tests.helpers import Simulators, cli

pytestmark = pytest.mark.timeout(120)
PROFILE = builtin_profile("example-inverter")
F08 = PROFILE.parameter("F08").address
RECIPE = "recipe: line\nprofile: example-inverter\nparameters:\n  F07: 10 s\n  F08: 12 s\n  stop_mode: coast\n"
WANT = {"F07": (0, 1000), "F08": (0, 1200), "stop_mode": (1,)}


def recipe(tmp: Path) -> str:
    p = tmp / "r.yaml"
    p.write_text(RECIPE)
    return str(p)


def inventory(tmp: Path, urls: dict[str, str], groups: dict[str, str] | None = None, extra: str = "") -> str:
    lines = ["defaults: {timeout: 1.0, retries: 0}", "devices:"]
    for name, url in urls.items():
        g = f", groups: [{groups[name]}]" if groups and name in groups else ""
        lines.append(f"  {name}: {{url: '{url}'{g}}}")
    p = tmp / "inventory.yaml"
    p.write_text("\n".join(lines) + "\n" + extra)
    return str(p)


def holds_recipe(sim: Simulator, unit: int = 1) -> bool:
    return all(sim.read(n, unit) == v for n, v in WANT.items())


@contextmanager
def fleet(n: int, faults: dict[int, Faults] | None = None) -> Iterator[list[Simulator]]:
    faults = faults or {}
    with Simulators([Simulator(PROFILE, faults=faults.get(i)) for i in range(n)]) as sims:
        yield sims


def names(n: int) -> list[str]:
    return [f"d{i:02d}" for i in range(n)]


# ---- selection and staging (pure) ----------------------------------------------------------------


def test_limit_takes_names_groups_globs_exclusions_and_reports(tmp_path: Path) -> None:
    inv = Inventory(
        "inv.yaml",
        tuple(
            FleetDevice(n, "tcp://h", groups=(g,))
            for n, g in [("press-1", "line3"), ("press-2", "line3"), ("saw-1", "line4")]
        ),
    )
    assert [d.name for d in select(inv, "line3")] == ["press-1", "press-2"]
    assert [d.name for d in select(inv, "saw-1, press-2")] == ["press-2", "saw-1"]  # inventory order
    assert [d.name for d in select(inv, "press-*")] == ["press-1", "press-2"]
    assert [d.name for d in select(inv, "line*,!press-1")] == ["press-2", "saw-1"]
    assert [d.name for d in select(inv, "!line3")] == ["saw-1"]
    with pytest.raises(UsageError, match="'pres-1' matches no device"):
        select(inv, "pres-1")
    report = tmp_path / "report.json"

    def report_of(*devices: tuple[str, str]) -> str:  # a report of version 1, as small as one is valid
        return json.dumps(
            {
                "schema": "deployer.report/1",
                "recipe": None,
                "devices": [
                    {
                        "name": n,
                        "url": "tcp://h",
                        "unit": 1,
                        "profile": "p",
                        "status": s,
                        "snapshot": None,
                        "requests": [],
                        "parameters": [],
                    }
                    for n, s in devices
                ],
                "summary": {
                    "devices": len(devices),
                    "ok": 0,
                    "partial": 0,
                    "failed": 0,
                    "unreachable": 0,
                    "write_requests": 0,
                    "read_requests": 0,
                    "seconds": 0,
                },
            }
        )

    report.write_text(report_of(("press-1", "ok"), ("press-2", "skipped"), ("saw-1", "partial")))
    assert not_ok(str(report)) == ["press-2", "saw-1"]
    assert [d.name for d in select(inv, f"@{report}")] == ["press-2", "saw-1"]
    assert [d.name for d in select(inv, f"@{report},!saw*")] == ["press-2"]
    report.write_text(report_of(("saw-1", "ok")))
    with pytest.raises(UsageError, match="nothing to retry"):
        select(inv, f"@{report}")


def test_batches_follow_ansible_serial_and_failure_budgets() -> None:
    assert batch_sizes("1,10%,100%", 50) == [1, 5, 44]
    assert batch_sizes("1,50%", 50) == [1, 25, 24]
    assert batch_sizes("2", 5) == [2, 2, 1]  # the last size repeats
    assert batch_sizes("1%", 10) == [1] * 10  # a percentage never rounds to zero
    assert batch_sizes(None, 3) == [3]
    assert failure_budget("2", 50) == 2 and failure_budget("10%", 50) == 5 and failure_budget(None, 5) is None
    for bad in ("0", "x", "150%", "-1"):
        with pytest.raises(UsageError, match="not a positive count"):
            batch_sizes(bad, 5)


# ---- apply over an inventory -------------------------------------------------------------------


def test_fifty_devices_three_faulty(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    # d07: dead (nothing listens), d23: rejects F08 (partial), d41: slow (but within the timeout)
    with fleet(50, {23: Faults(fail_registers=frozenset({F08})), 41: Faults(latency_ms=150)}) as sims:
        urls = {n: s.url for n, s in zip(names(50), sims, strict=True)}
        urls["d07"] = f"tcp://127.0.0.1:{dead_port()}"
        report_file = tmp_path / "report.json"
        code, out, err = cli(
            capsys,
            "apply",
            recipe(tmp_path),
            "--inventory",
            inventory(tmp_path, urls),
            "--yes",
            "--parallel",
            "16",
            "--json",
            "--report",
            str(report_file),
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 4
        report = json.loads(out)
        jsonschema.validate(report, schema.schema("report"))
        assert report == json.loads(report_file.read_text())
        by = {d["name"]: d for d in report["devices"]}
        assert list(by) == names(50)
        assert by["d07"]["status"] == "unreachable" and "connection refused" in by["d07"]["error"]
        assert not any(r["function"] == 16 for r in by["d07"]["requests"])
        bad = {p["name"]: p for p in by["d23"]["parameters"]}
        assert by["d23"]["status"] == "partial"
        assert bad["F08"]["status"] == "failed" and "exception 04" in bad["F08"]["error"]
        assert bad["F07"]["status"] == "ok" and bad["stop_mode"]["status"] == "ok"
        assert by["d41"]["status"] == "ok" and by["d41"]["seconds"] > 0.15 * 4
        healthy = [n for n in names(50) if n not in ("d07", "d23")]
        assert all(by[n]["status"] == "ok" for n in healthy)
        for n, sim in zip(names(50), sims, strict=True):
            if n in healthy:
                assert holds_recipe(sim), n
        assert report["summary"] == {
            **report["summary"],
            "devices": 50,
            "ok": 48,
            "partial": 1,
            "unreachable": 1,
            "failed": 0,
            "skipped": 0,
        }
        assert "d07: unreachable" in err and "d23: partial" in err  # a line per device without a terminal
        assert err.count("\n") >= 50


def test_failing_canary_stops_the_rollout_before_any_other_device_hears_a_request(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    with fleet(10, {0: Faults(fail_registers=frozenset({F08}))}) as sims:
        urls = {n: s.url for n, s in zip(names(10), sims, strict=True)}
        code, out, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path),
            "--inventory",
            inventory(tmp_path, urls),
            "--yes",
            "--batch",
            "1,50%",
            "--parallel",
            "8",
            "--json",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 4
        report = json.loads(out)
        jsonschema.validate(report, schema.schema("report"))
        assert report["devices"][0]["status"] == "partial"
        assert sims[0].log and all(not s.log for s in sims[1:])  # not a single request to the others
        for d in report["devices"][1:]:
            assert d["status"] == "skipped" and d["requests"] == []
            assert "the canary batch 1 did not end ok (d00 partial)" in d["error"]
            assert all(p["status"] == "skipped" for p in d["parameters"])
        assert report["summary"]["skipped"] == 9


def test_batches_run_one_after_the_other(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with fleet(7) as sims:
        urls = {n: s.url for n, s in zip(names(7), sims, strict=True)}
        code, _, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path),
            "--inventory",
            inventory(tmp_path, urls),
            "--yes",
            "--batch",
            "1,2",
            "--parallel",
            "8",
            "--json",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 0
        spans = [(min(e.time for e in s.log), max(e.time for e in s.log)) for s in sims]
        batches = [[0], [1, 2], [3, 4], [5, 6]]
        for before, after in itertools.pairwise(batches):
            assert max(spans[i][1] for i in before) <= min(spans[i][0] for i in after)


def test_max_failures_stops_starting_devices(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    bad = {1, 3, 4, 6, 8}
    with fleet(12, {i: Faults(fail_registers=frozenset({F08})) for i in bad}) as sims:
        urls = {n: s.url for n, s in zip(names(12), sims, strict=True)}
        code, out, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path),
            "--inventory",
            inventory(tmp_path, urls),
            "--yes",
            "--max-failures",
            "2",
            "--parallel",
            "2",
            "--json",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 4
        devices = json.loads(out)["devices"]
        failed = [d["name"] for d in devices if d["status"] in ("failed", "partial")]
        skipped = [d for d in devices if d["status"] == "skipped"]
        assert 2 <= len(failed) <= 2 + 1  # the budget, plus at most the other device in flight
        assert skipped and all("--max-failures 2" in d["error"] for d in skipped)
        for d, sim in zip(devices, sims, strict=True):
            if d["status"] == "skipped":
                assert not sim.log
        # the devices after the skipped ones were skipped too: no device starts once the budget is spent
        first = devices.index(skipped[0])
        assert all(d["status"] == "skipped" for d in devices[first:])


def test_an_unreachable_device_spends_the_failure_budget_and_batches_are_recorded(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # the run: --batch 1,20%,100% --max-failures 1 over ten devices, one of them dead (d01, batch 2)
    with fleet(10) as sims:
        urls = {n: s.url for n, s in zip(names(10), sims, strict=True)}
        urls["d01"] = f"tcp://127.0.0.1:{dead_port()}"
        report_file, state = tmp_path / "run.json", tmp_path / "s"
        code, out, err = cli(
            capsys,
            "apply",
            recipe(tmp_path),
            "--inventory",
            inventory(tmp_path, urls),
            "--yes",
            "--batch",
            "1,20%,100%",
            "--max-failures",
            "1",
            "--parallel",
            "1",
            "--json",
            "--report",
            str(report_file),
            "--state-dir",
            str(state),
        )
        assert code == 4
        report = json.loads(out)
        jsonschema.validate(report, schema.schema("report"))
        assert report == json.loads(report_file.read_text())
        by = {d["name"]: d for d in report["devices"]}
        # every device has its batch: 1 (the canary), 2 (20% of 10), 3 (the rest), skipped ones too
        assert {n: d["batch"] for n, d in by.items()} == {"d00": 1, "d01": 2, "d02": 2, **{n: 3 for n in names(10)[3:]}}
        assert by["d00"]["status"] == "ok" and by["d01"]["status"] == "unreachable"
        # the dead device spent the budget: nothing after it started (d02 came after it on --parallel 1)
        assert [n for n, d in by.items() if d["status"] == "skipped"] == names(10)[2:]
        assert all("1 device did not end ok (--max-failures 1" in by[n]["error"] for n in names(10)[2:])
        assert all(not s.log for s in sims[2:])
        # the progress lines and the audit log say the batch
        assert "d00: ok (batch 1, 2 writes)" in err and "d01: unreachable (batch 2, 0 writes)" in err
        lines = [json.loads(x) for x in (state / "audit.jsonl").read_text().splitlines()]
        started = [x for x in lines if x["event"] == "device-started"]
        assert [(x["name"], x["batch"]) for x in started] == [("d00", 1)]
        assert [(x["name"], x["batch"]) for x in lines if x["event"] == "device-finished"] == [("d00", 1)]
        finished = next(x for x in lines if x["event"] == "run-finished")
        assert {d["name"]: (d["batch"], d["status"]) for d in finished["devices"]} == {
            n: (by[n]["batch"], by[n]["status"]) for n in names(10)
        }
        # a skipped device is not a failure: with a budget of 2, the dead one alone does not stop the rollout
        code, out, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path),
            "--inventory",
            inventory(tmp_path, urls),
            "--yes",
            "--batch",
            "1,20%,100%",
            "--max-failures",
            "2",
            "--parallel",
            "1",
            "--json",
            "--state-dir",
            str(state),
        )
        assert code == 4
        assert [d["status"] for d in json.loads(out)["devices"]].count("ok") == 9


def test_retry_from_the_report_touches_exactly_the_devices_that_failed(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    with fleet(6, {2: Faults(fail_registers=frozenset({F08})), 4: Faults(busy_first=100)}) as sims:
        urls = {n: s.url for n, s in zip(names(6), sims[:6], strict=True)}
        inv = inventory(tmp_path, urls)
        report_file = str(tmp_path / "run1.json")
        code, _, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path),
            "--inventory",
            inv,
            "--yes",
            "--report",
            report_file,
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 4 and sorted(not_ok(report_file)) == ["d02", "d04"]
        for s in sims:  # the faults are fixed on site
            s.faults.fail_registers, s.faults.busy_first = frozenset(), 0
            s.log.clear()
        code, out, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path),
            "--inventory",
            inv,
            "--yes",
            "--json",
            "--limit",
            f"@{report_file}",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 0
        assert [d["name"] for d in json.loads(out)["devices"]] == ["d02", "d04"]
        assert [i for i, s in enumerate(sims) if s.log] == [2, 4]
        assert all(holds_recipe(s) for s in sims)


def test_report_file_survives_kill_9(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """Killed mid-run: the report names the finished devices as they ended, the rest 'not finished'."""
    with fleet(6, {i: Faults(latency_ms=60) for i in range(6)} | {1: Faults(fail_registers=frozenset({F08}))}) as sims:
        urls = {n: s.url for n, s in zip(names(6), sims[:6], strict=True)}
        inv = inventory(tmp_path, urls)
        report_file = tmp_path / "report.json"
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "deployer",
                "apply",
                recipe(tmp_path),
                "--inventory",
                inv,
                "--yes",
                "--parallel",
                "1",
                "--report",
                str(report_file),
                "--state-dir",
                str(tmp_path / "s"),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:  # until two devices have finished
                if (
                    report_file.exists()
                    and sum(
                        d["status"] not in ("skipped", "interrupted") for d in read_report(str(report_file))["devices"]
                    )
                    >= 2
                ):
                    break
                time.sleep(0.01)
            os.kill(proc.pid, signal.SIGKILL)
        finally:
            proc.wait(timeout=30)
        assert report_file.read_text().startswith('{"schema": "deployer.report-stream/3"')  # the run's stream
        data = read_report(str(report_file))
        jsonschema.validate(data, schema.schema("report"))
        status = {d["name"]: d["status"] for d in data["devices"]}
        assert status["d00"] == "ok" and status["d01"] == "partial"
        unfinished = [d for d in data["devices"] if d["status"] == "skipped"]
        assert unfinished and all(d["error"] == "not finished (interrupted run)" for d in unfinished)
        # the device being written when the run died, if the file got to say so: interrupted, with its snapshot
        assert all(d["snapshot"] for d in data["devices"] if d["status"] == "interrupted")
        assert not_ok(str(report_file)) == [n for n in names(6) if status[n] != "ok"]
        assert "d00" not in not_ok(str(report_file))
        # deployer report reads the stream as the run's report: the devices that need a look, the totals
        code, out, err = cli(capsys, "report", str(report_file))
        assert code == 0, err
        assert "d01" in out and "partial" in out and f"{len(unfinished)} skipped" in out


def test_devices_on_one_gateway_are_never_served_at_once(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    gw = Simulator(PROFILE, listen="rtu+tcp://127.0.0.1:0", units=(1, 2, 3, 4), faults=Faults(latency_ms=5))
    with Simulators([gw, Simulator(PROFILE), Simulator(PROFILE)]) as (gateway, a, b):
        inv = tmp_path / "inventory.yaml"
        inv.write_text(
            "devices:\n"
            + "".join(f"  g{u}: {{url: '{gateway.url}', unit: {u}}}\n" for u in (1, 2, 3, 4))
            + f"  a: {{url: '{a.url}'}}\n  b: {{url: '{b.url}'}}\n"
        )
        code, _, _ = cli(
            capsys,
            "apply",
            recipe(tmp_path),
            "--inventory",
            str(inv),
            "--yes",
            "--json",
            "--parallel",
            "8",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 0
        assert all(holds_recipe(gateway, u) for u in (1, 2, 3, 4)) and holds_recipe(a) and holds_recipe(b)
        times = {u: [e.time for e in gateway.log if e.unit == u] for u in (1, 2, 3, 4)}
        spans = sorted((min(t), max(t)) for t in times.values())
        for (_, end), (start, _) in itertools.pairwise(spans):
            assert end < start  # one unit's session ends before the next one's first request
        assert [e.unit for e in sorted(gateway.log, key=lambda e: e.time)] == sorted(e.unit for e in gateway.log)


# ---- reading fleets: plan, diff, pull ---------------------------------------------------------


def test_fleet_diff_names_exactly_the_drifted_devices(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with fleet(8) as sims:
        urls = {n: s.url for n, s in zip(names(8), sims, strict=True)}
        inv = inventory(tmp_path, urls)
        assert (
            cli(capsys, "apply", recipe(tmp_path), "--inventory", inv, "--yes", "--state-dir", str(tmp_path / "s"))[0]
            == 0
        )
        code, out, _ = cli(capsys, "diff", recipe(tmp_path), "--inventory", inv)
        assert code == 0 and "drift on 0 of 8 devices" in out
        sims[2].write("F07", (0, 999))
        sims[5].write("stop_mode", (0,))
        for s in sims:
            s.log.clear()
        code, out, _ = cli(capsys, "diff", recipe(tmp_path), "--inventory", inv)
        assert code == 2
        assert "drift on 2 of 8 devices: d02, d05" in out
        assert out.splitlines()[:6] == [
            "6 devices: as the recipe says",
            "  d00, d01, d03, d04, d06, d07",
            "1 device: F07 9.99 s (recipe 10 s)",
            "  d02",
            "1 device: stop_mode ramp (recipe coast)",
            "  d05",
        ]
        code, out, _ = cli(capsys, "diff", recipe(tmp_path), "--inventory", inv, "--per-device")
        rows = [line.split() for line in out.splitlines() if line.split()[:1] in (["d02"], ["d05"])]
        assert rows == [["d02", "F07", "10", "s", "9.99", "s", "drift"], ["d05", "stop_mode", "coast", "ramp", "drift"]]
        code, out, _ = cli(capsys, "diff", recipe(tmp_path), "--inventory", inv, "--json")
        data = json.loads(out)
        assert code == 2 and data["drifted"] == ["d02", "d05"]
        assert [d["name"] for d in data["devices"][5]["drift"]] == ["stop_mode"]
        assert all(e.function == 3 for s in sims for e in s.log)  # diff only reads


def test_fleet_plan_and_diff_group_identical_changes(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with fleet(7) as sims:
        urls = {n: s.url for n, s in zip(names(6), sims[:6], strict=True)}
        urls["dead-1"] = f"tcp://127.0.0.1:{dead_port()}"
        urls["dead-2"] = f"tcp://127.0.0.1:{dead_port()}"
        inv = inventory(tmp_path, urls, extra=f"  d06: {{url: '{sims[6].url}', parameters: {{F08: 20 s}}}}\n")
        for n, v in WANT.items():  # d05 already holds the recipe
            sims[5].write(n, v)
        sims[4].write("F08", (0, 1200))  # d04 needs only two of the three
        code, out, err = cli(capsys, "plan", recipe(tmp_path), "--inventory", inv, "--limit", "!d06")
        assert code == 3, err
        assert out.splitlines() == [
            "4 devices: F07 5 s -> 10 s, F08 5 s -> 12 s, stop_mode ramp -> coast",
            "  d00..d03",
            "1 device: F07 5 s -> 10 s, stop_mode ramp -> coast",
            "  d04",
            "1 device: as desired",
            "  d05",
            "2 unreachable: dead-1, dead-2",
            "5 of 8 devices would change (5 write requests; 33 requests in all, 5 writes to non-volatile memory); "
            "--per-device shows each device's plan",
        ]
        code, out, err = cli(capsys, "plan", recipe(tmp_path), "--inventory", inv, "--limit", "d0*", "--per-device")
        assert code == 0 and out.count("current -> desired") == 6 and "d05" not in out.splitlines()[0]
        assert (
            "6 of 7 devices would change (6 write requests; 39 requests in all, 6 writes to non-volatile memory): "
            "d00, d01, d02, d03, d04, d06\n"
        ) in out
        # a change list longer than a line goes into a table under its group
        many = tmp_path / "many.yaml"
        many.write_text(RECIPE + "  base_speed: 1600 rpm\n  torque_limit: 120 %\n")
        code, out, err = cli(capsys, "plan", str(many), "--inventory", inv, "--limit", "d00,d01")
        assert code == 0, err
        assert out.splitlines()[0] == "2 devices: 5 changes" and out.splitlines()[-2] == "  d00, d01"
        # the drift matrix: the drifted devices as columns, '=' where a device holds its recipe's value
        assert (
            cli(
                capsys,
                "apply",
                recipe(tmp_path),
                "--inventory",
                inv,
                "--limit",
                "d0*",
                "--yes",
                "--state-dir",
                str(tmp_path / "s"),
            )[0]
            == 0
        )
        sims[1].write("F07", (0, 999))
        sims[3].write("F07", (0, 999))
        sims[6].write("stop_mode", (0,))
        code, out, _ = cli(capsys, "diff", recipe(tmp_path), "--inventory", inv, "--limit", "d0*", "--matrix")
        assert code == 2
        assert [" ".join(ln.split()) for ln in out.splitlines()] == [
            "parameter recipe d01 d03 d06",
            "F07 10 s 9.99 s 9.99 s =",
            "stop_mode coast = = ramp",
            "drift on 3 of 7 devices: d01, d03, d06",
        ]
        code, out, _ = cli(capsys, "diff", recipe(tmp_path), "--inventory", inv, "--limit", "d0*")
        assert code == 2 and out.splitlines()[:4] == [
            "4 devices: as the recipe says",
            "  d00, d02, d04, d05",
            "2 devices: F07 9.99 s (recipe 10 s)",
            "  d01, d03",
        ]
        code, _, err = cli(capsys, "plan", recipe(tmp_path), "--per-device")
        assert code == 1 and "--per-device needs --inventory" in err


def test_fleet_plan_and_pull(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with fleet(3) as sims:
        urls = {n: s.url for n, s in zip(names(3), sims, strict=True)}
        urls["dead"] = f"tcp://127.0.0.1:{dead_port()}"
        inv = inventory(tmp_path, urls, groups={"d00": "a", "d01": "a", "d02": "b", "dead": "c"})
        sims[1].write("F07", (0, 1000))
        sims[1].write("F08", (0, 1200))
        sims[1].write("stop_mode", (1,))
        code, out, _ = cli(
            capsys, "plan", recipe(tmp_path), "--inventory", inv, "--limit", "a,b", "--detailed-exitcode"
        )
        assert code == 2 and (
            "2 of 3 devices would change (2 write requests; 15 requests in all, 2 writes to non-volatile memory)" in out
        )
        assert "2 devices: F07 5 s -> 10 s, F08 5 s -> 12 s, stop_mode ramp -> coast\n  d00, d02\n" in out
        code, out, _ = cli(
            capsys, "plan", recipe(tmp_path), "--inventory", inv, "--limit", "d01", "--detailed-exitcode", "--json"
        )
        assert code == 0 and all(
            s["kind"] not in ("write", "unlock", "commit") for s in json.loads(out)["devices"][0]["plan"]["steps"]
        )
        code, _, err = cli(capsys, "plan", recipe(tmp_path), "--inventory", inv, "--detailed-exitcode")
        assert code == 3 and "dead: unreachable" in err
        assert not any(e.function == 16 for s in sims for e in s.log)  # plan only reads

        folder = tmp_path / "pulled"
        code, _, err = cli(
            capsys, "pull", "--profile", "example-inverter", "--inventory", inv, "--limit", "a,b", "-o", str(folder)
        )
        assert code == 0 and "3 recipes written" in err
        assert sorted(os.listdir(folder)) == ["d00.yaml", "d01.yaml", "d02.yaml"]
        assert "F07: 10 s" in (folder / "d01.yaml").read_text() and "F07: 5 s" in (folder / "d00.yaml").read_text()
        assert cli(capsys, "validate", *(str(folder / f) for f in os.listdir(folder)))[0] == 0
        code, _, err = cli(capsys, "pull", "--profile", "example-inverter", "--inventory", inv, "-o", str(folder))
        assert code == 3 and "dead" in err
        code, _, err = cli(capsys, "pull", "--profile", "example-inverter", "--inventory", inv, "-o", "/proc/x")
        assert code == 1 and "cannot write recipes into /proc/x" in err


def test_a_fleet_plan_counts_the_requests_its_apply_sends(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    # every device's checks, writes, read-back and commit: what the devices log during the apply that follows
    with fleet(3) as sims:
        inv = inventory(tmp_path, {n: s.url for n, s in zip(names(3), sims, strict=True)})
        for n, v in WANT.items():  # d01 holds the recipe already: its checks only
            sims[1].write(n, v)
        code, out, err = cli(capsys, "plan", recipe(tmp_path), "--inventory", inv)
        assert code == 0, err
        said = re.search(r"\((\d+) write requests?; (\d+) requests in all, (\d+) writes? to non-volatile memory\)", out)
        assert said is not None, out
        for s in sims:
            s.log.clear()
        code, _, err = cli(capsys, "apply", recipe(tmp_path), "--inventory", inv, "--yes", "--state-dir", str(tmp_path))
        assert code == 0, err
        logged = [e for s in sims for e in s.log]
        commits = [e for e in logged if e.function == 16 and e.address == 0x08FF]  # the profile's commit: 0x0900
        assert (len(logged), len(commits)) == (int(said[2]), int(said[3])) == (15, 2)
        assert len([e for e in logged if e.function == 16]) - len(commits) == int(said[1])


def test_the_report_file_lists_every_device_before_the_first_one_starts(tmp_path: Path) -> None:
    import deployer

    seen: list[dict[str, str]] = []
    with fleet(3) as sims:
        urls = {n: s.url for n, s in zip(names(3), sims, strict=True)}
        rec = deployer.load_recipe(recipe(tmp_path))
        report_file = tmp_path / "r.json"

        def started(name: str) -> None:
            if not seen:
                seen.append({d["name"]: d.get("error") for d in read_report(str(report_file))["devices"]})

        report = deployer.apply(
            rec,
            inventory=inventory(tmp_path, urls),
            report_path=report_file,
            on_start=started,
            state_dir=tmp_path / "s",
        )
        assert seen == [{n: "not finished (interrupted run)" for n in names(3)}]
        assert report.exit_code == 0 and json.loads(report_file.read_text())["summary"]["ok"] == 3


def test_open_file_limit_is_raised_or_the_run_refused_up_front(tmp_path: Path) -> None:
    import resource

    urls = {n: f"tcp://127.0.0.1:{dead_port()}?timeout=0.2&retries=0" for n in names(3)}
    inv = inventory(tmp_path, urls)

    def run(soft: int, hard: int) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [
                sys.executable,
                "-m",
                "deployer",
                "apply",
                recipe(tmp_path),
                "--inventory",
                inv,
                "--yes",
                "--parallel",
                "8",
                "--state-dir",
                str(tmp_path / "s"),
            ],
            capture_output=True,
            text=True,
            timeout=60,
            stdin=subprocess.DEVNULL,
            preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard)),
        )

    low = run(40, 50)  # 3 sockets + headroom do not fit under a hard limit of 50
    assert low.returncode == 1 and "allows 50 (ulimit -Hn)" in low.stderr and "Traceback" not in low.stderr
    raised = run(40, 4096)  # the soft limit goes up towards the hard one; the devices are simply dead
    assert raised.returncode == 3, raised.stderr
    assert raised.stderr.count("unreachable") >= 3


def test_without_a_terminal_one_plain_unwrapped_line_per_device(tmp_path: Path) -> None:
    long = [f"line3-press-{i}-in-the-north-hall-next-to-the-big-door" for i in range(3)]
    urls = {n: f"tcp://127.0.0.1:{dead_port()}?timeout=0.2&retries=0" for n in long}
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "deployer",
            "apply",
            recipe(tmp_path),
            "--inventory",
            inventory(tmp_path, urls),
            "--yes",
            "--state-dir",
            str(tmp_path / "s"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
        stdin=subprocess.DEVNULL,
    )
    assert done.returncode == 3, done.stderr
    lines = [x for x in done.stderr.splitlines() if x.startswith("line3-")]
    assert sorted(x.split(":")[0] for x in lines) == long  # one line each, for logs and CI
    for x in lines:  # the whole error on the device's line (a console would wrap at 80 columns)
        assert x.startswith(f"{x.split(':')[0]}: unreachable (0 writes) - ") and x.endswith("connection refused"), x


def test_python_api_one_device_and_a_cheap_import(tmp_path: Path) -> None:
    import deployer

    proc = subprocess.run(
        [sys.executable, "-c", "import sys, deployer; print('deployer.api' in sys.modules, 'pymodbus' in sys.modules)"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.stdout.split() == ["False", "False"]  # the API (and pymodbus) load on first use
    with fleet(1) as (sim,):
        rec = deployer.load_recipe(recipe(tmp_path))
        plan = deployer.plan(rec, sim.url)
        assert [w.parameters for w in plan.writes] == [("F07", "F08", "stop_mode")]
        assert all(e.function in (3, 43) for e in sim.log)  # plan and diff only read
        assert [d.name for d in deployer.diff(rec, sim.url)] == ["F07", "F08", "stop_mode"]
        report = deployer.apply(rec, sim.url, state_dir=tmp_path / "s")
        assert report.exit_code == 0 and holds_recipe(sim)
        assert deployer.diff(rec, sim.url) == []
        assert deployer.pull("example-inverter", sim.url)["F07"] == (0, 1000)
        inline = deployer.recipe_from("example-inverter", {"F07": "20 s"})
        assert [(d.name, d.registers) for d in inline.desired] == [("F07", (0, 2000))]
        with pytest.raises(deployer.InputError, match="unknown parameter 'F7'"):
            deployer.recipe_from("example-inverter", {"F7": "20 s"})


def test_bad_fleet_options_are_refused_before_anything_is_sent(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    with fleet(2) as sims:
        inv = inventory(tmp_path, {n: s.url for n, s in zip(names(2), sims, strict=True)})
        state = tmp_path / "s"
        for args, message in [
            (["--batch", "0"], "--batch: '0' is not a positive count"),
            (["--max-failures", "x%"], "--max-failures: 'x%'"),
            (["--limit", "d9*"], "'d9*' matches no device name or group"),
            (["--limit", f"@{tmp_path / 'none.json'}"], "cannot read the report"),
            (["--report", "/proc/deployer-report.json"], "cannot write the report"),
        ]:
            code, _, err = cli(
                capsys, "apply", recipe(tmp_path), "--inventory", inv, "--yes", "--state-dir", str(state), *args
            )
            assert code == 1 and message in err, err
        code, _, err = cli(capsys, "apply", recipe(tmp_path), "--device", sims[0].url, "--yes", "--batch", "1")
        assert code == 1 and "need --inventory" in err
        assert not any(s.log for s in sims)
        assert not (state / "audit.jsonl").exists()  # not even a journal line: nothing started


def test_rollback_of_a_fleet_run_takes_a_limit(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with fleet(3) as sims:
        inv = inventory(tmp_path, {n: s.url for n, s in zip(names(3), sims, strict=True)})
        run = str(tmp_path / "run.json")
        assert (
            cli(
                capsys,
                "apply",
                recipe(tmp_path),
                "--inventory",
                inv,
                "--yes",
                "--report",
                run,
                "--state-dir",
                str(tmp_path / "s"),
            )[0]
            == 0
        )
        for s in sims:
            s.log.clear()
        code, out, err = cli(
            capsys,
            "rollback",
            "--report",
            run,
            "--limit",
            "d0[12]",
            "--yes",
            "--json",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 0, out + err
        assert [d["name"] for d in json.loads(out)["devices"]] == ["d01", "d02"]
        assert not sims[0].log and holds_recipe(sims[0])
        assert sims[1].read("F07") == sims[2].read("F07") == (0, 500)  # back to what they held


def test_declining_one_device_of_a_fleet_skips_only_that_one(tmp_path: Path) -> None:
    import asyncio

    import deployer
    from deployer.execute.session import ApplyOptions
    from deployer.fleet.rollout import apply_many

    with fleet(3) as sims:
        rec = deployer.load_recipe(recipe(tmp_path))
        jobs = deployer.api.commands.fleet_jobs(
            rec, inventory(tmp_path, {n: s.url for n, s in zip(names(3), sims, strict=True)})
        )

        async def confirm(plan: object, res: deployer.DeviceResult) -> bool:
            return res.name != "d01"

        report = asyncio.run(apply_many(jobs, options=ApplyOptions(state_dir=str(tmp_path / "s"), confirm=confirm)))
        assert [d.status for d in report.devices] == ["ok", "skipped", "ok"]
        assert report.devices[1].error == "not written: declined at the confirmation prompt"
        assert report.exit_code == 4 and not any(e.function == 16 for e in sims[1].log)


def test_live_progress_on_a_terminal_and_the_summary(tmp_path: Path) -> None:
    from tests.test_cli import _run_on_a_terminal

    with fleet(6, {i: Faults(latency_ms=40) for i in range(6)} | {2: Faults(fail_registers=frozenset({F08}))}) as sims:
        inv = inventory(tmp_path, {n: s.url for n, s in zip(names(6), sims, strict=True)})
        code, out = _run_on_a_terminal(
            [
                "apply",
                recipe(tmp_path),
                "--inventory",
                inv,
                "--yes",
                "--parallel",
                "2",
                "--state-dir",
                str(tmp_path / "s"),
            ],
            b"",
            prompt=b"never asked",
        )
        assert code == 4, out
        assert "in flight" in out and "ETA" in out and "writing: d0" in out  # the live display
        out = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", out)  # colours and cursor movements
        rows = {
            line.split()[0]: line.split()[1:]
            for line in out.splitlines()
            if line.strip().startswith("d0") and len(line.split()) >= 6
        }
        assert rows["d02"][:3] == ["partial", "2", "1"]  # status, changed, failed
        assert rows["d00"][:3] == ["ok", "3", "0"]
        assert "6 devices: 5 ok, 1 partial" in out


def test_each_distinct_recipe_is_checked_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import deployer
    from deployer.fleet import inventory as fleet_module
    from deployer.fleet.inventory import fleet_jobs, load_inventory

    calls: dict[str, int] = {"load_recipe": 0, "with_overrides": 0}
    for name in calls:
        real = getattr(fleet_module, name)

        def counting(*a: object, _real: object = real, _name: str = name, **k: object) -> object:
            calls[_name] += 1
            return _real(*a, **k)  # type: ignore[operator]

        monkeypatch.setattr(fleet_module, name, counting)
    other = tmp_path / "other.yaml"  # another device type: the same parameters, other registers
    other.write_text(
        "profile: other\nparameters:\n  F07: {register: 10, type: uint32, unit: s, scale: 0.01}\n"
        "  F08: {register: 12, type: uint32, unit: s, scale: 0.01}\n"
        "  stop_mode: {register: 14, type: uint16, values: {ramp: 0, coast: 1}}\n"
    )
    lines = ["devices:"]
    for i in range(60):
        extra = ""
        if i % 3 == 1:
            extra = ", parameters: {F07: 7 s}"
        elif i % 3 == 2:
            extra = ", profile: other.yaml" + (", parameters: {F07: 8 s}" if i % 2 else "")
        lines.append(f"  d{i:02d}: {{url: 'tcp://127.0.0.1:{1000 + i}'{extra}}}")
    (tmp_path / "inv.yaml").write_text("\n".join(lines) + "\n")
    jobs = fleet_jobs(load_inventory(tmp_path / "inv.yaml"), deployer.load_recipe(recipe(tmp_path)), None)
    assert len(jobs) == 60
    # one reload for the other profile; overrides: F07 7 s on the base, F07 8 s on the other profile
    assert calls == {"load_recipe": 1, "with_overrides": 2}
    by = {j.name: j.recipe for j in jobs}
    assert by["d00"] is by["d03"] and by["d01"] is by["d04"] and by["d02"] is not by["d00"]
    assert {d.name: d.registers for d in by["d05"].desired}["F07"] == (0, 800)
    assert by["d05"].profile.id == "other" and by["d02"].profile is by["d05"].profile


def test_the_report_files_first_state_is_every_device_not_finished(tmp_path: Path) -> None:
    from deployer.fleet.inventory import fleet_jobs, load_inventory
    from deployer.fleet.livereport import NOT_FINISHED, LiveReport
    from deployer.fleet.rollout import skipped_result
    from deployer.recipe.loader import load_recipe
    from deployer.report import read_report

    inv = tmp_path / "inventory.yaml"
    inv.write_text(
        "devices:\n"
        + "".join(f"  {n}: {{url: 'tcp://127.0.0.1:{1000 + i}'}}\n" for i, n in enumerate(names(3)))
        + f"  {names(4)[3]}: {{url: 'tcp://127.0.0.1:1003', parameters: {{F07: 12 s}}}}\n"
    )  # own values
    jobs = fleet_jobs(load_inventory(str(inv)), load_recipe(recipe(tmp_path)), None)
    assert jobs[3].recipe is not jobs[0].recipe
    live = LiveReport(str(tmp_path / "r.json"), "r.yaml", jobs, [2, 2], run={"id": "run-1"})
    live.stop()
    lines = (tmp_path / "r.json").read_text().splitlines()
    head = json.loads(lines[0])
    assert set(head.pop("profiles")) == {"example-inverter"}  # what the report says of its profile, once
    assert head == {"schema": "deployer.report-stream/3", "recipe": "r.yaml", "run": {"id": "run-1"}}
    # one small line per device: the skipped device without its parameters (the journal has what recovery needs)
    small = [
        skipped_result(j, NOT_FINISHED, b, parameters=False).to_json() for j, b in zip(jobs, (1, 1, 2, 2), strict=True)
    ]
    assert [json.loads(x) for x in lines[1:]] == small
    assert all(len(x) < 300 + len(str(tmp_path)) * 2 for x in lines[1:])  # name, url, paths: no parameters
    doc = read_report(str(tmp_path / "r.json"))  # read as the document it stands for
    jsonschema.validate(doc, schema.schema("report"))
    assert doc["devices"] == small and doc["run"] == {"id": "run-1"}
    assert doc["summary"] | {"seconds": 0} == {
        "devices": 4,
        "ok": 0,
        "sent": 0,
        "partial": 0,
        "failed": 0,
        "unreachable": 0,
        "skipped": 4,
        "rolled-back": 0,
        "interrupted": 0,
        "write_requests": 0,
        "read_requests": 0,
        "seconds": 0,
    }


def test_a_device_is_reported_done_once_its_journal_line_is_on_disk(tmp_path: Path) -> None:
    from deployer.execute.session import ApplyOptions
    from deployer.fleet.inventory import fleet_jobs, load_inventory
    from deployer.fleet.rollout import apply_many
    from deployer.recipe.loader import load_recipe

    state = tmp_path / "s"
    seen: dict[str, list[str]] = {}

    def on_done(r: object) -> None:  # what the journal says when the report and the progress hear of a device
        name = getattr(r, "name", "")
        lines = [json.loads(x) for x in (state / "audit.jsonl").read_text().splitlines()]
        seen[name] = [x["event"] for x in lines if x.get("name") == name]

    with fleet(6) as sims:
        inv = inventory(tmp_path, {n: s.url for n, s in zip(names(6), sims, strict=True)})
        jobs = fleet_jobs(load_inventory(inv), load_recipe(recipe(tmp_path)), None)
        report = asyncio.run(
            apply_many(jobs, parallel=2, on_done=on_done, options=ApplyOptions(state_dir=str(state), run_id="run-1"))
        )
        assert report.exit_code == 0 and all(holds_recipe(s) for s in sims)
    assert seen == {n: ["device-started", "device-finished"] for n in names(6)}


def test_a_caller_running_the_cli_in_process_keeps_its_garbage_collector(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    import gc

    threshold, frozen = gc.get_threshold(), gc.get_freeze_count()
    with fleet(2) as sims:
        inv = inventory(tmp_path, {n: s.url for n, s in zip(names(2), sims, strict=True)})
        code, _, err = cli(
            capsys, "apply", recipe(tmp_path), "--inventory", inv, "--yes", "--state-dir", str(tmp_path / "s")
        )
    assert code == 0, err
    assert (gc.get_threshold(), gc.get_freeze_count()) == (threshold, frozen)  # tuned only in the command's process


def test_one_report_document_in_both_forms() -> None:
    """report_text (files, --json of fleets) and Report.to_json (the API) are one document."""
    from deployer.report import DeviceResult, ParameterResult, Report, RequestRecord, report_text

    a = DeviceResult(
        "a",
        "tcp://127.0.0.1:1",
        1,
        "example-inverter",
        status="ok",
        seconds=0.5,
        error='quote " and "devices": [] inside',
        notices=["n"],
    )
    a.parameters = [ParameterResult("F07", 0x100, 1, "10 s", (100,), (50,), (100,), "ok")]
    a.requests = [RequestRecord(16, 0x100, 1)]
    b = DeviceResult("b", "rtu:///dev/x", 0, "example-inverter", status="unreachable", error="gone")
    report = Report('r "devices": [].yaml', [a, b], seconds=1.25)
    text = report_text(report)
    assert json.loads(text) == report.to_json()
    assert len(text.splitlines()) == 4  # head, one line per device, tail


def test_runs_of_numbered_names_are_shown_as_ranges() -> None:
    from deployer.cli.summary import compact

    assert compact(["d00", "d01", "d02", "d03"]) == ["d00..d03"]
    assert compact(["d00", "d01", "d03"]) == ["d00", "d01", "d03"]  # two in a row stay names
    assert compact(["a", "press-1", "press-2", "press-3", "press-5", "x9", "x10", "x11"]) == [
        "a",
        "press-1..press-3",
        "press-5",
        "x9..x11",
    ]
    assert compact(["p08", "p09", "p10", "q1", "q2", "r3"]) == ["p08..p10", "q1", "q2", "r3"]
    assert compact(["p8", "p09", "p10"]) == ["p8", "p09", "p10"]  # zero-padded and not: not one run
    assert compact(["line3-a", "line4-a", "line5-a"]) == ["line3-a", "line4-a", "line5-a"]  # the number must end it


def test_the_streamed_report_is_the_document_the_report_writer_makes(tmp_path: Path) -> None:
    """The file assembled from the stream equals ``report_text`` of the run's report (the document every
    report is written as), for a run with devices ok, partial, unreachable and never started; and a run
    retried with ``--limit @REPORT`` takes exactly the devices that did not end ok."""
    import deployer
    from deployer.report import report_text

    with fleet(5, {1: Faults(fail_registers=frozenset({F08})), 3: Faults(fail_registers=frozenset({F08}))}) as sims:
        urls = {n: s.url for n, s in zip(names(5), sims, strict=True)}
        urls["d02"] = f"tcp://127.0.0.1:{dead_port()}"  # nobody listens: unreachable
        inv = inventory(tmp_path, urls)
        report_file = tmp_path / "r.json"
        report = deployer.apply(
            deployer.load_recipe(recipe(tmp_path)),
            inventory=inv,
            report_path=report_file,
            parallel=1,
            max_failures="3",
            state_dir=tmp_path / "s",
        )
        written = json.loads(report_file.read_text())
        assert written == json.loads(report_text(report))
        jsonschema.validate(written, schema.schema("report"))
        assert [d["status"] for d in written["devices"]] == ["ok", "partial", "unreachable", "partial", "skipped"]
        assert len(written["devices"][4]["parameters"]) == 3  # never started: the recipe's parameters, skipped
        assert not_ok(str(report_file)) == ["d01", "d02", "d03", "d04"]
