"""Recipes and profiles: each loading rule, with real files."""

from __future__ import annotations

from decimal import Decimal
from pathlib import Path

import pytest

from deployer.errors import InputError
from deployer.profile import builtin_profile, builtin_profile_ids, load_profile, wire_address
from deployer.recipe.loader import load_recipe
from deployer.recipe.text import recipe_text

EXAMPLES = Path(__file__).parent.parent / "recipes" / "examples"


def write(tmp: Path, name: str, text: str) -> str:
    p = tmp / name
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(text)
    return str(p)


def values(path: str) -> dict[str, tuple[int, ...]]:
    return {d.name: d.registers for d in load_recipe(path).desired}


def test_builtin_profiles_load() -> None:
    assert {"omron-m1", "oriental-az", "example-inverter"} <= set(builtin_profile_ids())
    omron = builtin_profile("omron-m1")
    assert omron.parameter("F07").address == 0x1102  # register number 1103h - 1
    az = builtin_profile("oriental-az")
    assert az.parameter("operation_data[3].starting_rate").address == 6342
    assert az.parameter("operation_data[3].operating_current").address == 6346
    assert az.parameter("operation_data[0].starting_rate").address == 0x1800 + 6
    assert len(az.parameters) == 256 * 3


def test_examples_encode_like_the_manuals() -> None:
    assert values(str(EXAMPLES / "omron-m1-accel.yaml")) == {"F07": (0x0000, 0x03E8)}
    assert values(str(EXAMPLES / "oriental-az-op3.yaml")) == {
        "operation_data[3].starting_rate": (0, 10000),
        "operation_data[3].stopping_rate": (0, 20000),
        "operation_data[3].operating_current": (0, 500),
    }


@pytest.mark.parametrize(
    ("number", "mode", "wire"),
    [
        (0x1102, "address", 0x1102),
        (0x1103, "register-number", 0x1102),
        (40001, "modicon", 0),
        (44354, "modicon", 4353),
        (400001, "modicon", 0),
        (465536, "modicon", 65535),
    ],
)
def test_addressing_modes(number: int, mode: str, wire: int) -> None:
    assert wire_address(number, mode) == wire


@pytest.mark.parametrize("reg", ["1103h", "0x1103", 4355, "4355"])
def test_register_spellings(tmp_path: Path, reg: object) -> None:
    p = write(
        tmp_path,
        "p.yaml",
        f"profile: p\naddressing: register-number\nparameters:\n  a: {{register: {reg}, type: uint16}}\n",
    )
    assert load_profile(p).parameter("a").address == 0x1102


@pytest.mark.parametrize(
    ("text", "raw"),
    [
        ("10 s", 1000),
        ("10000 ms", 1000),
        ("10", 1000),
        ("10.00", 1000),
        ("0.5 min", 3000),
        ("{raw: 1234}", 1234),
        ("{value: 10.004 s, rounding: nearest}", 1000),
    ],
)
def test_value_forms(tmp_path: Path, text: str, raw: int) -> None:
    p = write(tmp_path, "r.yaml", f"recipe: r\nprofile: omron-m1\nparameters:\n  F07: {text}\n")
    assert values(p)["F07"] == (raw >> 16, raw & 0xFFFF)


def test_units_labels_percent_rpm(tmp_path: Path) -> None:
    p = write(
        tmp_path,
        "r.yaml",
        "recipe: r\nprofile: example-inverter\nparameters:\n"
        "  torque_limit: 50 %\n  base_speed: 1500 rpm\n  stop_mode: coast\n"
        "  speed_offset: -25\n  max_frequency: 0.06 kHz\n  pid_gain: 2.5\n",
    )
    v = values(p)
    assert v["torque_limit"] == (500,)
    assert v["base_speed"] == (1500,)
    assert v["stop_mode"] == (1,)
    assert v["speed_offset"] == (0x10000 - 25,)
    assert v["max_frequency"] == (600,)
    assert v["pid_gain"] == (0x4020, 0)


def test_rounding_nearest_at_recipe_level(tmp_path: Path) -> None:
    p = write(tmp_path, "r.yaml", "recipe: r\nprofile: omron-m1\nrounding: nearest\nparameters:\n  F07: 10.006 s\n")
    assert values(p)["F07"] == (0, 1001)


def test_extends_chain_merges_and_this_file_wins(tmp_path: Path) -> None:
    write(
        tmp_path,
        "base/base.yaml",
        "recipe: base\nprofile: example-inverter\nparameters:\n  F07: 5 s\n  stop_mode: ramp\n",
    )
    write(tmp_path, "mid.yaml", "recipe: mid\nextends: base/base.yaml\nparameters:\n  stop_mode: coast\n")
    top = write(tmp_path, "top.yaml", "recipe: top\nextends: mid.yaml\nparameters:\n  F08: 1 s\n")
    r = load_recipe(top)
    assert r.name == "top" and r.profile.id == "example-inverter"
    assert {d.name: d.text for d in r.desired} == {"F07": "5 s", "stop_mode": "coast", "F08": "1 s"}


