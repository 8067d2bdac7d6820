"""deployer profiles import wb-template: wb-mqtt-serial device templates (written here, in that format)."""

from __future__ import annotations

import json
from decimal import Decimal
from pathlib import Path

import pytest

from deployer.planning.model import Target
from deployer.planning.steps import make_plan
from deployer.profile import load_profile
from deployer.recipe.loader import load_recipe
from tests.helpers import cli

# A thermostat as a template author would describe it: every key the importer reads, comments included.
TEMPLATE = """\
{
    // a thermostat with settings in holding registers and coils
    "title": "Acme TH-1",
    "device_type": "acme_th1",
    "group": "g-thermostat",
    "hw": [{"signature": "TH1", "fw": "2.0"}],
    "device": {
        "name": "Acme TH-1",
        "id": "acme-th1",
        "max_write_registers": 10,
        "max_read_registers": 0, /* 0: as many as the protocol allows */
        "response_timeout_ms": 100,
        "setup": [{"title": "unlock", "address": 9000, "value": 1}],
        "parameters": [
            {"id": "setpoint", "title": "Set point", "address": 100, "reg_type": "holding", "format": "s16",
             "scale": 0.1, "min": -20, "max": 50, "default": 21.5, "units": "deg C", "order": 1, "group": "g"},
            {"id": "hysteresis", "title": "Hysteresis", "address": "0x65", "format": "u16", "scale": 0.5,
             "offset": 1, "min": 1, "max": 10, "default": 2},
            {"id": "mode", "title": "Mode", "address": "102", "format": "u16",
             "enum": [0, 1, 2], "enum_titles": ["off", "heat", "heat, then cool"], "default": 1},
            {"id": "display_unit", "title": "Display unit", "address": 5, "reg_type": "coil",
             "enum": [0, 1], "enum_titles": ["°C", "°F"], "default": 0},
            {"id": "buzzer", "title": "Buzzer", "address": 6, "reg_type": "coil", "default": 1},
            {"id": "led_on", "title": "LED", "address": "103:0:1", "format": "u16", "default": 1},
            {"id": "led_level", "title": "LED level", "address": "103:4:3", "format": "u16", "min": 0,
             "max": 7, "fw": "2.1.0"},
            {"id": "brightness", "title": "Brightness", "address": 104, "format": "u8", "max": 200},
            {"id": "trim", "title": "Trim", "address": 105, "format": "s8", "min": -100, "max": 100},
            {"id": "total", "title": "Runtime limit", "address": 106, "format": "u32", "word_order": "little_endian"},
            {"id": "delta", "title": "Delta", "address": 108, "format": "s32"},
            {"id": "gain", "title": "Gain", "address": 110, "format": "float"},
            {"id": "big", "title": "Big counter", "address": 112, "format": "u64"},
            {"id": "offset64", "title": "Signed 64", "address": 116, "format": "s64"},
            {"id": "precise", "title": "Precise", "address": 120, "format": "double"},
            {"id": "cool_setpoint", "title": "Cooling set point", "address": 124, "format": "s16",
             "scale": 0.1, "condition": "mode==2"},
            {"id": "cool_sp_alias", "title": "Cooling set point (old firmware)", "address": 124, "format": "s16",
             "scale": 0.1, "condition": "mode!=2"},
            {"id": "relay_limit", "title": "Relay limit", "address": 130, "write_address": 131, "format": "u16"},
            {"id": "password", "title": "Password", "write_address": 140, "format": "u16"},
            {"id": "same_rw", "title": "Same address", "address": 141, "write_address": 141},
            {"id": "ui_only", "title": "Show advanced settings", "readonly": true},
            {"id": "counts", "title": "Counts", "address": 150, "format": "bcd16"}
        ],
        "channels": [
            {"name": "Temperature", "reg_type": "input", "address": 0, "format": "s16", "scale": 0.1,
             "units": "deg C", "type": "value"},
            {"name": "Relay 1", "reg_type": "coil", "address": 10, "type": "switch"},
            {"name": "Door", "reg_type": "discrete", "address": 3, "type": "switch"},
            {"name": "Set point now", "reg_type": "holding", "address": 100, "format": "s16", "scale": 0.1},
            {"name": "Serial", "reg_type": "input", "address": 20, "format": "u32", "error_value": "0xFFFFFFFF"},
            {"name": "Temperature Set Point", "reg_type": "holding", "address": 200, "format": "s16", "scale": 0.1,
             "units": "deg C", "type": "value"},
            {"name": "Defrost Command", "reg_type": "coil", "address": 11, "type": "pushbutton"},
            {"name": "Model", "reg_type": "holding", "address": 30, "readonly": true},
            {"name": "Relay 1", "reg_type": "coil", "address": 10, "type": "switch"}
        ],
        "translations": {"en": {"Acme TH-1": "Acme TH-1 thermostat"}}
    }
}
"""


