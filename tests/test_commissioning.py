"""Commissioning: values as people type them, secrets, health checks in engineering units (simulator and umodbus)."""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from deployer.errors import InputError
from deployer.profile import builtin_profile, load_profile
from deployer.recipe.loader import load_recipe
from deployer.testing.simulator import Faults, Quirks, Simulator, SimulatorThread, parse_fault_rule
from tests.helpers import Simulators, cli, umodbus_server
from tests.test_pages import Elements, dom

pytestmark = pytest.mark.timeout(120)

LABELS = """profile: labels
parameters:
  outputs_restore_state: {register: 1, type: uint16, values: {"yes": 1, "no": 0}}
  stop_mode: {register: 2, type: uint16, values: {Coast: 0, Ramp: 1, "on, delayed": 2}}
  twins: {register: 3, type: uint16, values: {Fast: 0, FAST: 1}}
  F002: {register: 4, type: uint16, unit: s}
  plain: {register: 5, type: uint16}
"""


def _files(tmp: Path, profile: str, params: str, name: str = "r.yaml") -> Path:
    (tmp / "p.yaml").write_text(profile)
    r = tmp / name
    r.write_text(f"recipe: r\nprofile: p.yaml\nparameters:\n{params}")
    return r


def _messages(path: Path) -> list[str]:
    with pytest.raises(InputError) as err:
        load_recipe(path)
    return [f"{d.line}:{d.col}: {d.message}" for d in err.value.diagnostics]


# ---- values people type ----------------------------------------------------------------------------------


def test_yes_is_taken_as_the_label_written_and_labels_match_without_case(tmp_path: Path) -> None:
    r = _files(tmp_path, LABELS, "  outputs_restore_state: yes\n  stop_mode: coast\n  F002: 30 s\n")
    desired = {d.name: (d.text, d.registers) for d in load_recipe(r).desired}
    assert desired["outputs_restore_state"] == ("yes", (1,))
    assert desired["stop_mode"] == ("Coast", (0,))
    r = _files(tmp_path, LABELS, "  outputs_restore_state: NO\n")
    assert load_recipe(r).desired[0].registers == (0,)


def test_yaml_booleans_without_a_label_and_ambiguous_labels_say_what_to_do(tmp_path: Path) -> None:
    r = _files(tmp_path, LABELS, "  plain: on\n  twins: fast\n  stop_mode: brake\n")
    assert _messages(r) == [
        "4:10: plain: expected a number, a value with a unit or a label, got on (YAML reads it as true); to mean "
        "the text, quote it",
        "5:10: twins: 'fast' matches the labels Fast, FAST, which differ only in case: write one exactly",
        # a label holding a comma is shown quoted: the reader sees where each label ends
        "6:14: stop_mode: 'brake' is not a number with a unit or one of: 'Coast', 'Ramp', 'on, delayed'",
    ]


def test_a_number_with_thousands_separators_is_refused_with_the_fix(tmp_path: Path) -> None:
    r = _files(tmp_path, LABELS, "  F002: 3,000 s\n")
    assert _messages(r) == ["4:9: F002: '3,000 s': write numbers without thousands separators: 3000 s"]


SECRET = 48213  # the unlock password: must never appear in output, reports or snapshots


def test_an_unlock_password_from_the_environment_is_sent_and_never_shown(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "p.yaml").write_text("""profile: locked
unlock:
  - {register: 100, raw: {env: DRIVE_PASSWORD}, description: password}
lock:
  - {register: 100, raw: 0}
parameters:
  ramp: {register: 1, type: uint16, unit: s}
""")
    monkeypatch.delenv("DRIVE_PASSWORD", raising=False)
    with pytest.raises(InputError, match="environment variable DRIVE_PASSWORD is not set"):
        load_profile(str(tmp_path / "p.yaml"))
    monkeypatch.setenv("DRIVE_PASSWORD", str(SECRET))
    prof = load_profile(str(tmp_path / "p.yaml"))
    assert str(SECRET) not in repr(prof) and prof.unlock[0].registers == (SECRET,)
    with SimulatorThread(prof) as sim:
        r = tmp_path / "r.yaml"
        r.write_text(f"recipe: r\nprofile: p.yaml\ndevice: {{url: '{sim.url}'}}\nparameters:\n  ramp: 7 s\n")
        code, out, err = cli(
            capsys,
            "apply",
            str(r),
            "--yes",
            "--json",
            "--state-dir",
            str(tmp_path / "s"),
            "--report",
            str(tmp_path / "run.json"),
        )
        log = list(sim.log)
        assert sim.read("ramp") == (7,)  # the simulator takes writes only once unlocked: the password went out
    assert code == 0, err
    assert any(e.function in (6, 16) and e.address == 100 for e in log)
    saved = [p.read_text() for p in (tmp_path / "s").rglob("*") if p.is_file()]
    for text in (out, err, (tmp_path / "run.json").read_text(), *saved):
        assert str(SECRET) not in text and f"{SECRET:04X}" not in text.upper()


