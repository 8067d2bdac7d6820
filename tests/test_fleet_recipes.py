"""A mixed line from one inventory: two device types, each group its recipe and profile, per-device values.

Everything runs against simulators on loopback: plan, apply, diff and rollback with no RECIPE argument,
and the errors an inventory can have, each said once with the devices it concerns.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import jsonschema
import pytest

from deployer.cli.files import validate_file
from deployer.errors import InputError
from deployer.fleet.inventory import load_inventory
from deployer.load import schema, yamlsrc
from deployer.profile import builtin_profile, load_profile
from deployer.testing.simulator import Simulator
from tests.conftest import dead_port
from tests.helpers import Simulators, cli

pytestmark = pytest.mark.timeout(180)
MBPOLL = shutil.which("mbpoll")  # libmodbus's client: an implementation we did not write

# a temperature controller, from a file next to the inventory (the other type is the built-in inverter)
PID_PROFILE = """\
profile: pid-controller
description: an illustrative PID temperature controller
addressing: address
parameters:
  P: {register: 0x0010, type: uint16, unit: percent, scale: 0.1, min: 0, max: 100}
  I: {register: 0x0011, type: uint16, unit: s, min: 0, max: 3600}
  D: {register: 0x0012, type: uint16, unit: s, min: 0, max: 600}
  setpoint: {register: 0x0020, type: int16, unit: degC, scale: 0.1, min: -50, max: 400}