def test_profile_path_relative_to_recipe(tmp_path: Path) -> None:
    write(
        tmp_path, "profiles/dev.yaml", "profile: dev\nparameters:\n  speed: {register: 10, type: uint16, unit: rpm}\n"
    )
    r = write(tmp_path, "recipes/r.yaml", "recipe: r\nprofile: ../profiles/dev.yaml\nparameters:\n  speed: 100\n")
    assert values(r) == {"speed": (100,)}


def test_table_entry_forms(tmp_path: Path) -> None:
    p = write(
        tmp_path,
        "r.yaml",
        "recipe: r\nprofile: oriental-az\nparameters:\n"
        "  operation_data[0]: {starting_rate: 1}\n  operation_data[255].stopping_rate: 2\n",
    )
    assert values(p) == {"operation_data[0].starting_rate": (0, 1), "operation_data[255].stopping_rate": (0, 2)}


def test_all_errors_at_once(tmp_path: Path) -> None:
    p = write(
        tmp_path,
        "r.yaml",
        "recipe: r\nprofile: example-inverter\nparameters:\n  F07: 7000 s\n  F08: 10 Hz\n  firmware: 1\n  nope: 1\n",
    )
    with pytest.raises(InputError) as err:
        load_recipe(p)
    assert [(d.line, d.col) for d in err.value.diagnostics] == [(4, 8), (5, 8), (6, 3), (7, 3)]


def test_profile_overlap_names_both(tmp_path: Path) -> None:
    p = write(
        tmp_path,
        "p.yaml",
        "profile: p\nparameters:\n  speed: {register: 100, type: uint32}\n  limit: {register: 101, type: uint16}\n",
    )
    with pytest.raises(InputError) as err:
        load_profile(p)
    (d,) = err.value.diagnostics
    assert (d.line, d.col) == (4, 3) and "limit" in d.message and "speed" in d.message and "line 3" in d.message


def test_snapshot_text_loads_back_to_the_same_registers(tmp_path: Path) -> None:
    r = load_recipe(str(EXAMPLES / "conveyor-line3.yaml"))
    text = recipe_text(
        "example-inverter", {d.parameter: d.registers for d in r.desired}, name="snap", comment="a snapshot"
    )
    p = write(tmp_path, "snap.yaml", text)
    assert values(p) == {d.name: d.registers for d in r.desired}


def test_recipe_text_writes_floats_as_a_person_would(tmp_path: Path) -> None:
    # a pulled float32 of 4500 rpm read '4.5e+03 rpm'; an exponent only where repr would use one
    write(
        tmp_path,
        "p.yaml",
        "profile: p\nparameters:\n"
        "  speed: {register: 0, type: float32, unit: rpm}\n"
        "  tiny: {register: 2, type: float32}\n"
        "  gain: {register: 4, type: float64}\n"
        "  half: {register: 8, type: float32}\n",
    )
    prof = load_profile(str(tmp_path / "p.yaml"))
    regs = {
        prof.parameter("speed"): prof.parameter("speed").encode(4500.0),
        prof.parameter("tiny"): prof.parameter("tiny").encode(1.5e-7),
        prof.parameter("gain"): prof.parameter("gain").encode(120000.0),
        prof.parameter("half"): prof.parameter("half").encode(0.5),
    }
    text = recipe_text("p.yaml", regs, name="r")
    assert "speed: 4500 rpm\n" in text
    assert "tiny: 1.5e-07\n" in text
    assert "gain: 120000.0\n" in text
    assert "half: 0.5\n" in text
    assert values(write(tmp_path, "r.yaml", text)) == {p.name: r for p, r in regs.items()}


def test_recipe_text_keeps_out_of_range_values_as_comments(tmp_path: Path) -> None:
    prof = builtin_profile("example-inverter")
    f07 = prof.parameter("F07")
    text = recipe_text("example-inverter", {f07: f07.encode(700000), prof.parameter("F08"): (0, 500)}, name="s")
    assert "# F07: raw 700000 (000A AE60h) is outside the profile's range 0..6000 s" in text
    p = write(tmp_path, "s.yaml", text)
    assert values(p) == {"F08": (0, 500)}


def test_default_values_are_decimal() -> None:
    assert builtin_profile("example-inverter").parameter("F07").default == Decimal(5)


def test_word_order_per_profile_and_per_parameter(tmp_path: Path) -> None:
    write(
        tmp_path,
        "p.yaml",
        "profile: p\nword_order: little\nparameters:\n"
        "  lo: {register: 0, type: uint32}\n"
        "  hi: {register: 2, type: uint32, word_order: big}\n"
        "  f: {register: 4, type: float32}\n",
    )
    r = write(tmp_path, "r.yaml", "recipe: r\nprofile: p.yaml\nparameters: {lo: 300000, hi: 300000, f: 2.5}\n")
    assert values(r) == {"lo": (0x93E0, 0x0004), "hi": (0x0004, 0x93E0), "f": (0x0000, 0x4020)}


def test_modicon_profile(tmp_path: Path) -> None:
    p = write(
        tmp_path,
        "p.yaml",
        "profile: p\naddressing: modicon\nparameters:\n"
        "  a: {register: 44355, type: uint16}\n  b: {register: 404356, type: uint16}\n",
    )
    prof = load_profile(p)
    assert (prof.parameter("a").address, prof.parameter("b").address) == (4354, 4355)