def test_a_secret_from_a_file_that_is_not_a_number_is_refused_without_echoing_it(tmp_path: Path) -> None:
    (tmp_path / "pw").write_text("hunter2\n")
    (tmp_path / "p.yaml").write_text(
        "profile: locked\nunlock:\n  - {register: 100, raw: {file: pw}}\n"
        "parameters:\n  ramp: {register: 1, type: uint16}\n"
    )
    with pytest.raises(InputError) as err:
        load_profile(str(tmp_path / "p.yaml"))
    assert "file pw does not hold an integer" in str(err.value) and "hunter2" not in str(err.value)


# ---- health checks in engineering units -----------------------------------------------------------------

HEALTH = """profile: cabinet
parameters:
  dc_bus_voltage: {register: 10, type: uint16, scale: 0.1, unit: V, access: read-only}
  probe_temp: {register: 11, register_type: input, type: int16, scale: 0.1, unit: degC}
  power: {register: 12, type: float32, unit: kW, access: read-only}
  fault_state: {register: 14, type: uint16, bits: 0..3, values: {none: 0, overvoltage: 1}, access: read-only}
  alarm: {register: 5, register_type: discrete}
  relay: {register: 6, register_type: coil}
  ramp: {register: 1, type: uint16, unit: s}
health:
  - {parameter: dc_bus_voltage, min: 450 V, max: 800 V}
  - {parameter: probe_temp, min: -30 degC, max: 8 degC}
  - {parameter: power, max: 2500 W}
  - {parameter: fault_state, equals: None}
  - {parameter: alarm, equals: off}
  - {parameter: relay, equals: on}
"""


def test_health_checks_by_parameter_read_units_types_and_labels(tmp_path: Path) -> None:
    (tmp_path / "p.yaml").write_text(HEALTH)
    volts, temp, power, fault, alarm, relay = load_profile(str(tmp_path / "p.yaml")).health
    assert (volts.holds([4500]), volts.holds([8001]), volts.failure([8001])) == (
        True,
        False,
        "dc_bus_voltage is 800.1 V, expected 450..800 V",
    )
    minus_31 = (-310) & 0xFFFF  # int16 two's complement
    assert (temp.function, temp.holds([(-300) & 0xFFFF]), temp.holds([minus_31]), temp.failure([minus_31])) == (
        4,
        True,
        False,
        "probe_temp is -31 degC, expected -30..8 degC",
    )
    kw = [*struct.unpack(">HH", struct.pack(">f", 2.75))]
    assert power.count == 2 and not power.holds(kw) and power.failure(kw) == "power is 2.75 kW, expected at most 2.5 kW"
    assert fault.holds([0xFFF0]) and fault.failure([0x0001]) == "fault_state is overvoltage, expected none"
    assert (alarm.function, alarm.holds([0]), alarm.failure([1])) == (2, True, "alarm is true, expected false")
    assert (relay.function, relay.holds([1]), relay.holds([0])) == (1, True, False)


