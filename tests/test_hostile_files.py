"""Files deployer reads back that someone else may have edited (issue #28, items 11, 12, 14 and 16):
the learned limits, reports; names too long for a file system; big imports.

Each is refused at its position with exit 1 and never a traceback, before anything is sent.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from deployer.profile import builtin_profile
from deployer.testing.simulator import SimulatorThread
from tests.helpers import cli as run_cli

INVERTER = builtin_profile("example-inverter")
RECIPE = "recipe: line\nprofile: example-inverter\nparameters:\n  F07: 10 s\n  F08: 12 s\n"


def learned_file(state: Path, value: str, url: str) -> None:
    state.mkdir(exist_ok=True)
    port = url.rsplit(":", 1)[1]
    (state / "learned.json").write_text(
        '{"schema": "deployer.learned/1", "devices": [\n'
        f'  {{"profile": "example-inverter", "device": "127.0.0.1:{port}/1", "url": "{url}", "unit": 1,\n'
        f'   "limits": {{"max_write_registers": {value}}}, "seen": "", "when": ""}}]}}\n')


@pytest.mark.parametrize("value", ["1e400", "-Infinity", "NaN", '"x"', "null", "1.5", "true", "0", "999", "[]"])
def test_a_learned_file_deployer_did_not_write_is_refused(value: str, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "r.yaml").write_text(RECIPE)
    state = tmp_path / "st"
    with SimulatorThread(INVERTER) as sim:
        learned_file(state, value, sim.url)
        for args in (["learned", "list"], ["plan", str(tmp_path / "r.yaml"), "--device", sim.url],
                     ["apply", str(tmp_path / "r.yaml"), "--device", sim.url, "--yes"]):
            code, out, err = run_cli(capsys, *args, "--state-dir", str(state))
            assert code == 1, (args, out, err)
            assert "Traceback" not in err
            first = err.splitlines()[0]
            assert first.startswith(f"{state / 'learned.json'}:3:38: error: limits.max_write_registers"), first
            assert f"deployer learned forget --all --state-dir {state}" in first
        plan_reads = len(sim.log)  # plan read the device; apply sent nothing at all
        assert all(e.function in (3, 43) for e in sim.log)
        assert sim.read("F07") == INVERTER.parameter("F07").default_registers()
        code, out, _ = run_cli(capsys, "learned", "forget", "--all", "--state-dir", str(state))
        assert code == 0 and "not a learned file deployer wrote" in out
        code, _, err = run_cli(capsys, "apply", str(tmp_path / "r.yaml"), "--device", sim.url, "--yes",
                               "--state-dir", str(state))
        assert code == 0, err
        assert len(sim.log) > plan_reads


def test_a_learned_file_that_is_not_json_is_refused_where_it_breaks(tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    state = tmp_path / "st"
    state.mkdir()
    (state / "learned.json").write_text('{"schema": "deployer.learned/1",\n "devices": [')
    code, _, err = run_cli(capsys, "learned", "list", "--state-dir", str(state))
    assert code == 1 and err.startswith(f"{state / 'learned.json'}:2:14: error: invalid JSON")
    (state / "learned.json").write_bytes(b'{"schema": "deployer.learned/1", "devices": ["\xff"]}')
    code, _, err = run_cli(capsys, "learned", "list", "--state-dir", str(state))
    assert code == 1 and "1:47: error: not UTF-8 text" in err
    (state / "learned.json").write_text(json.dumps({"schema": "deployer.learned/1", "devices": [
        {"profile": "p", "device": "d", "limits": {"max_read_registers": 2}, "extra": 1}]}))
    code, _, err = run_cli(capsys, "learned", "list", "--state-dir", str(state))
    assert code == 1 and "unknown key 'extra'" in err and "unknown limit 'max_read_registers'" in err


@pytest.mark.parametrize("name", ["r" * 300, "日本語" * 100, "CON." + "x" * 260])
def test_a_long_recipe_name_gets_a_bounded_snapshot_name(name: str, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    rec = tmp_path / "r.yaml"
    rec.write_text(RECIPE.replace("recipe: line", f"recipe: {json.dumps(name)}"))
    state = tmp_path / "st"
    with SimulatorThread(INVERTER) as sim:
        before = sim.read("F07")
        code, _, err = run_cli(capsys, "apply", str(rec), "--device", sim.url, "--yes", "--state-dir", str(state))
        assert code == 0, err
        (snap,) = (state / "snapshots").iterdir()
        assert len(snap.name.encode()) <= 130 and snap.name.endswith(".yaml")
        other = tmp_path / "other.yaml"  # another long name with the same start keeps its own snapshot
        other.write_text(rec.read_text().replace(json.dumps(name), json.dumps(name + "2")).replace("10 s", "11 s"))
        code, _, err = run_cli(capsys, "apply", str(other), "--device", sim.url, "--yes", "--state-dir", str(state))
        assert code == 0, err
        assert len(list((state / "snapshots").iterdir())) == 2
        code, _, err = run_cli(capsys, "rollback", str(snap), "--device", sim.url, "--yes", "--state-dir", str(state))
        assert code == 0, err
        assert sim.read("F07") == before


def test_status_of_a_fleet_whose_recipes_come_from_groups(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """What a crashed run of ``apply --inventory`` (no RECIPE: each device's from its groups) leaves in the
    journal: status names the inventory, not an empty recipe, and its check command runs as printed."""
    import shlex

    from deployer.state import journal

    monkeypatch.chdir(tmp_path)
    Path("drive.yaml").write_text(RECIPE)
    with SimulatorThread(INVERTER) as sim:
        Path("site.yaml").write_text("groups:\n  drives: {recipe: drive.yaml}\ndevices:\n"
                                     f"  drive-1: {{url: '{sim.url}', groups: [drives]}}\n")
        journal.run_started("st", "run-1", command="apply", argv=["apply", "--inventory", "site.yaml", "--yes"],
                            recipe=None, via="cli", devices=[("drive-1", sim.url, 1)])
        journal.append("st", {**journal.device_started("run-1", name="drive-1", url=sim.url, unit=1,
                                                       plan_digest="0" * 64), "snapshot": "st/snapshots/s.yaml"})
        code, out, _ = run_cli(capsys, "status", "--state-dir", "st")
        assert code == 0
        assert "apply --inventory site.yaml by " in out and "apply  by" not in out and "PROFILE" not in out
        check = next(line for line in out.splitlines() if "check with: " in line)
        command = check.split("check with: ")[1].split(";")[0]
        assert command == "deployer diff --inventory site.yaml --limit drive-1"
        code, out, err = run_cli(capsys, *shlex.split(command)[1:])
        assert code == 2 and "drive-1" in out, err  # the device still holds its old values: drift
        assert "undo with: deployer rollback st/snapshots/s.yaml --state-dir st" in check
