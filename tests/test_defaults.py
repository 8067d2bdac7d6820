"""Factory defaults: diff --defaults shows what differs from them, pull --non-default writes only that."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from deployer.api.values import defaults_diff, non_default
from deployer.profile import Profile
from deployer.testing.simulator import SimulatorThread
from tests.helpers import cli, profile_from

PROFILE = """\
profile: th
parameters:
  setpoint: {register: 100, type: int16, scale: 0.1, unit: degC, default: 21.5}
  mode: {register: 101, type: uint16, values: {off: 0, heat: 1, cool: 2}, default: heat}
  led: {register: 102, type: bool, bits: 0, default: true}
  level: {register: 102, type: uint16, bits: 4..6, default: 3}
  name: {register: 103, type: string, count: 4, default: TH-1}
  trim: {register: 107, type: int16}
  unit_f: {register: 5, register_type: coil, values: {celsius: 0, fahrenheit: 1}, default: celsius}
  buzzer: {register: 6, register_type: coil, default: true}
  probe: {register: 0, register_type: input, type: int16, scale: 0.1, default: 20}
"""


@pytest.fixture
def th(tmp_path: Path) -> Profile:
    return profile_from(tmp_path, PROFILE, "th.yaml")


def test_a_factory_fresh_device_holds_every_default(
    tmp_path: Path, th: Profile, capsys: pytest.CaptureFixture[str]
) -> None:
    with SimulatorThread(th) as sim:  # the simulator starts at the defaults: a device out of the box
        code, out, err = cli(capsys, "diff", "--defaults", "--profile", str(tmp_path / "th.yaml"), "--device", sim.url)
    assert code == 0, err
    assert "factory settings: all 8 parameters with a default hold it" in out
    assert "not compared: 1 parameter without a default in profile th" in out


def test_diff_defaults_names_what_was_changed(tmp_path: Path, th: Profile, capsys: pytest.CaptureFixture[str]) -> None:
    with SimulatorThread(th) as sim:
        sim.write("setpoint", (230,))
        sim.write("led", (0x0030,))  # led off (bit 0), level 3 kept (bits 4..6)
        sim.write("unit_f", (1,))
        sim.write("trim", (5,))  # no default: never "differs"
        code, out, err = cli(
            capsys, "diff", "--defaults", "--profile", str(tmp_path / "th.yaml"), "--device", sim.url, "--json"
        )
        assert code == 2, err
        data = json.loads(out)
        assert data["differs"] == [
            {
                "name": "setpoint",
                "default": "21.5 degC",
                "device": "23 degC",
                "default_raw": [215],
                "device_raw": [230],
            },
            {"name": "led", "default": "true", "device": "false", "default_raw": [1], "device_raw": [0x30]},
            {"name": "unit_f", "default": "celsius", "device": "fahrenheit", "default_raw": [0], "device_raw": [1]},
        ]
        assert (data["compared"], data["no_default"]) == (8, ["trim"])
        # the same through a recipe (its profile and device), as a table
        (tmp_path / "r.yaml").write_text(
            f"recipe: r\nprofile: th.yaml\ndevice: {{url: '{sim.url}'}}\nparameters: {{mode: cool}}\n"
        )
        code, out, _ = cli(capsys, "diff", str(tmp_path / "r.yaml"), "--defaults")
        assert code == 2
        assert out.splitlines()[-2:] == [
            "3 of 8 parameters with a factory default differ from it",
            "not compared: 1 parameter without a default in profile th",
        ]
        assert "setpoint   21.5 degC        23 degC" in out


def test_pull_non_default_is_the_difference_from_the_factory(
    tmp_path: Path, th: Profile, capsys: pytest.CaptureFixture[str]
) -> None:
    with SimulatorThread(th) as sim:
        sim.write("mode", (2,))
        sim.write("level", (0x0051,))  # led on, level 5
        sim.write("buzzer", (0,))
        code, _, err = cli(
            capsys,
            "pull",
            "--profile",
            str(tmp_path / "th.yaml"),
            "--device",
            sim.url,
            "--non-default",
            "-o",
            str(tmp_path / "pulled.yaml"),
        )
        assert code == 0, err
        text = (tmp_path / "pulled.yaml").read_text()
        assert (
            "# Only the values that differ from the factory defaults of profile th: 4 parameters at the default "
            "left out; 1 parameter without a default in the profile kept\n" in text
        )
        assert text.endswith("parameters:\n  mode: cool\n  level: 5\n  trim: 0\n  buzzer: false\n")
        changed = {n: sim.read(n) for n in th.names()}
    # a factory-fresh device plus the pulled recipe is the device it was pulled from
    with SimulatorThread(th) as fresh:
        code, _, err = cli(
            capsys,
            "apply",
            str(tmp_path / "pulled.yaml"),
            "--device",
            fresh.url,
            "--yes",
            "--state-dir",
            str(tmp_path / ".d"),
        )
        assert code == 0, err
        assert {n: fresh.read(n) for n in th.names()} == changed


def test_defaults_in_code(th: Profile) -> None:
    current = {
        "setpoint": (215,),
        "mode": (1,),
        "led": (0x31,),
        "level": (0x31,),
        "name": (0x5448, 0x2D31, 0, 0),
        "trim": (7,),
        "unit_f": (0,),
        "buzzer": (1,),
    }
    assert defaults_diff(th, current) == ([], ["trim"])
    assert non_default(th, current) == {"trim": (7,)}
    current["name"] = (0x5448, 0x2D32, 0, 0)  # TH-2
    differs, _ = defaults_diff(th, current)
    assert [(d.name, d.default, d.device) for d in differs] == [("name", "TH-1", "TH-2")]


def test_defaults_usage(tmp_path: Path, th: Profile, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = cli(capsys, "diff", "--defaults", "--profile", str(tmp_path / "th.yaml"))
    assert code == 1 and "diff --defaults needs RECIPE, or --profile ID|FILE and --device URL" in err
    code, _, err = cli(capsys, "diff", "--profile", str(tmp_path / "th.yaml"), "--device", "tcp://127.0.0.1:1")
    assert code == 1 and "--profile goes with --defaults" in err