"""
ZONE = "recipe: zone\nprofile: ../profiles/pid.yaml\nparameters:\n  P: 12.0 %\n  I: 120 s\n  setpoint: 180 degC\n"
DRIVE = "recipe: drive\nprofile: example-inverter\nparameters:\n  F07: 10 s\n  F08: 12 s\n  stop_mode: coast\n"


def line(tmp: Path, urls: dict[str, str], extra_devices: str = "") -> str:
    """Two zones (PID) and three drives; drive-3 is also 'slow' (a later group wins), zone-2 and drive-2
    have their own values (a device wins over its groups)."""
    (tmp / "profiles").mkdir(exist_ok=True)
    (tmp / "profiles" / "pid.yaml").write_text(PID_PROFILE)
    (tmp / "recipes").mkdir(exist_ok=True)
    (tmp / "recipes" / "zone.yaml").write_text(ZONE)
    (tmp / "recipes" / "drive.yaml").write_text(DRIVE)
    inv = tmp / "line5.yaml"
    inv.write_text(
        "defaults: {timeout: 1.0, retries: 0}\n"
        "groups:\n"
        "  zones: {recipe: recipes/zone.yaml, profile: profiles/pid.yaml, parameters: {D: 30 s}}\n"
        "  drives: {recipe: recipes/drive.yaml, profile: example-inverter, parameters: {F07: 15 s}}\n"
        "  slow: {parameters: {F07: 20 s, F08: 25 s}}\n"
        "devices:\n"
        f"  zone-1: {{url: '{urls['zone-1']}', groups: [zones]}}\n"
        f"  zone-2: {{url: '{urls['zone-2']}', groups: [zones], parameters: {{setpoint: 200 degC}}}}\n"
        f"  drive-1: {{url: '{urls['drive-1']}', groups: [drives]}}\n"
        f"  drive-2: {{url: '{urls['drive-2']}', groups: [drives], parameters: {{F08: 9 s}}}}\n"
        f"  drive-3: {{url: '{urls['drive-3']}', groups: [drives, slow]}}\n" + extra_devices
    )
    return str(inv)


# what each device must hold afterwards: recipe < defaults < groups (in order) < device
WANT: dict[str, dict[str, tuple[int, ...]]] = {
    "zone-1": {"P": (120,), "I": (120,), "D": (30,), "setpoint": (1800,)},
    "zone-2": {"P": (120,), "I": (120,), "D": (30,), "setpoint": (2000,)},
    "drive-1": {"F07": (0, 1500), "F08": (0, 1200), "stop_mode": (1,)},
    "drive-2": {"F07": (0, 1500), "F08": (0, 900), "stop_mode": (1,)},
    "drive-3": {"F07": (0, 2000), "F08": (0, 2500), "stop_mode": (1,)},
}
NAMES = list(WANT)


def holds(sim: Simulator, want: dict[str, tuple[int, ...]]) -> bool:
    return all(sim.read(n) == v for n, v in want.items())


def writes(sims: list[Simulator]) -> int:
    return sum(1 for s in sims for e in s.log if e.function in (6, 16))


@pytest.fixture
def sims(tmp_path: Path) -> list[Simulator]:
    pid = load_profile(str(_pid_file(tmp_path)))
    inverter = builtin_profile("example-inverter")
    return [Simulator(pid), Simulator(pid), Simulator(inverter), Simulator(inverter), Simulator(inverter)]


def _pid_file(tmp: Path) -> Path:
    (tmp / "profiles").mkdir(exist_ok=True)
    p = tmp / "profiles" / "pid.yaml"
    p.write_text(PID_PROFILE)
    return p


def test_settings_come_from_device_then_groups_in_order_then_defaults(tmp_path: Path) -> None:
    urls = {n: f"tcp://127.0.0.1:{5000 + i}" for i, n in enumerate(NAMES)}
    inv = load_inventory(
        line(
            tmp_path,
            urls,
            "  odd-1: {url: 'tcp://h', unit: 9, groups: [slow, drives], recipe: recipes/drive.yaml, timeout: 3}\n",
        )
    )
    by = {d.name: d for d in inv.devices}
    assert by["zone-1"].recipe == str(tmp_path / "recipes" / "zone.yaml")
    assert by["zone-1"].profile == str(tmp_path / "profiles" / "pid.yaml")  # relative to the inventory
    assert by["drive-1"].profile == "example-inverter" and by["drive-1"].timeout == 1.0 and by["drive-1"].retries == 0
    values = {d.name: {e.name: e.value for e in d.overrides} for d in inv.devices}
    assert values["zone-2"] == {"D": "30 s", "setpoint": "200 degC"}
    assert values["drive-3"] == {"F07": "20 s", "F08": "25 s"}  # slow is listed after drives: it wins
    assert values["odd-1"] == {"F07": "15 s", "F08": "25 s"}  # here drives comes last
    assert by["odd-1"].unit == 9 and by["odd-1"].timeout == 3.0
    # parameters merge per name: defaults < groups (in the device's order) < the device
    small = tmp_path / "small.yaml"
    small.write_text(
        "defaults: {parameters: {F07: 1 s, F08: 1 s, stop_mode: ramp}, unit: 2}\n"
        "groups: {a: {parameters: {F08: 2 s}, unit: 3}, b: {parameters: {F08: 3 s, stop_mode: coast}}}\n"
        "devices:\n  x: {url: 'tcp://h', groups: [b, a], parameters: {F07: 4 s}}\n"
        "  y: {url: 'tcp://h', groups: [a, b, line9]}\n  z: {url: 'tcp://h'}\n"
    )
    got = {d.name: ({e.name: e.value for e in d.overrides}, d.unit) for d in load_inventory(small).devices}
    assert got == {
        "x": ({"F07": "4 s", "F08": "2 s", "stop_mode": "coast"}, 3),
        "y": ({"F07": "1 s", "F08": "3 s", "stop_mode": "coast"}, 3),
        "z": ({"F07": "1 s", "F08": "1 s", "stop_mode": "ramp"}, 2),
    }


def test_mixed_line_plan_apply_diff_rollback(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, sims: list[Simulator]
) -> None:
    state = str(tmp_path / "state")
    with Simulators(sims):
        inv = line(tmp_path, {n: s.url for n, s in zip(NAMES, sims, strict=True)})
        before = {n: {p: s.read(p) for p in WANT[n]} for n, s in zip(NAMES, sims, strict=True)}

        code, out, err = cli(capsys, "plan", "--inventory", inv, "--detailed-exitcode", "--per-device")
        assert code == 2, err
        assert "5 of 5 devices would change" in out
        assert "zone-2 " in out and "200 degC" in out and "25 s" in out
        code, out, err = cli(capsys, "plan", "--inventory", inv)  # the summary: one line per distinct change
        assert code == 0 and out.splitlines()[:2] == [
            "1 device: P 0 % -> 12 %, I 0 s -> 120 s, D 0 s -> 30 s, setpoint 0 degC -> 180 degC",
            "  zone-1",
        ]
        assert writes(sims) == 0

        report = tmp_path / "run.json"
        code, out, err = cli(
            capsys, "apply", "--inventory", inv, "--yes", "--json", "--report", str(report), "--state-dir", state
        )
        assert code == 0, err
        data = json.loads(out)
        jsonschema.validate(data, schema.schema("report"))
        assert data["recipe"] is None  # no one recipe: each device says its own
        by = {d["name"]: d for d in data["devices"]}
        assert by["zone-1"]["recipe"] == str(tmp_path / "recipes" / "zone.yaml")
        assert by["drive-1"]["recipe"] == str(tmp_path / "recipes" / "drive.yaml")
        assert by["zone-1"]["profile"] == "pid-controller" and by["drive-1"]["profile"] == "example-inverter"
        for n, s in zip(NAMES, sims, strict=True):
            assert by[n]["status"] == "ok" and holds(s, WANT[n]), n
        # the snapshot records the device's own recipe as what was applied after it
        snap = yamlsrc.load(by["zone-2"]["snapshot"])[0]
        assert snap["snapshot"]["applied"] == str(tmp_path / "recipes" / "zone.yaml")

        if MBPOLL is not None:  # libmodbus reads what each device type got: its own registers, its own values
            assert "[16]: \t120\n[17]: \t120\n[18]: \t30\n" in mbpoll(sims[1], 16, 3)
            assert "[32]: \t2000\n" in mbpoll(sims[1], 32)
            assert "[4354]: \t0\n[4355]: \t2000\n[4356]: \t0\n[4357]: \t2500\n" in mbpoll(sims[4], 4354, 4)
        code, out, err = cli(capsys, "diff", "--inventory", inv)
        assert code == 0, out + err
        if MBPOLL is not None:  # drive-2 moved on the panel: libmodbus writes F08 = 10 s (FC16)
            mbpoll(sims[3], 4356, write=(0, 1000))
        else:
            sims[3].write("F08", (0, 1000))
        code, out, err = cli(capsys, "diff", "--inventory", inv, "--per-device")
        assert code == 2 and "drift on 1 of 5 devices: drive-2" in out and "10 s" in out

        # drive-2 no longer holds what the run wrote: --all-or-nothing refuses them all, nothing sent
        code, out, err = cli(
            capsys, "rollback", "--from-report", str(report), "--yes", "--state-dir", state, "--all-or-nothing"
        )
        assert code == 1 and "drive-2 no longer holds what the run wrote (F08)" in err, out + err
        assert all({p: s.read(p) for p in WANT[n]} != before[n] for n, s in zip(NAMES, sims, strict=True))
        # by default the other four are restored and drive-2 is refused by name (exit 4)
        code, out, err = cli(capsys, "rollback", "--from-report", str(report), "--yes", "--state-dir", state)
        assert code == 4 and "refused: drive-2 no longer holds what the run wrote (F08)" in err, out + err
        assert "refused 1 changed device: drive-2" in err
        for n, s in zip(NAMES, sims, strict=True):
            assert ({p: s.read(p) for p in WANT[n]} == before[n]) == (n != "drive-2"), n
        code, out, err = cli(
            capsys,
            "rollback",
            "--from-report",
            str(report),
            "--yes",
            "--state-dir",
            state,
            "--limit",
            "drive-2",
            "--even-if-changed",
        )
        assert code == 0, out + err
        for n, s in zip(NAMES, sims, strict=True):
            assert {p: s.read(p) for p in WANT[n]} == before[n], n


def mbpoll(sim: Simulator, register: int, count: int = 1, write: tuple[int, ...] = ()) -> str:
    """mbpoll on a simulator's holding registers (protocol addresses): read ``count`` of them, or write ``write``."""
    assert MBPOLL is not None
    port = sim.url.rsplit(":", 1)[1]
    done = subprocess.run(
        [
            MBPOLL,
            "-m",
            "tcp",
            "-p",
            port,
            "-a",
            "1",
            "-t",
            "4",
            "-0",
            "-1",
            "-r",
            str(register),
            *([] if write else ["-c", str(count)]),
            "127.0.0.1",
            *map(str, write),
        ],
        capture_output=True,
        text=True,
        timeout=20,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_a_recipe_for_one_type_over_a_mixed_line_names_the_devices_once(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    urls = {n: f"tcp://127.0.0.1:{dead_port()}" for n in NAMES}
    inv = line(tmp_path, urls)
    zone = str(tmp_path / "recipes" / "zone.yaml")
    code, _, err = cli(capsys, "plan", zone, "--inventory", inv)
    assert code == 1
    # the RECIPE goes to every device, with each device's profile: the drives do not know P
    problem = [ln for ln in err.splitlines() if "unknown parameter 'P'" in ln]
    assert problem == [
        f"{zone}:4:3: error: unknown parameter 'P' in profile example-inverter "
        "(devices drive-1, drive-2, drive-3; the inventory gives them recipes of their own: "
        "leave out RECIPE to use those)"
    ]
    assert "nothing was sent to any device" in err


def test_a_device_without_a_recipe_stops_the_run_before_anything_is_sent(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, sims: list[Simulator]
) -> None:
    with Simulators(sims):
        inv = line(
            tmp_path,
            {n: s.url for n, s in zip(NAMES, sims, strict=True)},
            "  spare-1: {url: 'tcp://127.0.0.1:1'}\n  spare-2: {url: 'tcp://127.0.0.1:2', groups: [zone]}\n",
        )
        for command in ("plan", "diff", "apply"):
            more = ["--yes", "--state-dir", str(tmp_path / "s")] if command == "apply" else []
            code, _, err = cli(capsys, command, "--inventory", inv, *more)
            assert code == 1, command
            assert f"{inv}:12:3: error: no recipe: give the device one" in err and "(device spare-1)\n" in err
            assert f"{inv}:13:3: error: no recipe" in err
            assert "its group 'zone' has no entry under groups: (did you mean 'zones'?) (device spare-2)\n" in err
        assert sum(len(s.log) for s in sims) == 0  # not even read
        # leaving them out, the rest goes
        code, _, err = cli(capsys, "plan", "--inventory", inv, "--limit", "!spare-*")
        assert code == 0, err
        code, _, err = cli(capsys, "plan", "--device", "tcp://127.0.0.1:1")
        assert code == 1 and "pass RECIPE, or --inventory FILE whose devices name their recipes" in err


def test_inventory_errors_name_their_devices_and_validate_checks_the_recipes(tmp_path: Path) -> None:
    urls = {n: f"tcp://127.0.0.1:{1502 + i}" for i, n in enumerate(NAMES)}  # one device, one entry
    inv = line(tmp_path, urls)
    assert validate_file(inv) == "inventory: 5 devices, 2 recipes"
    text = Path(inv).read_text()
    # a group's bad value concerns every device of the group; a missing recipe file is said where it is named
    Path(inv).write_text(
        text.replace("parameters: {D: 30 s}", "parameters: {D: 9000 s}").replace(
            "recipes/drive.yaml", "recipes/drives.yaml"
        )
    )
    with pytest.raises(InputError) as e:
        validate_file(inv)
    msgs = [str(d) for d in e.value.diagnostics]
    assert msgs == [
        f"{inv}:3:82: error: D: 9000 s is out of range 0..600 s (devices zone-1, zone-2)",
        f"{inv}:4:20: error: recipe {tmp_path / 'recipes' / 'drives.yaml'}: no such file "
        "(devices drive-1, drive-2, drive-3)",
    ]
    # the schema: groups take only a device's settings, not a url
    Path(inv).write_text(text.replace("slow: {parameters", "slow: {url: 'tcp://x', parameters"))
    with pytest.raises(InputError, match=r"line5.yaml:5:10: error: .*url"):
        validate_file(inv)


def test_counts_read_as_english_and_percent_as_a_symbol(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    (tmp_path / "profiles").mkdir()
    (tmp_path / "profiles" / "pid.yaml").write_text(PID_PROFILE)
    one = tmp_path / "one.yaml"
    one.write_text("recipe: one\nprofile: profiles/pid.yaml\nparameters:\n  P: 12.0 %\n")
    code, out, _ = cli(capsys, "plan", str(one), "--show-frames")
    assert code == 0 and " 12 % " in out and "(write): FC16 at 0x0010, 1 register (P)" in out
    sim = Simulator(load_profile(str(tmp_path / "profiles" / "pid.yaml")))
    with Simulators([sim]):
        state = str(tmp_path / "s")
        inv = tmp_path / "inv.yaml"
        inv.write_text(f"devices:\n  z1: {{url: '{sim.url}', recipe: one.yaml}}\n")
        code, out, err = cli(capsys, "apply", "--inventory", str(inv), "--yes", "--state-dir", state)
        assert code == 0 and "z1: ok (1 write)" in err
        assert "1 device: 1 ok; 4 requests (2 reads, 1 write, 1 device identification)" in out
        code, out, _ = cli(capsys, "diff", str(one), "--device", sim.url)
        assert code == 0 and out == "no drift: the device holds the recipe's value\n"
        sim.write("P", (100,))
        code, out, _ = cli(capsys, "diff", str(one), "--device", sim.url)
        assert code == 2 and "1 of 1 parameter differs from the recipe" in out and "10 %" in out


def test_the_ansible_module_takes_the_inventorys_recipes(tmp_path: Path) -> None:
    import deployer
    from ansible_collections.deployer.modbus.plugins.module_utils import deployer_common as common

    class Module:
        def __init__(self, **params: object) -> None:
            self.params = {"timeout": None, "retries": None, "unit": None, "limit": None, **params}

    inv = line(tmp_path, {n: f"tcp://127.0.0.1:{1502 + i}" for i, n in enumerate(NAMES)})
    task = Module(inventory=inv)
    assert common.recipe_of(task) is None  # no recipe, profile or parameters: each device's own
    fleet = deployer.plan(None, offline=True, state_dir=None, **common.targets_of(task, None))
    assert {n: fleet[n].recipe_name for n in fleet} == {
        "zone-1": "zone",
        "zone-2": "zone",
        "drive-1": "drive",
        "drive-2": "drive",
        "drive-3": "drive",
    }
    with pytest.raises(
        InputError,
        match=r"unknown parameter 'F07' in profile pid-controller \(devices zone-1, "
        "zone-2; the inventory gives them recipes of their own",
    ):
        drive = common.recipe_of(Module(inventory=inv, recipe=str(tmp_path / "recipes" / "drive.yaml")))
        deployer.plan(drive, offline=True, state_dir=None, **common.targets_of(task, drive))
