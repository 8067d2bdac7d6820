"""Messages that said something else than what happened (issue #17 item 12): real processes against the simulator."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from decimal import Decimal
from pathlib import Path

import pytest

from deployer.load import yamlsrc
from deployer.profile import builtin_profile
from deployer.testing.simulator import Faults, SimulatorThread

pytestmark = pytest.mark.timeout(120)
PROFILE = builtin_profile("example-inverter")


def run(*args: str) -> tuple[int, str, str]:
    p = subprocess.run(
        [sys.executable, "-m", "deployer", *args],
        capture_output=True,
        text=True,
        timeout=60,
        env=os.environ | {"PYTHONPATH": str(Path(__file__).parent.parent)},
    )
    return p.returncode, p.stdout, p.stderr


def test_exception_04_to_a_write_that_took_is_told_and_the_read_back_decides(tmp_path: Path) -> None:
    f07 = PROFILE.parameter("F07").address
    with SimulatorThread(PROFILE, faults=Faults(complain_registers=frozenset({f07}))) as sim:
        recipe = tmp_path / "r.yaml"
        recipe.write_text("recipe: r\nprofile: example-inverter\nparameters:\n  F07: 10 s\n  base_speed: 1700 rpm\n")
        code, out, err = run(
            "apply",
            str(recipe),
            "--device",
            sim.url,
            "--yes",
            "--json",
            "--on-error",
            "stop",
            "--state-dir",
            str(tmp_path / "s"),
        )
        dev = json.loads(out)["devices"][0]
        assert code == 0, err
        assert {p["name"]: p["status"] for p in dev["parameters"]} == {"F07": "ok", "base_speed": "ok"}
        assert any(r["result"] == "exception" and r["exception_code"] == 4 for r in dev["requests"])
        assert any(
            "answered exception 04 (server device failure) to the write of F07" in n
            and "reading back shows the values took" in n
            for n in dev["notices"]
        ), dev["notices"]
        assert sim.read("F07") == (0, 1000) and sim.read("base_speed") == (1700,)  # --on-error stop went on


def test_pull_counts_only_the_parameters_it_sets(tmp_path: Path) -> None:
    f07 = PROFILE.parameter("F07").address
    with SimulatorThread(PROFILE, init={f07: 0x000A, f07 + 1: 0xAE60}) as sim:  # 7000 s: above its 6000 s
        out = tmp_path / "pulled.yaml"
        code, _, err = run("pull", "--profile", "example-inverter", "--device", sim.url, "-o", str(out))
    wanted = [p.name for p in PROFILE.parameters if p.readable and p.writable]
    assert code == 0
    assert f"{len(wanted) - 1} parameters written to {out}; 1 outside the profile's range kept as comments: F07" in err
    text = out.read_text()
    assert "  # F07: raw 700000" in text and "\n  F07:" not in text


def test_an_exponent_without_a_point_is_a_number(tmp_path: Path) -> None:
    f = tmp_path / "p.yaml"
    f.write_text(
        "profile: p\nparameters:\n  a: {register: 1, type: uint16, scale: 1e-3, unit: s}\n"
        "  b: {register: 2, type: uint16, scale: 1E2}\n"
    )
    data, _ = yamlsrc.load(str(f))
    assert data["parameters"]["a"]["scale"] == Decimal("0.001") and data["parameters"]["b"]["scale"] == 100
    code, out, err = run("validate", str(f))
    assert code == 0, out + err
    f.write_text("a: '1e-3'\nb: 1e\nc: e5\n")
    assert yamlsrc.load(str(f))[0] == {"a": "1e-3", "b": "1e", "c": "e5"}
