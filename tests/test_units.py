"""Units as the field means them: a revolution is one cycle (3000 rpm = 50 Hz), angles and cycles stay apart
unless a parameter says otherwise, and the conversions drive, pump and HVAC parameters use come out exact."""

from __future__ import annotations

from decimal import Decimal
from pathlib import Path

import pytest

from deployer.errors import InputError
from deployer.profile import load_profile, units
from deployer.testing.simulator import Simulator
from tests.helpers import Simulators, cli, count

# (value, from, to, expected): the exact figures, to 28 digits where they do not end (1 psi = 0.45359237 kg *
# 9.80665 m/s2 / 0.0254^2 m2 = 6894.757293168361336722673445... Pa)
TABLE = [
    # speed and frequency: a revolution is one cycle
    ("3000", "rpm", "Hz", "50"),
    ("50", "Hz", "rpm", "3000"),
    ("1", "rps", "Hz", "1"),
    ("60", "rpm", "rps", "1"),
    ("1500", "1/min", "Hz", "25"),
    ("1500", "1/min", "rpm", "1500"),
    ("1500", "min^-1", "rpm", "1500"),
    ("25", "Hz", "1/min", "1500"),
    ("1", "kHz", "Hz", "1000"),
    ("1450", "r/min", "rpm", "1450"),
    ("3", "rev/s", "rpm", "180"),
    ("600", "rpm", "rev/s", "10"),
    ("1", "Hz", "1/s", "1"),
    # ratios
    ("50", "%", "", "0.5"),
    ("12.5", "%", "‰", "125"),
    ("125", "‰", "%", "12.5"),
    ("5", "permille", "percent", "0.5"),
    ("0.25", "", "%", "25"),
    ("45", "%RH", "%", "45"),
    # temperatures and their differences
    ("20", "degC", "K", "293.15"),
    ("293.15", "K", "degC", "20"),
    ("68", "degF", "degC", "20"),
    ("20", "degC", "degF", "68"),
    ("-40", "degC", "degF", "-40"),
    ("32", "°F", "°C", "0"),
    ("0", "degC", "K", "273.15"),
    ("5", "delta_degC", "K", "5"),
    ("5", "K", "delta_degC", "5"),
    ("9", "delta_degF", "delta_degC", "5"),
    ("9", "delta_degF", "K", "5"),
    ("5", "Δ°C", "delta_degF", "9"),
    # pressure
    ("1", "bar", "kPa", "100"),
    ("250", "kPa", "bar", "2.5"),
    ("1", "bar", "mbar", "1000"),
    ("1", "psi", "Pa", "6894.757293168361336722673445"),
    ("1", "bar", "psi", "14.5037737730209215154241028"),
    ("1", "MPa", "bar", "10"),
    ("1", "kg/cm2", "bar", "0.980665"),
    ("1", "kgf/cm²", "kPa", "98.0665"),
    ("1", "mH2O", "kPa", "9.80665"),
    # flow
    ("60", "l/min", "m3/h", "3.6"),
    ("3.6", "m3/h", "l/min", "60"),
    ("1", "m^3/h", "l/h", "1000"),
    ("1000", "l/h", "m³/h", "1"),
    ("1", "lpm", "l/min", "1"),
    ("10", "m3/s", "m3/h", "36000"),
    ("1", "gpm", "l/min", "3.785411784"),
    ("1", "cfm", "m3/h", "1.69901079552"),
    # power and torque
    ("1", "kW", "W", "1000"),
    ("1", "hp", "kW", "0.74569987158227022"),
    ("1", "PS", "kW", "0.73549875"),
    ("1", "CV", "W", "735.49875"),
    ("1", "TR", "W", "3516.853333333333333333333333"),
    ("20", "Nm", "N*m", "20"),
    ("1.5", "kNm", "Nm", "1500"),
    ("1", "kWh", "kJ", "3600"),
    # time
    ("250", "ms", "s", "0.25"),
    ("0.25", "s", "ms", "250"),
    ("1.5", "min", "s", "90"),
    ("90", "s", "min", "1.5"),
    ("1", "h", "min", "60"),
    ("2", "h", "s", "7200"),
    ("30", "min", "h", "0.5"),
    ("36", "s", "h", "0.01"),
    ("1", "d", "h", "24"),
    # electrical
    # kept as pint has them (docs/recipes.md)
    ("1", "inH2O", "Pa", "249.08891"),
    ("1", "inH2O_60F", "Pa", "248.84007017891"),
    ("1", "gal", "l", "3.785411784"),
    ("1", "imperial_gallon", "l", "4.54609"),
    ("1", "Btu", "J", "1055.056"),
    ("1", "Btu_it", "J", "1055.05585262"),
    ("1", "electrical_horsepower", "W", "746"),
    ("1", "kBtu/h", "Btu/h", "1000"),
    ("400", "mA", "A", "0.4"),
    ("24", "V", "mV", "24000"),
    ("1.5", "kVA", "VA", "1500"),
]


