"""Commissioning: values as people type them, secrets, health checks in engineering units (simulator and umodbus)."""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any

import pytest

from deployer.load.diagnostics import InputError
from deployer.profile import load_profile
from deployer.recipe.loader import load_recipe
from deployer.testing.simulator import SimulatorThread
from tests.helpers import cli, umodbus_server

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
        capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
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
        code, out, err = cli(capsys, "apply", str(r), "--yes", "--json", "--state-dir", str(tmp_path / "s"),
                             "--report", str(tmp_path / "run.json"))
        log = list(sim.log)
        assert sim.read("ramp") == (7,)  # the simulator takes writes only once unlocked: the password went out
    assert code == 0, err
    assert any(e.function in (6, 16) and e.address == 100 for e in log)
    saved = [p.read_text() for p in (tmp_path / "s").rglob("*") if p.is_file()]
    for text in (out, err, (tmp_path / "run.json").read_text(), *saved):
        assert str(SECRET) not in text and f"{SECRET:04X}" not in text.upper()


def test_a_secret_from_a_file_that_is_not_a_number_is_refused_without_echoing_it(tmp_path: Path) -> None:
    (tmp_path / "pw").write_text("hunter2\n")
    (tmp_path / "p.yaml").write_text("profile: locked\nunlock:\n  - {register: 100, raw: {file: pw}}\n"
                                     "parameters:\n  ramp: {register: 1, type: uint16}\n")
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
        True, False, "dc_bus_voltage is 800.1 V, expected 450..800 V")
    minus_31 = (-310) & 0xFFFF  # int16 two's complement
    assert (temp.function, temp.holds([(-300) & 0xFFFF]), temp.holds([minus_31]), temp.failure([minus_31])) == (
        4, True, False, "probe_temp is -31 degC, expected -30..8 degC")
    kw = [*struct.unpack(">HH", struct.pack(">f", 2.75))]
    assert power.count == 2 and not power.holds(kw) and power.failure(kw) == "power is 2.75 kW, expected at most 2.5 kW"
    assert fault.holds([0xFFF0]) and fault.failure([0x0001]) == "fault_state is overvoltage, expected none"
    assert (alarm.function, alarm.holds([0]), alarm.failure([1])) == (2, True, "alarm is true, expected false")
    assert (relay.function, relay.holds([1]), relay.holds([0])) == (1, True, False)


@pytest.mark.parametrize(("check", "why"), [
    ("{parameter: nope, max: 1}", "unknown parameter 'nope'"),
    ("{parameter: dc_bus_voltage, max: 8 degC}", "convert"),
    ("{parameter: dc_bus_voltage, register: 10, max: 1}", "names either a 'parameter'"),
    ("{parameter: dc_bus_voltage, bits: 3, max: 1}", "'bits' comes from the parameter"),
    ("{register: 10, min: -300}", "does not fit in the selected bits"),
    ("{register: 10, max: 800 V}", "a raw value is an integer"),
    ("{parameter: fault_state, equals: broken}", "'broken' is not a number with a unit or one of: none, overvoltage"),
])
def test_bad_health_checks_say_why(tmp_path: Path, check: str, why: str) -> None:
    (tmp_path / "p.yaml").write_text(HEALTH.split("health:")[0] + f"health:\n  - {check}\n")
    with pytest.raises(InputError) as err:
        load_profile(str(tmp_path / "p.yaml"))
    assert why in str(err.value), str(err.value)


def _apply(capsys: pytest.CaptureFixture[str], tmp: Path, url: str,
           profile: str = "p.yaml") -> tuple[int, dict[str, Any]]:
    r = tmp / "r.yaml"
    r.write_text(f"recipe: r\nprofile: {profile}\ndevice: {{url: '{url}', unit: 1}}\nparameters:\n  ramp: 7 s\n")
    code, out, _ = cli(capsys, "apply", str(r), "--yes", "--json", "--soak", "400ms", "--health-interval",
                         "100ms", "--state-dir", str(tmp / "s"))
    return code, json.loads(out)["devices"][0]


def _init(prof_path: Path, **values: int) -> dict[int, int]:
    prof = load_profile(str(prof_path))
    out = {prof.parameter("dc_bus_voltage").key: 5000, prof.parameter("relay").key: 1}
    for name, raw in values.items():
        out[prof.parameter(name).key] = raw & 0xFFFF
    return out


def test_a_soak_against_the_simulator_passes_then_a_cold_probe_below_zero_rolls_back(
        capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
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
    assert code == 4 and dev["status"] == "rolled-back"
    assert "probe_temp is -31 degC, expected -30..8 degC" in dev["error"]
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
    with umodbus_server(store, coils, connections=2) as port:
        code, dev = _apply(capsys, tmp_path, f"tcp://127.0.0.1:{port}")
        assert (code, dev["status"], store[1]) == (0, "ok", 7), dev
        store[12], store[13] = struct.unpack(">HH", struct.pack(">f", 2.75))
        store[1] = 3
        code, dev = _apply(capsys, tmp_path, f"tcp://127.0.0.1:{port}")
        assert store[1] == 3, (dev["status"], dev["error"])  # rolled back
    assert code == 4 and "power is 2.75 kW, expected at most 2.5 kW" in dev["error"]
