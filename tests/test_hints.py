"""Errors that say what to check: the exact texts users see for common set-up mistakes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from deployer.cli.files import validate_file
from deployer.errors import InputError
from deployer.profile import builtin_profile, builtin_profile_ids
from deployer.testing.simulator import Faults, SimulatorThread
from tests.helpers import cli

pytestmark = pytest.mark.timeout(60)
BUILTINS = ", ".join(builtin_profile_ids())  # example-inverter, omron-m1, ... as the message lists them


def messages(path: Path) -> list[str]:
    with pytest.raises(InputError) as err:
        validate_file(str(path))
    return [str(d) for d in err.value.diagnostics]


def test_no_answer_on_a_serial_line_names_the_line_settings(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, socat_pair: tuple[str, str]
) -> None:
    a, b = socat_pair
    recipe = tmp_path / "r.yaml"
    recipe.write_text("recipe: r\nprofile: example-inverter\nparameters: {F07: 10 s}\n")
    # the device answers unit 1 only: unit 5 on a serial line meets silence
    with SimulatorThread(builtin_profile("example-inverter"), listen=f"rtu://{a}", units=(1,)):
        code, _, err = cli(
            capsys, "diff", str(recipe), "--device", f"rtu://{b}?baudrate=9600&timeout=0.1&retries=1", "--unit", "5"
        )
        assert code == 3
        assert err == (
            f"error: rtu://{b}?baudrate=9600 unit 5: no answer after 2 attempts at 9600 baud, 8 data bits, parity N, "
            "1 stop bit, unit 5: check that the device uses the same baud rate, parity, data bits and stop bits "
            "and answers to unit 5 (URL options baudrate, parity, bytesize, stopbits; --unit)\n"
        )
        code, out, _ = cli(
            capsys,
            "apply",
            str(recipe),
            "--device",
            f"ascii://{b}?timeout=0.1&retries=0",
            "--unit",
            "1",
            "--yes",
            "--json",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 3  # an RTU device does not understand ASCII frames: silence again
        (dev,) = json.loads(out)["devices"]
        assert dev["status"] == "unreachable" and dev["error"] == (
            "no answer after 1 attempt at 19200 baud, 8 data bits, parity N, 1 stop bit, unit 1: check that the "
            "device uses the same baud rate, parity, data bits and stop bits and answers to unit 1 (URL options "
            "baudrate, parity, bytesize, stopbits; --unit); nothing was written"
        )


def test_no_answer_over_tcp_has_no_line_settings_hint(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    recipe = tmp_path / "r.yaml"
    recipe.write_text("recipe: r\nprofile: example-inverter\nparameters: {F07: 10 s}\n")
    with SimulatorThread(builtin_profile("example-inverter"), faults=Faults(drop_every=1)) as sim:
        code, _, err = cli(capsys, "diff", str(recipe), "--device", f"{sim.url}?timeout=0.1&retries=0")
    assert code == 3 and err.endswith("unit 1: no answer after 1 attempt\n")


def test_unknown_builtin_profile_lists_the_builtins_and_says_a_path_works(tmp_path: Path) -> None:
    recipe = tmp_path / "r.yaml"
    recipe.write_text("recipe: r\nprofile: pid-ctrl\nparameters: {sp: 1}\n")
    assert messages(recipe) == [
        f"{recipe}:2:10: error: unknown built-in profile 'pid-ctrl' (built-in: {BUILTINS}"
        "); a profile file works too: its path relative to the recipe, ending in .yaml, "
        "e.g. 'pid-ctrl.yaml'"
    ]
    (tmp_path / "pid-ctrl.yaml").write_text("profile: pid-ctrl\nparameters: {sp: {register: 1, type: uint16}}\n")
    assert messages(recipe)[0].endswith("ending in .yaml, did you mean 'pid-ctrl.yaml'?")
    recipe.write_text("recipe: r\nprofile: pid-ctrl.yaml\nparameters: {sp: 1}\n")
    assert validate_file(str(recipe)) == "recipe r: 1 parameter for profile pid-ctrl"


def test_unknown_builtin_profile_on_the_command_line(capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = cli(capsys, "profiles", "show", "pid-ctrl")
    assert code == 1 and err == (
        f"error: unknown built-in profile 'pid-ctrl' (built-in: {BUILTINS}); a profile "
        "file works too: its path relative to the current directory, ending in .yaml, e.g. 'pid-ctrl.yaml'\n"
    )


@pytest.mark.parametrize(
    ("register", "hint"),
    [
        (30001, "; 3xxxx references are input registers, which cannot be written"),
        (4355, "; for 0-based addresses use addressing: address, for 1-based numbers addressing: register-number"),
        (50000, ""),
        (465537, ""),
    ],
)
def test_bad_modicon_reference_says_which_ranges_are_accepted(tmp_path: Path, register: int, hint: str) -> None:
    prof = tmp_path / "p.yaml"
    prof.write_text(f"profile: p\naddressing: modicon\nparameters:\n  a: {{register: {register}, type: uint16}}\n")
    assert messages(prof) == [
        f"{prof}:4:17: error: {register} is not a holding-register reference: addressing: modicon accepts "
        f"40001-49999 (5 digits, addresses 0-9998) or 400001-465536 (6 digits, addresses 0-65535){hint}"
    ]


def test_unknown_profile_in_an_inventory_says_paths_are_relative_to_it(tmp_path: Path) -> None:
    inv = tmp_path / "fleet.yaml"
    inv.write_text("devices:\n  press-1: {url: 'tcp://127.0.0.1', profile: drive-b}\n")
    (tmp_path / "drive-b.yaml").write_text("profile: drive-b\nparameters: {sp: {register: 1, type: uint16}}\n")
    assert messages(inv) == [
        f"{inv}:2:46: error: unknown built-in profile 'drive-b' (built-in: {BUILTINS}"
        "); a profile file works too: its path relative to the inventory, ending in .yaml, "
        "did you mean 'drive-b.yaml'? (device press-1)"
    ]


def test_no_answer_through_a_gateway_points_at_the_gateway_settings(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    recipe = tmp_path / "r.yaml"
    recipe.write_text("recipe: r\nprofile: example-inverter\nparameters: {F07: 10 s}\n")
    with SimulatorThread(
        builtin_profile("example-inverter"), listen="rtu+tcp://127.0.0.1:0", faults=Faults(drop_every=1)
    ) as sim:
        url = sim.url  # the port the system gave
        code, _, err = cli(capsys, "diff", str(recipe), "--device", f"{url}?timeout=0.1&retries=0", "--unit", "3")
    assert code == 3 and err.endswith(
        "unit 3: no answer after 1 attempt through the gateway, unit 3: check the unit id and that the gateway's "
        "serial line settings (baud rate, parity, data bits, stop bits) match the device's\n"
    )