@pytest.mark.parametrize(("value", "src", "dst", "expected"), TABLE)
def test_unit_table(value: str, src: str, dst: str, expected: str) -> None:
    got = units.convert(Decimal(value), src, dst or "dimensionless")
    assert got == Decimal(expected), f"{value} {src} -> {got} {dst}, expected {expected}"
    assert str(got) == expected  # as it is printed: no trailing zeros, no exponent


# refused without a parameter's say-so, with the reason
REFUSED = [
    ("1", "rad/s", "Hz", "a cycle (rev, rpm, Hz) is not an angle"),
    ("50", "Hz", "rad/s", "'cycles_as_angles: true'"),
    ("1", "rev", "deg", "'cycles_as_angles: true'"),
    ("3000", "rpm", "deg/s", "'cycles_as_angles: true'"),
    ("90", "deg", "", "not convertible"),
    ("5", "degC", "delta_degC", "a temperature difference"),
    ("5", "delta_degC", "degC", "a temperature difference"),
    ("20", "°", "degC", "'°' is an angle"),
    ("20", "C", "degC", "'C' is the coulomb"),
    ("1", "ton", "kW", "a ton of refrigeration is TR"),
    ("10", "a", "A", "the ampere is A"),
    ("50", "F", "degF", "'F' is the farad"),
    ("1", "pu", "%", "per-unit values have no unit"),
    ("2", "barg", "bar", "unknown unit 'barg'"),
    ("2", "psig", "psi", "unknown unit 'psig'"),
    ("10", "m", "bar", "[length] vs. [mass] / [length] / [time] ** 2"),
    ("1", "Nm3/h", "m3/h", "unknown unit 'Nm3/h'"),
]


@pytest.mark.parametrize(("value", "src", "dst", "why"), REFUSED)
def test_refused_conversions_say_why(value: str, src: str, dst: str, why: str) -> None:
    with pytest.raises(ValueError) as exc:
        units.convert(Decimal(value), src, dst or "dimensionless")
    assert why in str(exc.value)


@pytest.mark.parametrize(
    ("value", "src", "dst", "expected"),
    [
        ("50", "Hz", "rad/s", "314.1592653589793238462643383"),
        ("1", "rev", "deg", "360"),
        ("90", "deg", "rev", "0.25"),
        ("180", "deg/s", "rpm", "30"),
        ("60", "rpm", "rad/s", "6.283185307179586476925286767"),
        ("3.141592653589793238462643383279502884197", "rad/s", "Hz", "0.5"),
        ("1", "turn", "rad", "6.283185307179586476925286767"),
    ],
)
def test_cycles_as_angles_when_the_parameter_says_so(value: str, src: str, dst: str, expected: str) -> None:
    assert units.convert(Decimal(value), src, dst, cycles_as_angles=True) == Decimal(expected)
    # the flag is part of the answer's key: the refusal without it is not the answer with it, nor the reverse
    with pytest.raises(ValueError):
        units.convert(Decimal(value), src, dst)


def test_field_meanings_replace_pints() -> None:
    """Spellings pint reads as something else entirely read as the field means them."""
    assert units.convert(Decimal(1), "Nm", "J") == 1  # pint: a yarn count, km/kg
    assert units.convert(Decimal(1), "cfm", "ft^3/min") == 1  # pint: centifermi
    assert units.convert(Decimal(1), "PS", "metric_horsepower") == 1  # pint: petasiemens
    assert units.convert(Decimal(1), "TR", "refrigeration_ton") == 1  # pint: teramolar gas constant
    assert units.convert(Decimal(1), "rev", "revolution") == units.convert(Decimal(1), "cycle", "turn") == 1


def _profile(tmp: Path, extra: str = "") -> Path:
    p = tmp / "vfd.yaml"
    p.write_text(
        "profile: vfd\nparameters:\n"
        "  speed_high_limit: {register: 10, type: uint16, unit: Hz, scale: 0.01, max: 400}\n"
        "  accel_time: {register: 11, type: uint16, unit: s, scale: 0.1, max: 3600}\n"
        f"{extra}"
    )
    return p


