"""Health before the change: a soak or a confirmation does not write a device that already fails a health
check (the change would be rolled back and blamed for an old alarm), unless the operator allows it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from deployer.profile import builtin_profile
from deployer.testing.simulator import Faults, LogEntry, Simulator, parse_fault_rule
from tests.helpers import Simulators, cli
from tests.test_safe import inventory, recipe

pytestmark = pytest.mark.timeout(180)
PROFILE = builtin_profile("example-inverter")
FAULT = PROFILE.health[0].address  # wire 0x2000: "drive fault code is zero"
COMMIT = PROFILE.commit[0].address
F07 = PROFILE.parameter("F07").address
WRITES = (5, 6, 15, 16)
ALREADY = "health check already failing before the change: register 0x2000 (drive fault code is zero) is 7, expected 0"


def writes(log: list[LogEntry]) -> list[LogEntry]:
    return [e for e in log if e.function in WRITES]


@pytest.mark.parametrize("window", [["--soak", "1h"], ["--confirm-within", "1h"]])
def test_a_device_already_in_alarm_is_not_written(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, window: list[str]
) -> None:
    with Simulators([Simulator(PROFILE, init={FAULT: 7})]) as (sim,):
        before = sim.registers()
        code, out, err = cli(
            capsys,
            "apply",
            recipe(tmp_path, "3 s"),
            "--device",
            sim.url,
            "--yes",
            "--json",
            *window,
            "--state-dir",
            str(tmp_path / "s"),
        )
        log = list(sim.log)
        assert sim.registers() == before
    assert code == 4, err
    dev = json.loads(out)["devices"][0]
    assert dev["status"] == "failed" and dev["snapshot"] is None
    assert dev["error"].startswith(ALREADY) and dev["error"].endswith("; nothing was written")
    assert "--allow-unhealthy" in dev["error"] and "after 0.0 s" not in out + err
    assert writes(log) == [] and log  # the reads went out, nothing else
    assert any(e.function == 3 and e.address == FAULT for e in log)
    assert all(p["status"] == "skipped" for p in dev["parameters"])


def test_allow_unhealthy_writes_and_the_window_does_not_blame_the_change(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    with Simulators([Simulator(PROFILE, init={FAULT: 7})]) as (sim,):
        code, out, err = cli(
            capsys,
            "apply",
            recipe(tmp_path, "3 s"),
            "--device",
            sim.url,
            "--yes",
            "--json",
            "--soak",
            "300ms",
            "--health-interval",
            "100ms",
            "--allow-unhealthy",
            "--state-dir",
            str(tmp_path / "s"),
        )
        log = list(sim.log)
        f07 = sim.read("F07")
    assert code == 0, err
    dev = json.loads(out)["devices"][0]
    assert dev["status"] == "ok" and dev["commit"] == "sent"
    assert any(
        "health check already failing before the change, written anyway (--allow-unhealthy): register "
        "0x2000 (drive fault code is zero) is 7, expected 0" in n
        for n in dev["notices"]
    )
    assert f07 == (0, 300)  # 3 s at 0.01 s
    assert any(e.address == COMMIT for e in writes(log))  # the soak passed: the commit went out


def test_a_new_alarm_during_the_window_still_rolls_back_with_allow_unhealthy(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """Only the checks that failed before are left out of the window: a device whose other check fails after the
    change is rolled back as always."""
    prof_text = tmp_path / "p.yaml"
    prof_text.write_text(
        "profile: p\nhealth:\n"
        "  - {register: 48, equals: 0, description: old alarm}\n"
        "  - {register: 49, equals: 0, description: drive fault}\n"
        "parameters:\n  ramp: {register: 10, type: uint16, max: 100}\n"
    )
    from deployer.profile import load_profile

    prof = load_profile(str(prof_text))
    trip = parse_fault_rule("ramp < 5: 49=3", prof)
    (tmp_path / "r.yaml").write_text("recipe: r\nprofile: p.yaml\nparameters:\n  ramp: 2\n")
    with Simulators([Simulator(prof, init={48: 1}, faults=Faults(rules=(trip,)))]) as (sim,):
        code, out, err = cli(
            capsys,
            "apply",
            str(tmp_path / "r.yaml"),
            "--device",
            sim.url,
            "--yes",
            "--json",
            "--soak",
            "5s",
            "--health-interval",
            "100ms",
            "--allow-unhealthy",
            "--state-dir",
            str(tmp_path / "s"),
        )
        ramp = sim.read("ramp")
    assert code == 4, err
    dev = json.loads(out)["devices"][0]
    assert dev["status"] == "rolled-back"
    assert "register 0x0031 (drive fault) is 3, expected 0" in dev["error"]
    assert "old alarm" not in dev["error"]
    assert ramp == (0,)


def test_the_canary_already_in_alarm_stops_the_rollout_with_nothing_written(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    with Simulators([Simulator(PROFILE, init={FAULT: 7} if i == 0 else None) for i in range(3)]) as sims:
        urls = {f"d{i}": s.url for i, s in enumerate(sims)}
        code, out, err = cli(
            capsys,
            "apply",
            recipe(tmp_path, "3 s"),
            "--inventory",
            inventory(tmp_path, urls),
            "--yes",
            "--json",
            "--batch",
            "1,100%",
            "--soak",
            "1h",
            "--health-interval",
            "100ms",
            "--state-dir",
            str(tmp_path / "s"),
        )
        logs = [list(s.log) for s in sims]
    assert code == 4, err
    first, *rest = json.loads(out)["devices"]
    assert first["status"] == "failed" and first["error"].startswith(ALREADY)
    assert writes(logs[0]) == []
    for d, log in zip(rest, logs[1:], strict=True):
        assert d["status"] == "skipped" and "canary batch 1 did not end ok" in d["error"] and log == []


def test_allow_unhealthy_needs_a_window(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code, _, err = cli(
        capsys,
        "apply",
        recipe(tmp_path, "3 s"),
        "--device",
        "tcp://127.0.0.1:1",
        "--yes",
        "--allow-unhealthy",
        "--state-dir",
        str(tmp_path / "s"),
    )
    assert code == 1 and "--allow-unhealthy goes with --soak or --confirm-within" in err


def test_a_plain_apply_writes_a_device_in_alarm(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """Without a window nothing judges the change by its health: the checks are not read at all."""
    with Simulators([Simulator(PROFILE, init={FAULT: 7})]) as (sim,):
        code, _, err = cli(
            capsys, "apply", recipe(tmp_path, "3 s"), "--device", sim.url, "--yes", "--state-dir", str(tmp_path / "s")
        )
        log = list(sim.log)
    assert code == 0, err
    assert not any(e.function == 3 and e.address == FAULT for e in log)