def write(tmp: Path, text: str = TEMPLATE, name: str = "th1.json") -> str:
    path = tmp / name
    path.write_text(text, encoding="utf-8")
    return str(path)


def imported(tmp: Path, capsys: pytest.CaptureFixture[str], *extra: str) -> tuple[str, str]:
    src = write(tmp)
    out = str(tmp / "th1.yaml")
    code, _, err = cli(capsys, "profiles", "import", "wb-template", src, "-o", out, *extra)
    assert code == 0, err
    return out, err


def test_every_key_becomes_the_profile_parameter(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, _ = imported(tmp_path, capsys)
    prof = load_profile(out)
    assert prof.id == "acme_th1" and prof.description.startswith("Acme TH-1 thermostat (wb-mqtt-serial template")
    assert (prof.limits.max_write_registers, prof.limits.max_read_registers) == (10, 125)
    p = {q.name: q for q in prof.parameters}
    sp = p["setpoint"]
    assert (sp.address, sp.type, str(sp.scale), sp.unit, sp.min, sp.max, sp.default) == (
        100,
        "int16",
        "0.1",
        "degC",
        Decimal(-20),
        Decimal(50),
        Decimal("21.5"),
    )
    hy = p["hysteresis"]  # register = (value - offset) / scale: 2 -> raw 2
    assert (hy.address, hy.scale, hy.offset, hy.to_raw(Decimal(2))) == (0x65, Decimal("0.5"), Decimal(1), 2)
    assert p["mode"].address == 102 and p["mode"].values == (("off", 0), ("heat", 1), ("heat, then cool", 2))
    assert p["mode"].default == 1
    du = p["display_unit"]
    assert (du.register_type, du.address, du.values, du.default) == ("coil", 5, (("°C", 0), ("°F", 1)), Decimal(0))
    assert (p["buzzer"].register_type, p["buzzer"].default) == ("coil", Decimal(1))
    assert (p["led_on"].type, p["led_on"].mask, p["led_level"].mask) == ("bool", 0x0001, 0x0070)
    assert "needs firmware 2.1.0 or later" in p["led_level"].description
    assert (p["brightness"].mask, p["brightness"].max, p["trim"].mask, p["trim"].type) == (
        0xFF,
        Decimal(200),
        0xFF,
        "int16",
    )
    assert (p["total"].type, p["total"].word_order) == ("uint32", "little")
    assert [p[n].type for n in ("delta", "gain", "big", "offset64", "precise")] == [
        "int32",
        "float32",
        "uint64",
        "int64",
        "float64",
    ]
    # two ids at one register: imported once, the alias named in the description, the condition kept
    assert "cool_sp_alias" not in p
    assert p["cool_setpoint"].description == (
        "Cooling set point; applies when mode==2; also named cool_sp_alias in the template (applies when mode!=2)"
    )
    # read at 130, written at 131: read-only here, the write address kept; write-only at 140
    assert (p["relay_limit"].access, p["relay_limit"].address) == ("read-only", 130)
    assert "written at register 131 (write_address)" in p["relay_limit"].description
    assert (p["password"].access, p["password"].address) == ("write-only", 140)
    assert p["same_rw"].access == "read-write"
    assert "ui_only" not in p and "counts" not in p
    # channels: read-only values of their tables; one reading a parameter's register is that parameter
    assert (p["Temperature"].register_type, p["Temperature"].access, p["Temperature"].unit) == (
        "input",
        "read-only",
        "degC",
    )
    assert (p["Relay_1"].register_type, p["Relay_1"].access) == ("coil", "read-write")  # writable unless readonly
    tsp = p["Temperature_Set_Point"]  # a set point channel (s16, scale 0.1, not readonly): deployable
    assert (tsp.access, tsp.type, tsp.scale, tsp.unit) == ("read-write", "int16", Decimal("0.1"), "degC")
    assert (p["Defrost_Command"].action, p["Defrost_Command"].register_type) == (True, "coil")
    assert p["Model"].access == "read-only" and not p["Temperature"].writable
    assert p["led_level"].firmware == "2.1.0" and prof.firmware is not None  # fw carried over
    assert p["Door"].register_type == "discrete"
    assert "Set_point_now" not in p and "also named Set_point_now" in p["setpoint"].description
    assert "error_value 0xFFFFFFFF" in p["Serial"].description


def test_warnings_name_the_key_and_its_position(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _, err = imported(tmp_path, capsys)
    src = str(tmp_path / "th1.json")
    lines = TEMPLATE.splitlines()

    def at(needle: str, key: str) -> str:
        n = next(i for i, line in enumerate(lines) if needle in line)
        for i in range(n, len(lines)):
            quoted = '"' + key + '"'
            if quoted in lines[i]:  # the value's column: after '"key": '
                return f"{src}:{i + 1}:{lines[i].index(quoted) + len(quoted) + 3}"
        raise AssertionError(needle)

    for where, message in [
        (
            at('"cool_setpoint"', "condition"),
            "parameter 'cool_setpoint': condition 'mode==2' cannot be said in a profile: kept in the description",
        ),
        (at('"relay_limit"', "write_address"), "parameter 'relay_limit': read at 130 but written at write_address 131"),
        (
            at('"ui_only"', "readonly"),
            "parameter 'ui_only': readonly: true marks a setting of the web configurator "
            "only, with no register in the device: left out",
        ),
        (at('"counts"', "format"), "parameter 'counts': format bcd16 has no profile type"),
        (at('"setup"', "setup"), "setup: 1 writes the driver sends at start-up"),
    ]:
        assert f"warning: {where}: {message}" in err, (where, message, err)
    assert "cool_sp_alias shares its register 124 with cool_setpoint (line 35): imported once" in err
    assert "fw '2.1.0'" not in err  # a profile says it now (firmware: on the parameter)
    # a channel showing a parameter's value, or one channel listed twice, is no ambiguity: no warning
    assert "Set_point_now shares" not in err and "Relay_1 shares" not in err
    assert err.count("shares its register") + err.count("share the register") == 1
    assert "2 entries of the template left out" in err


def test_round_trip_template_profile_recipe_plan(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, _ = imported(tmp_path, capsys)
    (tmp_path / "r.yaml").write_text(
        "recipe: th\nprofile: th1.yaml\nparameters:\n  setpoint: 22.5 degC\n  hysteresis: 3\n  mode: heat, then cool\n"
        "  display_unit: °F\n  buzzer: false\n  led_on: true\n  led_level: 5\n  brightness: 200\n  trim: -3\n"
        "  total: 305419896\n  gain: 1.5\n  password: 4321\n",
        encoding="utf-8",
    )
    code, _, err = cli(capsys, "validate", out, str(tmp_path / "r.yaml"))
    assert code == 0, err
    plan = make_plan(load_recipe(str(tmp_path / "r.yaml")), Target(None, 1, out))
    assert [(w.function, w.address, w.registers) for w in plan.writes] == [
        # 100..107: s16, (3 - 1) / 0.5, enum, bits 0 and 4..6, u8 and s8 (the low byte), u32 low word first
        (16, 100, (225, 4, 2, 0x0051, 200, 0x00FD, 0x5678, 0x1234)),
        (16, 110, (0x3FC0, 0x0000)),  # float 1.5
        (16, 140, (4321,)),
        (15, 5, (1, 0)),
    ]  # display_unit °F, buzzer off: one FC15
    code, out_text, err = cli(capsys, "plan", str(tmp_path / "r.yaml"), "--json")
    assert code == 0, err
    writes = [s for s in json.loads(out_text)["steps"] if s["kind"] == "write"]
    assert writes[3] == {
        "kind": "write",
        "function": 15,
        "address": 5,
        "count": 2,
        "values": [1, 0],
        "parameters": ["display_unit", "buzzer"],
        "stage": 0,
    }


def test_object_form_and_no_channels(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = write(
        tmp_path,
        """{"device_type": "obj", "device": {"name": "o", "id": "o",
        "parameters": {"speed": {"title": "Speed", "address": 1, "format": "u16", "max": 3000, "default": 1500},
                       "dir": {"title": "Direction", "address": "2:0:1", "enum": [0, 1],
                               "enum_titles": ["forward", "reverse"]}},
        "channels": [{"name": "Speed now", "reg_type": "input", "address": 7}]}}""",
        "obj.json",
    )
    code, out, err = cli(capsys, "profiles", "import", "wb-template", src, "--no-channels", "--id", "my-obj")
    assert code == 0, err
    assert out.splitlines()[2:] == [
        'profile: "my-obj"',
        'description: "o (wb-mqtt-serial template obj)"',
        "parameters:",
        '  speed: {register: 0x0001, type: "uint16", max: 3000, default: 1500, description: "Speed"}',
        '  dir: {register: 0x0002, mask: 1, type: "bool", values: {forward: 0, reverse: 1}, description: "Direction"}',
    ]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            '{"device_type": "x", "device": {"protocol": "milur", "channels": []}}',
            "1:45: error: protocol 'milur' is not Modbus: only Modbus templates become profiles",
        ),
        (
            '{"device_type": "x", "device": {"parameters": [{"id" "a", "address": 1}]}}',
            "1:54: error: invalid JSON: expected ',' or '}'",
        ),
        ('{"device_type": "x"}', "1:1: error: not a wb-mqtt-serial device template"),
        (
            '{"device_type": "x", "device": {"parameters": [{"id": "a", "readonly": true}]}}',
            "1:32: error: the template has no parameter or channel with a Modbus register",
        ),
    ],
)
def test_bad_templates(tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, message: str) -> None:
    src = write(tmp_path, text, "bad.json")
    code, _, err = cli(capsys, "profiles", "import", "wb-template", src)
    assert code == 1 and f"{src}:{message}" in err, err
    assert "Traceback" not in err


def test_profile_problems_point_into_the_template(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = write(
        tmp_path,
        '{"device_type": "x", "device": {"parameters": [\n'
        '  {"id": "a", "address": 1, "format": "u16"},\n'
        '  {"id": "b", "address": 1, "format": "u32"}]}}',
        "ov.json",
    )
    code, out, err = cli(capsys, "profiles", "import", "wb-template", src)
    assert code == 0, err  # an overlap is handled (the second left out), not refused
    assert f"{src}:3:3: b overlaps a (line 2) in register 1: left out" in err
    assert "  a: {register: 0x0001" in out and "  b:" not in out


def test_hostile_input_is_bounded(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = cli(capsys, "profiles", "import", "wb-template", "/dev/zero")
    assert code == 1 and "not a regular file" in err
    many = ",".join(f'{{"name": "c{i}", "reg_type": "input", "address": {i % 60000}}}' for i in range(20001))
    src = write(tmp_path, f'{{"device_type": "x", "device": {{"channels": [{many}]}}}}', "many.json")
    code, _, err = cli(capsys, "profiles", "import", "wb-template", src)
    assert code == 1 and "20001 parameters and channels; at most 20000" in err


def test_the_repository_ships_no_wb_mqtt_serial_template() -> None:
    """Their MIT-WB licence allows use on Wiren Board controllers only (docs/importers.md): deployer ships none,
    nor a profile made from one; the tests write their own."""
    import os
    import subprocess

    root = Path(__file__).resolve().parent.parent
    try:
        listed = subprocess.run(["git", "ls-files"], cwd=root, capture_output=True, text=True, timeout=60, check=True)
        files = [root / f for f in listed.stdout.splitlines()]
    except (OSError, subprocess.SubprocessError):  # a source tree without git: every file but the environments'
        files = [  # and the bytecode (make test-windows compiles the tests: this one's holds the text it looks for)
            Path(d) / f
            for d, dirs, names in os.walk(root)
            if not any(
                part.startswith(".") or part in ("build", "node_modules", "__pycache__")
                for part in Path(d).parts[len(root.parts) :]
            )
            for f in names
        ]
    assert len(files) > 100
    found = []
    for f in files:
        if not f.is_file():
            continue
        text = f.read_text(encoding="utf-8", errors="replace")
        rel = f.relative_to(root).as_posix()
        if f.name.endswith((".json", ".jinja", ".json5")) and '"device_type"' in text:
            found.append(f"{rel}: a device template")
        if "Contactless Devices" in text and rel not in ("docs/importers.md", "tests/test_wb_template.py"):
            found.append(f"{rel}: Wiren Board's licence text")  # a copied template or profile brings its notice
        if f.suffix == ".yaml" and "wb-mqtt-serial template" in text:
            found.append(f"{rel}: a profile made from a template")
    assert found == []
    assert "MIT-WB" in (root / "docs" / "importers.md").read_text(encoding="utf-8")