def test_plan_and_apply_3000_rpm_into_a_hz_parameter_write_50_hz(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The commissioning case: `speed_high_limit: 3000 rpm` against a profile in Hz. pint planned 314.159 Hz."""
    prof = _profile(tmp_path)
    recipe = tmp_path / "r.yaml"
    recipe.write_text(
        "recipe: r\nprofile: vfd.yaml\nparameters:\n  speed_high_limit: 3000 rpm\n  accel_time: 1.5 min\n"
    )
    code, out, err = cli(capsys, "plan", str(recipe))
    assert code == 0, err
    row = next(line for line in out.splitlines() if "speed_high_limit" in line)
    assert "50 Hz" in row and "1388" in row and "314" not in out  # 5000 = 1388h at 0.01 Hz
    with Simulators([Simulator(load_profile(str(prof)))]) as (sim,):
        code, out, err = cli(
            capsys, "apply", str(recipe), "--device", sim.url, "--yes", "--state-dir", str(tmp_path / "state")
        )
        assert code == 0, out + err
        assert sim.read("speed_high_limit") == (5000,) and sim.read("accel_time") == (900,)  # 50 Hz, 90 s
        assert count(sim.log, 16) == 1


def test_a_rad_per_second_value_into_a_hz_parameter_is_refused_before_anything_is_sent(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _profile(tmp_path)
    recipe = tmp_path / "r.yaml"
    recipe.write_text("recipe: r\nprofile: vfd.yaml\nparameters:\n  speed_high_limit: 314.16 rad/s\n")
    code, _, err = cli(capsys, "plan", str(recipe))
    assert code == 1
    assert f"{recipe}:4:21: error: speed_high_limit: 'rad/s' is not convertible to 'Hz'" in err
    assert "cycles_as_angles" in err


def test_a_profile_says_cycles_as_angles(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _profile(
        tmp_path, "  shaft_speed: {register: 12, type: uint16, unit: rad/s, scale: 0.001, cycles_as_angles: true}\n"
    )
    recipe = tmp_path / "r.yaml"
    recipe.write_text("recipe: r\nprofile: vfd.yaml\nrounding: nearest\nparameters:\n  shaft_speed: 60 rpm\n")
    code, out, err = cli(capsys, "plan", str(recipe), "--json")
    assert code == 0, err
    assert '"desired": "6.283 rad/s"' in out


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        (
            "{register: 12, type: uint16, unit: s, cycles_as_angles: true}",
            "'cycles_as_angles' is for a parameter whose unit",
        ),
        ("{register: 12, type: uint16, cycles_as_angles: true}", "this one has no unit"),
        ("{register: 12, register_type: coil, cycles_as_angles: true}", "'cycles_as_angles' does not apply to a coil"),
        ("{register: 12, type: uint16, unit: rad/s, cycles_as_angles: 1}", "cycles_as_angles"),
    ],
)
def test_cycles_as_angles_where_it_means_nothing_is_an_error(tmp_path: Path, spec: str, message: str) -> None:
    p = _profile(tmp_path, f"  x: {spec}\n")
    with pytest.raises(InputError) as exc:
        load_profile(str(p))
    assert message in str(exc.value)


def test_answers_kept_on_disk_are_keyed_by_the_field_definitions(monkeypatch: pytest.MonkeyPatch) -> None:
    """The units cache (~/.cache/deployer) keeps pint's answers between runs: answers given under other
    definitions (pint's own: 3000 rpm = 314.159 Hz) are in another file, never read as these."""
    ours = units._DiskCache().path
    monkeypatch.setattr(units, "FIELD_DEFINITIONS", units.FIELD_DEFINITIONS[1:])
    assert ours is not None and units._DiskCache().path not in (None, ours)


def test_exact_whatever_ran_before_and_whatever_is_cached(tmp_path: Path) -> None:
    """pint computes a definition's numbers (degF's 5/9, a degree's pi/180) as it reads them and keeps them, in
    memory and in its cache folder. Another program's pint (or a first use at 28 digits) must not leave deployer
    at 19.99999999999999999999999998 degC: in fresh processes, twice (the second from the caches on disk)."""
    import os
    import subprocess
    import sys

    code = (
        "import decimal, pint\n"
        "pint.UnitRegistry(non_int_type=decimal.Decimal, cache_folder=':auto:')('degF').to('degC')\n"
        "from decimal import Decimal\n"
        "from deployer.profile import units\n"
        "from deployer.state.caches import writing\n"
        "with writing():\n"
        "    units.check('degF')\n"
        "    print(units.convert(Decimal(68), 'degF', 'degC'), units.convert(Decimal(20), 'degC', 'degF'),\n"
        "          units.convert(Decimal(90), 'deg', 'rev', cycles_as_angles=True),\n"
        "          units.convert(Decimal(3000), 'rpm', 'Hz'))\n"
    )
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache"), "HOME": str(tmp_path)}
    for _ in range(2):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
        assert out.returncode == 0, out.stderr
        assert out.stdout.split() == ["20", "68", "0.25", "50"]
    assert (tmp_path / "cache" / "deployer" / "pint-60").is_dir()  # deployer's own, beside pint's