@pytest.mark.parametrize(
    ("check", "why"),
    [
        ("{parameter: nope, max: 1}", "unknown parameter 'nope'"),
        ("{parameter: dc_bus_voltage, max: 8 degC}", "convert"),
        ("{parameter: dc_bus_voltage, register: 10, max: 1}", "names either a 'parameter'"),
        ("{parameter: dc_bus_voltage, bits: 3, max: 1}", "'bits' comes from the parameter"),
        ("{register: 10, min: -300}", "does not fit in the selected bits"),
        ("{register: 10, max: 800 V}", "a raw value is an integer"),
        (
            "{parameter: fault_state, equals: broken}",
            "'broken' is not a number with a unit or one of: none, overvoltage",
        ),
    ],
)
def test_bad_health_checks_say_why(tmp_path: Path, check: str, why: str) -> None:
    (tmp_path / "p.yaml").write_text(HEALTH.split("health:")[0] + f"health:\n  - {check}\n")
    with pytest.raises(InputError) as err:
        load_profile(str(tmp_path / "p.yaml"))
    assert why in str(err.value), str(err.value)


def _apply(
    capsys: pytest.CaptureFixture[str], tmp: Path, url: str, profile: str = "p.yaml"
) -> tuple[int, dict[str, Any]]:
    r = tmp / "r.yaml"
    r.write_text(f"recipe: r\nprofile: {profile}\ndevice: {{url: '{url}', unit: 1}}\nparameters:\n  ramp: 7 s\n")
    code, out, _ = cli(
        capsys,
        "apply",
        str(r),
        "--yes",
        "--json",
        "--soak",
        "400ms",
        "--health-interval",
        "100ms",
        "--state-dir",
        str(tmp / "s"),
    )
    return code, json.loads(out)["devices"][0]


def _init(prof_path: Path, **values: int) -> dict[int, int]:
    prof = load_profile(str(prof_path))
    out = {prof.parameter("dc_bus_voltage").key: 5000, prof.parameter("relay").key: 1}
    for name, raw in values.items():
        out[prof.parameter(name).key] = raw & 0xFFFF
    return out


