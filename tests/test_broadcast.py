"""Broadcast (unit 0) from the command line: `sent`, exit 0, when every request went out."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import pytest

from deployer.load import schema
from deployer.profile import builtin_profile
from deployer.testing.simulator import SimulatorThread
from tests.helpers import cli

pytestmark = pytest.mark.timeout(60)


def test_broadcast_ends_sent_with_exit_0(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    recipe = tmp_path / "r.yaml"
    recipe.write_text("recipe: r\nprofile: example-inverter\nparameters: {F07: 10 s, stop_mode: coast}\n")
    with SimulatorThread(builtin_profile("example-inverter"), units=(1, 2)) as sim:
        code, out, _ = cli(
            capsys,
            "apply",
            str(recipe),
            "--device",
            sim.url,
            "--unit",
            "0",
            "--allow-broadcast",
            "--yes",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 0
        assert "(example-inverter): sent" in out
        assert "broadcast sent: every request went out; no device answers a broadcast" in out
        code, out, _ = cli(
            capsys,
            "apply",
            str(recipe),
            "--device",
            sim.url,
            "--unit",
            "0",
            "--allow-broadcast",
            "--yes",
            "--json",
            "--report",
            str(tmp_path / "report.json"),
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 0
        assert sim.read("F07", 1) == sim.read("F07", 2) == (0, 1000)
    report = json.loads(out)
    assert report == json.loads((tmp_path / "report.json").read_text())
    jsonschema.validate(report, schema.schema("report"))
    (dev,) = report["devices"]
    assert dev["status"] == "sent" and dev["snapshot"] is None
    assert {p["status"] for p in dev["parameters"]} == {"unverified"}
    assert [r["result"] for r in dev["requests"]] == ["broadcast", "broadcast"]
    assert report["summary"]["sent"] == 1 and report["summary"]["ok"] == 0
    audit = [json.loads(line) for line in (tmp_path / "s" / "audit.jsonl").read_text().splitlines()]
    assert [a["exit_code"] for a in audit if a["event"] == "run-finished"] == [0, 0]


def test_retrying_a_report_leaves_sent_broadcasts_alone(tmp_path: Path) -> None:
    from deployer.fleet.inventory import not_ok

    report = tmp_path / "run.json"
    report.write_text(
        json.dumps(
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
                    for n, s in (("a", "ok"), ("all", "sent"), ("b", "partial"), ("c", "skipped"))
                ],
                "summary": {
                    "devices": 4,
                    "ok": 1,
                    "partial": 1,
                    "failed": 0,
                    "unreachable": 0,
                    "write_requests": 0,
                    "read_requests": 0,
                    "seconds": 0,
                },
            }
        )
    )
    assert not_ok(str(report)) == ["b", "c"]