def test_a_soak_against_the_simulator_passes_then_a_cold_probe_below_zero_rolls_back(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    (tmp_path / "p.yaml").write_text(HEALTH)
    prof = load_profile(str(tmp_path / "p.yaml"))
    with SimulatorThread(prof, init=_init(tmp_path / "p.yaml", probe_temp=-50)) as sim:
        code, dev = _apply(capsys, tmp_path, sim.url)
        log = list(sim.log)
    assert code == 0 and dev["status"] == "ok", dev
    assert {(e.function, e.address) for e in log} >= {(4, 11), (3, 12), (2, 5), (1, 6)}  # each table's own read
    with SimulatorThread(prof, init=_init(tmp_path / "p.yaml", probe_temp=-310)) as sim:
        code, dev = _apply(capsys, tmp_path, sim.url)
        assert sim.read("ramp") == (0,)
        assert not [e for e in sim.log if e.function in (5, 6, 15, 16)]
    # the probe was below its range before the change: the device is not written, and the change not blamed
    assert code == 4 and dev["status"] == "failed" and dev["snapshot"] is None
    assert dev["error"].startswith(
        "health check already failing before the change: probe_temp is -31 degC, expected -30..8 degC"
    )
    with SimulatorThread(prof, init=_init(tmp_path / "p.yaml", alarm=1)) as sim:
        code, dev = _apply(capsys, tmp_path, sim.url)
    assert code == 4 and "alarm is true, expected false" in dev["error"]


def test_float_and_coil_health_checks_against_umodbus(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """An independent device (umodbus): holding registers and coils only, so the profile watches those."""
    (tmp_path / "p.yaml").write_text("""profile: indie
parameters:
  ramp: {register: 1, type: uint16, unit: s}
  power: {register: 12, type: float32, unit: kW, access: read-only}
  relay: {register: 6, register_type: coil, access: read-only}
health:
  - {parameter: power, max: 2500 W}
  - {parameter: relay, equals: on}
""")
    hi, lo = struct.unpack(">HH", struct.pack(">f", 2.25))
    store, coils = {1: 3, 12: hi, 13: lo}, {6: 1}
    with umodbus_server(store, coils) as port:  # one connection at a time: the rollback waits for none
        code, dev = _apply(capsys, tmp_path, f"tcp://127.0.0.1:{port}")
        assert (code, dev["status"], store[1]) == (0, "ok", 7), dev
        store[12], store[13] = struct.unpack(">HH", struct.pack(">f", 2.75))
        store[1] = 3
        code, dev = _apply(capsys, tmp_path, f"tcp://127.0.0.1:{port}")
        assert store[1] == 3, (dev["status"], dev["error"])  # not written: over the limit before the change
    assert code == 4 and dev["status"] == "failed"
    assert "already failing before the change: power is 2.75 kW, expected at most 2.5 kW" in dev["error"]


# ---- rollouts over mixed lines -------------------------------------------------------------------------

RELAY = "profile: relay\nparameters:\n  safety_timer_s: {register: 0x30, type: uint16, unit: s, max: 3600}\n"


def _mixed_line(tmp: Path, urls: dict[str, str]) -> str:
    """Drives first in the file (3), then relays (8): the relays' canary must not wait for the drives."""
    (tmp / "relay.yaml").write_text(RELAY)
    (tmp / "relay-r.yaml").write_text("recipe: relay\nprofile: relay.yaml\nparameters:\n  safety_timer_s: 900 s\n")
    (tmp / "drive-r.yaml").write_text("recipe: drive\nprofile: example-inverter\nparameters:\n  F07: 10 s\n")
    inv = tmp / "line.yaml"
    inv.write_text(
        "defaults: {timeout: 1.0, retries: 0}\ngroups:\n"
        "  drives: {recipe: drive-r.yaml, profile: example-inverter}\n"
        "  relays: {recipe: relay-r.yaml, profile: relay.yaml}\n  east: {}\n  west: {}\ndevices:\n"
        + "".join(
            f"  {n}: {{url: '{u}', groups: [{'drives' if n.startswith('drive') else 'relays'}, "
            f"{'east' if int(n[-1]) % 2 else 'west'}]}}\n"
            for n, u in urls.items()
        )
    )
    return str(inv)


def test_each_batch_covers_every_profile_and_batch_by_group_uses_the_first_group(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    relay = load_profile_text(tmp_path, RELAY)
    names = [f"drive{i}" for i in range(3)] + [f"relay{i}" for i in range(8)]
    sims = [Simulator(builtin_profile("example-inverter")) for _ in range(3)] + [Simulator(relay) for _ in range(8)]
    with Simulators(sims) as running:
        inv = _mixed_line(tmp_path, {n: s.url for n, s in zip(names, running, strict=True)})
        code, out, err = cli(
            capsys,
            "apply",
            "--inventory",
            inv,
            "--yes",
            "--json",
            "--batch",
            "1,25%,100%",
            "--parallel",
            "1",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 0, err
        batch = {d["name"]: d["batch"] for d in json.loads(out)["devices"]}
        # batch 1: one of each profile; batch 2: 25% of each, rounded (3 -> 1, 8 -> 2); batch 3: the rest
        assert batch == {
            "drive0": 1,
            "relay0": 1,
            "drive1": 2,
            "relay1": 2,
            "relay2": 2,
            "drive2": 3,
            **{f"relay{i}": 3 for i in range(3, 8)},
        }
        starts = {n: min(e.time for e in s.log if e.function in (6, 16)) for n, s in zip(names, running, strict=True)}
        assert max(starts[n] for n, b in batch.items() if b == 1) < min(starts[n] for n, b in batch.items() if b == 2)
        code, out, _ = cli(
            capsys,
            "apply",
            "--inventory",
            inv,
            "--yes",
            "--json",
            "--batch",
            "1,100%",
            "--batch-by",
            "group",
            "--write-all",
            "--state-dir",
            str(tmp_path / "s"),
        )
        assert code == 0
        by_group = {d["name"]: d["batch"] for d in json.loads(out)["devices"]}
        assert [n for n, b in by_group.items() if b == 1] == ["drive0", "relay0"]  # drives, relays: first groups


def test_any_failed_canary_device_ends_the_rollout(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    relay = load_profile_text(tmp_path, RELAY)
    names = ["drive0", "drive1", "relay0", "relay1"]
    broken = Faults(fail_registers=frozenset({0x30}))
    sims = [Simulator(builtin_profile("example-inverter")) for _ in range(2)] + [
        Simulator(relay, faults=broken),
        Simulator(relay),
    ]
    with Simulators(sims) as running:
        inv = _mixed_line(tmp_path, {n: s.url for n, s in zip(names, running, strict=True)})
        code, out, _ = cli(
            capsys,
            "apply",
            "--inventory",
            inv,
            "--yes",
            "--json",
            "--batch",
            "1,100%",
            "--state-dir",
            str(tmp_path / "s"),
        )
    by = {d["name"]: d for d in json.loads(out)["devices"]}
    assert code == 4 and by["drive0"]["status"] == "ok" and by["relay0"]["status"] in ("failed", "partial")
    for n in ("drive1", "relay1"):  # the drive canary was fine: one failed canary of another profile still stops it
        assert by[n]["status"] == "skipped" and "the canary batch 1 did not end ok (relay0 " in by[n]["error"]


def load_profile_text(tmp: Path, text: str, name: str = "relay.yaml") -> Any:
    (tmp / name).write_text(text)
    return load_profile(str(tmp / name))


def test_pull_over_an_inventory_uses_each_devices_recipe_profile(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    relay = load_profile_text(tmp_path, RELAY)
    with Simulators([Simulator(builtin_profile("example-inverter")), Simulator(relay)]) as (drive, rel):
        (tmp_path / "relay-r.yaml").write_text(
            "recipe: relay\nprofile: relay.yaml\nparameters:\n  safety_timer_s: 900 s\n"
        )
        (tmp_path / "drive-r.yaml").write_text("recipe: drive\nprofile: example-inverter\nparameters:\n  F07: 10 s\n")
        inv = tmp_path / "line.yaml"  # recipes only: no profile anywhere in the inventory
        inv.write_text(
            f"devices:\n  drive0: {{url: '{drive.url}', recipe: drive-r.yaml}}\n"
            f"  relay0: {{url: '{rel.url}', recipe: relay-r.yaml}}\n"
        )
        code, _, err = cli(capsys, "pull", "--inventory", str(inv), "-o", str(tmp_path / "pulled"))
    assert code == 0, err
    assert "safety_timer_s: 0 s" in (tmp_path / "pulled" / "relay0.yaml").read_text()
    assert "F07:" in (tmp_path / "pulled" / "drive0.yaml").read_text()


def test_health_is_watched_while_the_confirmation_waits(tmp_path: Path) -> None:
    """--confirm-within reads the health checks until the answer: a device that fails meanwhile is rolled back
    at once, long before the confirmation time runs out, and its commit is never sent."""
    from deployer.window.confirm import awaiting
    from tests.helpers import wait_for

    prof = builtin_profile("example-inverter")
    fault, commit, f07 = prof.health[0].address, prof.commit[0].address, prof.parameter("F07").address
    state = str(tmp_path / "s")
    with SimulatorThread(prof) as sim:
        before = sim.registers()
        r = tmp_path / "r.yaml"
        r.write_text(f"recipe: r\nprofile: example-inverter\ndevice: {{url: '{sim.url}'}}\nparameters:\n  F07: 3 s\n")
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "deployer",
                "apply",
                str(r),
                "--yes",
                "--json",
                "--confirm-within",
                "1h",
                "--health-interval",
                "100ms",
                "--state-dir",
                state,
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            wait_for(lambda: bool(awaiting(state)) or proc.poll() is not None)
            wait_for(lambda: sum(1 for e in sim.log if e.function == 3 and e.address == fault) >= 2)
            sim.set_register(fault, 7)
            out, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
        log = list(sim.log)
        after = sim.registers()
    assert proc.returncode == 4, err
    dev = json.loads(out)["devices"][0]
    assert dev["status"] == "rolled-back" and dev["commit"] == "not sent"
    assert "of the confirmation wait: register 0x2000 (drive fault code is zero) is 7, expected 0" in dev["error"]
    assert {a: v for a, v in after.items() if a != fault} == {a: v for a, v in before.items() if a != fault}
    assert not any(e.function in (6, 16) and e.address <= commit < e.address + e.count for e in log)
    assert any(e.function in (6, 16) and e.address <= f07 + 1 < e.address + e.count for e in log)


# ---- wb-mqtt-serial templates that deploy; firmware-aware profiles -----------------------------------

# our own template in wb-mqtt-serial's format: a refrigeration controller's set point as a channel, a relay
# coil, a defrost pushbutton, a firmware-gated parameter
FRIDGE = """{
  "device_type": "acme_fridge", "title": "Acme fridge controller",
  "device": {
    "name": "Acme fridge", "id": "acme-fridge",
    "parameters": [
      {"id": "differential", "title": "Differential", "address": 12, "format": "s16", "scale": 0.1,
       "min": 0.1, "max": 20, "fw": "2.0"}
    ],
    "channels": [
      {"name": "Temperature Set Point", "reg_type": "holding", "address": 10, "format": "s16", "scale": 0.1,
       "units": "deg C", "type": "value"},
      {"name": "Probe", "reg_type": "input", "address": 0, "format": "s16", "scale": 0.1, "units": "deg C"},
      {"name": "Compressor Relay", "reg_type": "coil", "address": 3, "type": "switch"},
      {"name": "Defrost Command", "reg_type": "coil", "address": 4, "type": "pushbutton"}
    ]
  }
}
"""


def _fridge(tmp: Path, capsys: pytest.CaptureFixture[str]) -> Any:
    (tmp / "fridge.json").write_text(FRIDGE)
    code, _, err = cli(
        capsys, "profiles", "import", "wb-template", str(tmp / "fridge.json"), "-o", str(tmp / "fridge.yaml")
    )
    assert code == 0, err
    return load_profile(str(tmp / "fridge.yaml"))


def test_a_wb_template_set_point_is_planned_and_applied(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    prof = _fridge(tmp_path, capsys)
    with SimulatorThread(prof, quirks=Quirks(identity={0: "Acme", 1: "FR-1", 2: "2.3"})) as sim:
        r = tmp_path / "r.yaml"
        r.write_text(
            f"recipe: r\nprofile: fridge.yaml\ndevice: {{url: '{sim.url}'}}\nparameters:\n"
            "  Temperature_Set_Point: -18.5 degC\n  Compressor_Relay: on\n  differential: 2\n"
        )
        code, out, err = cli(capsys, "plan", str(r), "--json")
        assert code == 0, err
        assert [
            (w["function"], w["address"], w["values"]) for w in json.loads(out)["steps"] if w["kind"] == "write"
        ] == [(16, 10, [(-185) & 0xFFFF]), (16, 12, [20]), (5, 3, [1])]
        code, out, err = cli(capsys, "apply", str(r), "--yes", "--json", "--state-dir", str(tmp_path / "s"))
        assert code == 0, out
        assert sim.read("Temperature_Set_Point") == ((-185) & 0xFFFF,) and sim.read("Compressor_Relay") == (1,)
        # the pushbutton is an action: pull leaves it out, a recipe naming it is told so
        code, out, err = cli(capsys, "pull", "--profile", str(tmp_path / "fridge.yaml"), "--device", sim.url)
        assert code == 0 and "Compressor_Relay" in out and "Defrost_Command" not in out
    r.write_text("recipe: r\nprofile: fridge.yaml\nparameters:\n  Defrost_Command: on\n")
    assert _messages(r) == [
        "4:3: Defrost_Command is an action in profile acme_fridge (a momentary command such as "
        "a defrost or reset), not a setting: a recipe does not set it"
    ]


def test_a_firmware_gate_refuses_a_wrong_revision_before_any_write(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    prof = _fridge(tmp_path, capsys)
    with SimulatorThread(prof, quirks=Quirks(identity={0: "Acme", 1: "FR-1", 2: "1.9.4"})) as sim:
        r = tmp_path / "r.yaml"
        r.write_text(
            f"recipe: r\nprofile: fridge.yaml\ndevice: {{url: '{sim.url}'}}\nparameters:\n"
            "  Temperature_Set_Point: -18 degC\n  differential: 2\n"
        )
        code, out, _ = cli(capsys, "apply", str(r), "--yes", "--json", "--state-dir", str(tmp_path / "s"))
        log = list(sim.log)
    dev = json.loads(out)["devices"][0]
    assert code == 4 and dev["status"] == "failed"
    assert dev["error"] == ("firmware '1.9.4' (Function 43 revision): differential needs 2.0; nothing was written")
    assert not any(e.function in (5, 6, 15, 16) for e in log)
    # the whole profile can be gated too, and from a register that holds the revision as text
    (tmp_path / "p.yaml").write_text(
        "profile: gated\nfirmware: {register: 0x40, count: 2, format: text, "
        "applies: '>=3, <4'}\nparameters:\n  x: {register: 1, type: uint16}\n"
        "  fw: {register: 0x40, type: string, count: 2, access: read-only}\n"
    )
    gated = load_profile(str(tmp_path / "p.yaml"))
    with SimulatorThread(gated, init={0x40: 0x322E, 0x41: 0x3900}) as sim:  # "2.9"
        (tmp_path / "g.yaml").write_text(
            f"recipe: g\nprofile: p.yaml\ndevice: {{url: '{sim.url}'}}\nparameters:\n  x: 5\n"
        )
        code, out, _ = cli(
            capsys, "apply", str(tmp_path / "g.yaml"), "--yes", "--json", "--state-dir", str(tmp_path / "s")
        )
        assert sim.read("x") == (0,)
    assert code == 4 and json.loads(out)["devices"][0]["error"] == (
        "firmware '2.9' (register 0x0040) is not one profile gated applies to (>=3, <4); nothing was written"
    )


def test_a_jinja_template_says_how_to_render_it(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    src = tmp_path / "mr6.json.jinja"
    src.write_text(
        '{\n  "device_type": "mr6",\n  "device": {\n    {% for i in range(6) %}"x": {{ i }}{% endfor %}\n  }\n}\n'
    )
    code, _, err = cli(capsys, "profiles", "import", "wb-template", str(src))
    assert code == 1 and f"{src}:4:5: error: a Jinja template (.json.jinja)" in err
    assert f"> {tmp_path / 'mr6.json'}, then import {tmp_path / 'mr6.json'}" in err and "Traceback" not in err


# ---- the commissioning record, printed -------------------------------------------------------------------


def _pdf_text(page: Path, tmp: Path) -> str:
    from tests.test_pages import browser

    pdf = tmp / (page.stem + ".pdf")
    proc = browser(f"--print-to-pdf={pdf}", "--no-pdf-header-footer", page.as_uri(), tmp=tmp)
    assert proc.returncode == 0 and pdf.read_bytes().startswith(b"%PDF"), proc.stderr
    return subprocess.run(["pdftotext", "-layout", str(pdf), "-"], capture_output=True, text=True, check=True).stdout


@pytest.mark.skipif(shutil.which("pdftotext") is None, reason="pdftotext (poppler-utils) is not installed")
def test_the_printed_record_has_the_outcome_one_sign_off_page_numbers_identity_and_unknown_states(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    from tests.test_pages import CHROMIUM

    if CHROMIUM is None:
        pytest.skip("no Chromium")
    prof = builtin_profile("example-inverter")
    trip = parse_fault_rule("F07 < 2 s: 0x2000=7", prof)
    ident = Quirks(identity={0: "ACME", 1: "AC-7", 2: "2.1"})
    sims = [
        Simulator(prof, quirks=ident),
        Simulator(prof, quirks=ident, faults=Faults(rules=(trip,))),
        Simulator(prof, quirks=ident),
    ]
    with Simulators(sims) as running:
        (tmp_path / "ok.yaml").write_text("recipe: ramp\nprofile: example-inverter\nparameters:\n  F07: 10 s\n")
        (tmp_path / "trip.yaml").write_text("recipe: trip\nprofile: example-inverter\nparameters:\n  F07: 1.5 s\n")
        inv = tmp_path / "line.yaml"
        inv.write_text(
            "meta: {site: Plant 3, project: P-2291 retrofit, customer: ACME Foods}\n"
            "defaults: {timeout: 1.0, retries: 0, recipe: ok.yaml}\ndevices:\n"
            + "".join(
                f"  drive-{i}: {{url: '{s.url}'{', recipe: trip.yaml' if i == 1 else ''}}}\n"
                for i, s in enumerate(running)
            )
        )
        page, report = tmp_path / "run.html", tmp_path / "run.json"
        code, _, err = cli(
            capsys,
            "apply",
            "--inventory",
            str(inv),
            "--yes",
            "--soak",
            "300ms",
            "--health-interval",
            "100ms",
            "--state-dir",
            str(tmp_path / "st"),
            "--report",
            str(report),
            "--html",
            str(page),
            "--meta",
            "line=line 3",
        )
        assert code == 4, err
    run_id = json.loads(report.read_text())["run"]["id"]
    words = _pdf_text(page, tmp_path)
    first = words.split("\f")[0]
    assert "Outcome" in first and "Sign-off" in first and "Commissioned by" in first and "Checked by" in first
    assert "2 devices passed the soak" in first and "1 device failed a health check" in first
    assert words.count("Commissioned by") == 1 and "Signature" not in words.replace("signature", "")
    pages = words.count("\f")
    assert f"page 1 of {pages}" in words and f"page {pages} of {pages}" in words
    for n in range(pages):  # every page: the site's line at the top, the run id at the bottom
        text = words.split("\f")[n]
        assert "site: Plant 3" in text and "customer: ACME Foods" in text and "line: line 3" in text, n
        assert f"run {run_id}" in text, n
    assert "vendor ACME, product code AC-7, revision 2.1" in words
    assert "--health-interval 100ms" in words and "--state-dir" in words  # wrapped at spaces, not inside a word

    # a device whose final state nobody knows: unreachable during its rollback
    doc = json.loads(report.read_text())
    dev = next(d for d in doc["devices"] if d["name"] == "drive-2")
    dev["status"], dev["seen"] = "failed", "2026-11-25T05:00:00Z"
    dev["error"] = (
        "health check failed after 0.2 s of the 300ms soak: drive fault; the rollback did not verify "
        "(unreachable: no answer)"
    )
    for p in dev["parameters"]:
        p["status"] = "unverified"
    report.write_text(json.dumps(doc))
    code, _, _ = cli(capsys, "report", str(report), "--html", str(tmp_path / "again.html"))
    words = " ".join(_pdf_text(tmp_path / "again.html", tmp_path).split())
    assert code == 0 and "unknown (last seen 10 s at 2026-11-25T05:00:00Z)" in words
    assert "1 device in a state nobody knows" in words

    # compact: the device list, and parameters only of the devices that changed or did not end ok
    code, _, _ = cli(capsys, "report", str(report), "--html", str(tmp_path / "compact.html"), "--compact")
    assert code == 0
    compact = Elements(dom(tmp_path / "compact.html", tmp_path))
    sections = [str(d["text"]).split()[0] for d in compact.all("details", "device")]
    assert sorted(sections) == ["drive-0", "drive-1", "drive-2"]  # all changed (or did not end ok) here
    assert len([r for r in compact.all("tr", "dev")]) == 3


@pytest.mark.skipif(shutil.which("pdftotext") is None, reason="pdftotext (poppler-utils) is not installed")
def test_the_as_found_record_drops_the_run_columns(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    from tests.test_pages import CHROMIUM

    if CHROMIUM is None:
        pytest.skip("no Chromium")
    with Simulators([Simulator(builtin_profile("example-inverter"))]) as (sim,):
        inv = tmp_path / "line.yaml"
        inv.write_text(f"meta: {{site: Plant 3}}\ndevices:\n  drive-0: {{url: '{sim.url}'}}\n")
        page = tmp_path / "found.html"
        code, _, err = cli(
            capsys,
            "pull",
            "--inventory",
            str(inv),
            "--profile",
            "example-inverter",
            "-o",
            str(tmp_path / "pulled"),
            "--html",
            str(page),
        )
        assert code == 0, err
    heads = [str(h["text"]) for h in Elements(dom(page, tmp_path)).all("th")]
    assert "batch" not in heads and "seconds" not in heads and "requests" not in heads and "device" in heads
    words = _pdf_text(page, tmp_path)
    assert "site: Plant 3" in words and "page 1 of" in words and words.count("Commissioned by") == 1
