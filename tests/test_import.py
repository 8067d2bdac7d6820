"""profiles import: vendor CSV register lists and SunSpec models become profiles that validate and plan."""

from __future__ import annotations

import asyncio
import csv
import random
from pathlib import Path

import pytest

from deployer.execute.device import apply_device
from deployer.execute.session import ApplyOptions
from deployer.planning.model import Target
from deployer.planning.steps import make_plan
from deployer.profile import load_profile
from deployer.recipe.loader import load_recipe
from deployer.testing.simulator import SimulatorThread
from deployer.transport.clients import parse_url
from tests.helpers import cli

pytestmark = pytest.mark.timeout(60)


# a vendor's sheet: its own headers ("Reg No" needs --column), types, R/W, "0=..;1=.." enumerations
HEADER = [
    "Parameter",
    "Reg No",
    "Data Type",
    "Unit",
    "Resolution",
    "Min",
    "Max",
    "R/W",
    "Description",
    "Values",
    "Bits",
    "Count",
]


def vendor_rows(n: int = 240, seed: int = 7) -> list[list[str]]:
    rnd = random.Random(seed)
    rows: list[list[str]] = []
    address = 0x1000
    kinds = ["U16", "S16", "U32", "S32", "FLOAT", "STRING", "BITS", "ENUM"]
    while len(rows) < n:
        kind = rnd.choice(kinds)
        i = len(rows)
        if kind == "BITS":  # three fields of one status/control word
            rows.append([f"Ctrl {i} enable", str(address), "BOOL", "", "", "", "", "RW", "enable", "", "0", ""])
            rows.append(
                [f"Ctrl {i} mode", str(address), "U16", "", "", "", "", "RW", "mode", "0=off;1=auto;2=hand", "1..2", ""]
            )
            rows.append([f"Ctrl {i} step", str(address), "U16", "mm", "0.5", "0", "7", "RW", "", "", "12..15", ""])
            address += 1
        elif kind == "STRING":
            rows.append([f"Tag {i}", str(address), "STRING", "", "", "", "", "RW", "tag name", "", "", "4"])
            address += 4
        elif kind == "ENUM":
            rows.append([f"Stop mode {i}", hex(address), "U16", "", "", "", "", "RW", "", "0=ramp;1=coast", "", ""])
            address += 1
        else:
            size = {"U16": 1, "S16": 1, "U32": 2, "S32": 2, "FLOAT": 2}[kind]
            unit, res = rnd.choice([("s", "0.01"), ("Hz", "0.1"), ("rpm", "1"), ("%", "0.1"), ("", "")])
            lo = "-100" if kind.startswith("S") else "0"
            rows.append(
                [
                    f"P{i:03d} {unit or 'count'}",
                    f"{address:04X}h",
                    kind,
                    unit,
                    res,
                    lo,
                    "100",
                    rnd.choice(["RW", "R", "RW"]),
                    f"parameter {i}",
                    "",
                    "",
                    "",
                ]
            )
            address += size
        if rnd.random() < 0.1:
            address += 3  # gaps between blocks, as in real maps
    return rows


def write_csv(path: Path, rows: list[list[str]], delimiter: str = ",") -> None:
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f, delimiter=delimiter)
        w.writerow(HEADER)
        w.writerows(rows)


def test_csv_of_240_rows_imports_validates_and_plans(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rows = vendor_rows()
    assert len(rows) >= 200
    src = tmp_path / "vendor.csv"
    write_csv(src, rows, ";")
    out = tmp_path / "vendor.yaml"
    code, _, err = cli(
        capsys,
        "profiles",
        "import",
        "csv",
        str(src),
        "--id",
        "vendor-drive",
        "-o",
        str(out),
        "--column",
        "address=Reg No",
    )
    assert code == 0, err
    assert f"profile vendor-drive with {len(rows)} parameters" in err
    code, _, err = cli(capsys, "validate", str(out))
    assert code == 0, err
    prof = load_profile(out)
    assert len(prof.parameters) == len(rows)
    # every row is where the sheet says, with its type
    for row in rows:
        p = prof.parameter(row[0].replace(" ", "_").replace("%", "").strip("_"))
        text = row[1]
        assert p.address == (int(text[:-1], 16) if text.endswith("h") else int(text, 0))
        assert (
            p.type
            == {
                "U16": "uint16",
                "S16": "int16",
                "U32": "uint32",
                "S32": "int32",
                "FLOAT": "float32",
                "STRING": "string",
                "BOOL": "bool",
            }[row[2]]
        )
        if row[10]:
            assert p.mask
    # a recipe naming some of them plans to those addresses
    writable = [p for p in prof.parameters if p.writable and not p.is_string and p.type != "bool" and not p.values]
    chosen = writable[::7][:25]
    body = "".join(f"  {p.name}: {p.min if p.min is not None else 1}{' ' + p.unit if p.unit else ''}\n" for p in chosen)
    bits = next(p for p in prof.parameters if p.name.endswith("_mode") and p.mask)
    body += f"  {bits.name}: hand\n"
    (tmp_path / "r.yaml").write_text(f"recipe: r\nprofile: vendor.yaml\nparameters:\n{body}")
    rec = load_recipe(tmp_path / "r.yaml")
    plan = make_plan(rec, Target(None, 1, str(out)))
    planned = {p.name: p.address for p in plan.parameters}
    assert planned == {p.name: p.address for p in [*chosen, bits]}
    covered = {a for w in plan.writes for a in range(w.address, w.address + w.count)}
    assert all(p.address in covered for p in [*chosen, bits])
    assert {(w.address, w.registers) for w in plan.writes if w.address == bits.address} == {(bits.address, (0x0004,))}


def test_csv_errors_point_at_cells(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "bad.csv"
    src.write_text(
        "Name,Address,Type,Access,Bits\n"
        "speed,0x10,U16,RW,\n"
        "accel,zz,U16,RW,\n"
        "decel,0x11,BLOB,RW,\n"
        "speed,0x12,U16,RW,\n"
        "mode,0x13,U16,maybe,\n"
        '"run, forward",0x14,BOOL,R,\n'
        "wide,0x10,U32,RW,\n"
    )
    code, _, err = cli(capsys, "profiles", "import", "csv", str(src), "--id", "x")
    assert code == 1
    assert f"{src}:3:7: error: not a register address: 'zz'" in err
    assert f"{src}:4:12: error: unknown type 'BLOB'" in err
    assert f"{src}:5:1: error: 'speed' is already defined on line 2" in err
    assert f"{src}:6:15: error: access 'maybe' is not R, W or RW" in err
    assert f"{src}:7:21: error: run_forward: a bool needs the bit number in the 'bits' column" in err
    # problems only the whole profile shows (an overlap) still point at the row
    src.write_text("Name,Address,Type\n# a comment row\nspeed,0x10,U16\nwide,0x10,U32\n")
    code, _, err = cli(capsys, "profiles", "import", "csv", str(src), "--id", "x")
    assert code == 1
    assert f"{src}:4:1: error: wide (registers 0x0010-0x0011) overlaps speed (registers 0x0010-0x0010, line 3)" in err
    code, _, err = cli(capsys, "profiles", "import", "csv", str(src), "--id", "x", "--column", "adress=Reg")
    assert code == 1 and "--column adress=...: unknown column" in err


def test_sunspec_basic_settings_model_plans_to_its_addresses(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("sunspec2", reason="pysunspec2 is the optional 'sunspec' extra")
    out = tmp_path / "inv.yaml"
    # model 121 after the common model (1, 66 registers + ID/L at 40002) and model 103 (50 + 2): ID at 40122
    code, _, err = cli(
        capsys,
        "profiles",
        "import",
        "sunspec",
        "121",
        "--at",
        "40122",
        "--sf",
        "WMax_SF=1",
        "--sf",
        "VRef_SF=-1",
        "--sf",
        "VMinMax_SF=-1",
        "--id",
        "inverter-settings",
        "-o",
        str(out),
    )
    assert code == 0, err
    assert "warning: VRefOfs: scale factor VRefOfs_SF unknown: imported raw, without its unit" in err
    prof = load_profile(out)
    # a point whose scale factor is unknown carries no unit: '10 V' could not be converted rightly
    assert prof.parameter("VRefOfs").unit is None and prof.parameter("VRefOfs").scale == 1
    assert "raw: the value in V is raw x 10^VRefOfs_SF" in prof.parameter("VRefOfs").description
    # SunSpec model 121: ID, L, then WMax, VRef, VRefOfs, VMax, VMin, VAMax, VArMaxQ1-4, WGra, PFMinQ1-4,
    # VArAct, ClcTotVA, MaxRmpRte, ECPNomHz, ConnPh, then the scale factors; L = 30
    offsets = {
        "ID": 0,
        "L": 1,
        "WMax": 2,
        "VRef": 3,
        "VMax": 5,
        "VMin": 6,
        "VArAct": 17,
        "ConnPh": 21,
        "WMax_SF": 22,
        "ECPNomHz_SF": 31,
    }
    assert {n: prof.parameter(n).address - 40122 for n in offsets} == offsets
    assert prof.parameter("L").default == 30 and prof.identity[0].raw == 121
    assert prof.parameter("WMax").scale == 10 and prof.parameter("WMax").unit == "W"
    assert prof.parameter("WMax_SF").access == "read-only"
    (tmp_path / "r.yaml").write_text(
        "recipe: grid\nprofile: inv.yaml\nparameters:\n  WMax: 5 kW\n  VRef: 230 V\n  VMax: 253 V\n  ConnPh: B\n"
    )
    rec = load_recipe(tmp_path / "r.yaml")
    plan = make_plan(rec, Target(None, 1, str(out)))
    assert [(w.address, w.registers) for w in plan.writes] == [
        (40124, (500, 2300)),  # WMax 5000 W at 10 W, VRef 230 V at 0.1 V
        (40127, (2530,)),  # VMax
        (40143, (2,)),
    ]  # ConnPh B
    # and against a simulated device of that model (its identity: model ID 121 at 40122)
    with SimulatorThread(prof) as sim:
        res = asyncio.run(
            apply_device(rec, parse_url(sim.url), 1, options=ApplyOptions(state_dir=str(tmp_path / ".d")))
        )
        assert res.status == "ok", res.to_json()
        assert sim.read("WMax") == (500,)


def test_sunspec_unknown_model(capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("sunspec2")
    code, _, err = cli(capsys, "profiles", "import", "sunspec", "99999")
    assert code == 1 and "no SunSpec model 99999" in err


def test_csv_round_trip_profile_csv_profile(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """import -> export -> import gives the same parameters (the 240-row sheet, and a profile with layouts)."""
    import dataclasses

    def same(p: object) -> dict[str, object]:
        return {k: v for k, v in dataclasses.asdict(p).items() if k not in ("line", "col")}  # type: ignore[call-overload]

    src = tmp_path / "vendor.csv"
    write_csv(src, vendor_rows())
    first = tmp_path / "first.yaml"
    assert (
        cli(capsys, "profiles", "import", "csv", str(src), "--id", "v", "-o", str(first), "--column", "address=Reg No")[
            0
        ]
        == 0
    )
    exported = tmp_path / "exported.csv"
    assert cli(capsys, "profiles", "export", "csv", str(first), "-o", str(exported))[0] == 0
    second = tmp_path / "second.yaml"
    assert cli(capsys, "profiles", "import", "csv", str(exported), "--id", "v", "-o", str(second))[0] == 0
    a, b = load_profile(first), load_profile(second)
    assert len(a.parameters) == len(b.parameters) >= 200
    assert [same(p) for p in a.parameters] == [same(p) for p in b.parameters]
    # layouts, strings with a byte swap, defaults and labels survive too
    prof = tmp_path / "dev.yaml"
    prof.write_text(
        "profile: dev\nbyte_order: CDAB\nparameters:\n"
        "  f: {register: 0, type: float32, default: 1.5}\n"
        "  q: {register: 2, type: uint64, byte_order: HGFEDCBA, min: 0, max: 1000000}\n"
        "  s: {register: 6, type: string, count: 3, swap: byte, padding: space, default: ab}\n"
        "  e: {register: 9, type: int16, bits: 4..7, values: {low: -2, high: 3}, default: high}\n"
    )
    code, text, _ = cli(capsys, "profiles", "export", "csv", str(prof))
    assert code == 0 and "s,6,string,,,,,read-write,,,,3,byte,ab" in text
    (tmp_path / "dev.csv").write_text(text)
    assert (
        cli(
            capsys,
            "profiles",
            "import",
            "csv",
            str(tmp_path / "dev.csv"),
            "--id",
            "dev",
            "-o",
            str(tmp_path / "back.yaml"),
        )[0]
        == 0
    )
    assert [same(p) for p in load_profile(prof).parameters] == [
        same(p) for p in load_profile(tmp_path / "back.yaml").parameters
    ]


def test_csv_default_byte_order(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "m.csv"
    src.write_text("name\taddress\ttype\tbyte order\npower\t0\tFLOAT\t\ncounter\t2\tU32\tABCD\n")
    out = tmp_path / "m.yaml"
    code, _, err = cli(
        capsys, "profiles", "import", "csv", str(src), "--id", "m", "--byte-order", "CDAB", "-o", str(out)
    )
    assert code == 0, err
    prof = load_profile(out)
    assert prof.parameter("power").layout == "CDAB" and prof.parameter("counter").layout == "ABCD"
    code, _, err = cli(capsys, "profiles", "import", "csv", str(src), "--id", "m", "--byte-order", "ACBD")
    assert code == 1 and "--byte-order ACBD: expected one of ABCD" in err


def test_xlsx_with_a_title_block(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    openpyxl = pytest.importorskip("openpyxl", reason="openpyxl is the optional 'xlsx' extra")
    book = openpyxl.Workbook()
    ws = book.active
    ws.title = "Registers"
    ws.append(["ACME AD-200 drive: Modbus register map"])  # a title block above the header
    ws.append([])
    ws.append(HEADER)
    rows = vendor_rows(60)
    for row in rows:
        ws.append([int(c) if c.isdigit() else c for c in row])  # addresses as numbers, as Excel keeps them
    path = tmp_path / "map.xlsx"
    book.save(path)
    out = tmp_path / "map.yaml"
    code, _, err = cli(
        capsys, "profiles", "import", "xlsx", str(path), "--id", "acme", "--column", "address=Reg No", "-o", str(out)
    )
    assert code == 0, err
    prof = load_profile(out)
    assert len(prof.parameters) == len(rows)
    ws.cell(row=5, column=3, value="U24")  # the second register row's type
    book.save(path)
    code, _, err = cli(capsys, "profiles", "import", "xlsx", str(path), "--id", "acme", "--column", "address=Reg No")
    assert code == 1 and f"{path}[Registers]:5:3: error: unknown type 'U24'" in err
    code, _, err = cli(capsys, "profiles", "import", "xlsx", str(path), "--id", "acme", "--sheet", "Nope")
    assert code == 1 and "no sheet 'Nope' (sheets: Registers)" in err


def test_sunspec_first_model_carries_the_suns_marker(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("sunspec2")
    out = tmp_path / "common.yaml"
    code, _, err = cli(capsys, "profiles", "import", "sunspec", "common", "-o", str(out))
    assert code == 0, err
    prof = load_profile(out)
    assert prof.parameter("SunS").address == 40000 and prof.parameter("ID").address == 40002
    assert [(c.address, c.raw) for c in prof.identity] == [(40000, 0x5375), (40001, 0x6E53), (40002, 1)]
    assert prof.parameter("Mn").type == "string" and prof.parameter("Mn").count == 16
    with SimulatorThread(prof) as sim:  # the simulated device passes its own identity check
        from deployer.execute.read import read_current

        values = asyncio.run(read_current(prof, ["Mn", "DA"], parse_url(sim.url), 1))
    assert set(values) == {"Mn", "DA"}


def test_sunspec_repeating_groups_and_counts(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("sunspec2")
    out = tmp_path / "vv.yaml"
    code, _, err = cli(capsys, "profiles", "import", "sunspec", "126", "--at", "40200", "-o", str(out))
    assert code == 0 and "--count curve=N" in err  # the device says how many curves it has
    code, _, err = cli(
        capsys, "profiles", "import", "sunspec", "126", "--at", "40200", "--count", "curve=4", "-o", str(out), "--force"
    )
    assert code == 0, err
    prof = load_profile(out)
    # model 126 (volt-var): 10 registers of header, then 4 curves of 54 registers each; L = 226
    assert prof.parameter("L").default == 226
    assert prof.parameter("curve[0].ActPt").address == 40200 + 12
    assert prof.parameter("curve[3].ActPt").address == 40200 + 12 + 3 * 54
    code, _, err = cli(capsys, "profiles", "import", "sunspec", "126", "--count", "curve=x")
    assert code == 1 and "--count" in err


def test_import_usage_errors_are_messages(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "m.csv"
    src.write_text("name,address,type\na,1,U16\n")
    code, _, err = cli(capsys, "profiles", "import", "csv", str(src), "--id", "bad id")
    assert code == 1 and "--id 'bad id': letters, digits" in err
    code, _, err = cli(capsys, "profiles", "import", "csv", str(tmp_path / "none.csv"), "--id", "x")
    assert code == 1 and "none.csv:0:0: error: no such file" in err
    pytest.importorskip("openpyxl")
    code, _, err = cli(capsys, "profiles", "import", "xlsx", str(src), "--id", "x")
    assert code == 1 and f"{src}:1:1: error: not an Excel workbook" in err and "Traceback" not in err
    pytest.importorskip("sunspec2")
    code, _, err = cli(capsys, "profiles", "import", "sunspec", "121", "--at", "65530")
    assert code == 1 and "would end past register 65535" in err
    code, _, err = cli(capsys, "profiles", "import", "sunspec", "121", "--at", "zz")
    assert code == 1 and "--at zz: not a register address" in err


def test_csv_numbers_as_manuals_write_them(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "m.csv"
    src.write_text(
        "name;address;type;scale;min;max\nmask;0x10;U16;;0;0xFFFF\nlimit;11h;U16;0,01;0;FFh\n"
        "gain;0x12;FLOAT;;-1e3;1.5E3\n"
    )
    out = tmp_path / "m.yaml"
    assert cli(capsys, "profiles", "import", "csv", str(src), "--id", "m", "-o", str(out))[0] == 0
    prof = load_profile(out)
    assert prof.parameter("mask").max == 0xFFFF and prof.parameter("limit").max == 0xFF
    assert str(prof.parameter("limit").scale) == "0.01" and prof.parameter("gain").min == -1000


def test_sunspec_curves_with_points(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Model 705 (DER volt-var): curves (NCrv) of points (NPt), both counts reported by the device."""
    pytest.importorskip("sunspec2")
    out = tmp_path / "vv.yaml"
    code, _, err = cli(
        capsys,
        "profiles",
        "import",
        "sunspec",
        "705",
        "--at",
        "40300",
        "--count",
        "Crv=3",
        "--count",
        "Pt=4",
        "-o",
        str(out),
    )
    assert code == 0, err
    prof = load_profile(out)
    # 15 registers of header (ID and L included), then curves of 10 registers + 4 points x (V, Var)
    assert prof.parameter("L").default == 13 + 3 * 18
    assert prof.parameter("Crv[0].ActPt").address == 40300 + 15
    assert prof.parameter("Crv[1].Pt2_V").address == 40300 + 15 + 18 + 10 + 2 * 2
    assert prof.parameter("Crv[2].Pt3_Var").address == 40300 + 15 + 2 * 18 + 10 + 3 * 2 + 1
    (tmp_path / "r.yaml").write_text(
        "recipe: vv\nprofile: vv.yaml\nparameters:\n"
        "  Crv[1]: {ActPt: 2, Pt0_V: 920, Pt0_Var: 300, Pt1_V: 1080, Pt1_Var: -300}\n"
    )
    plan = make_plan(load_recipe(tmp_path / "r.yaml"), Target(None, 1, str(out)))
    assert [(w.address, w.count) for w in plan.writes] == [(40300 + 15 + 18, 1), (40300 + 15 + 18 + 10, 4)]


def test_sunspec_scale_factors_read_from_the_device(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("sunspec2")
    from deployer.profile.emit import check
    from deployer.profile.importers.sunspec import read_model

    _, device_profile = check(read_model("121", at=40122)[0], str(tmp_path / "dev.yaml"))
    sf = {n: device_profile.parameter(n).address for n in ("WMax_SF", "VRef_SF", "VMinMax_SF")}
    init = {sf["WMax_SF"]: 1, sf["VRef_SF"]: 0xFFFF, sf["VMinMax_SF"]: 0xFFFF}  # 1, -1, -1 as int16
    out = tmp_path / "inv.yaml"
    with SimulatorThread(device_profile, init=init) as sim:
        code, _, err = cli(
            capsys,
            "profiles",
            "import",
            "sunspec",
            "121",
            "--at",
            "40122",
            "--device",
            sim.url,
            "--sf",
            "VMinMax_SF=-2",
            "-o",
            str(out),
        )
        assert code == 0, err
        assert "scale factors from" in err and "WMax_SF=1" in err and "VRef_SF=-1" in err
        code, _, err = cli(capsys, "profiles", "import", "sunspec", "121", "--at", "40002", "--device", sim.url)
        assert code == 3 and "exception 02 (illegal data address)" in err  # no model 121 there
    prof = load_profile(out)
    assert prof.parameter("WMax").scale == 10 and str(prof.parameter("VRef").scale) == "0.1"
    assert str(prof.parameter("VMax").scale) == "0.01"  # --sf wins over the device


def test_nul_after_a_syntax_error_is_a_message(tmp_path: Path) -> None:
    """Found by fuzzing the SunSpec import: libyaml stops at the syntax error, the pure-Python re-parse
    (for its wording) refuses the whole text because of a NUL further on; that must stay a message."""
    from deployer.cli.files import validate_file
    from deployer.errors import InputError

    bad = tmp_path / "r.yaml"
    head = "recipe: r\nprofile: omron-m1\nparameters:\n  F07: 10 s\n F08: 8 s\n"  # line 5: a bad indent
    bad.write_text(head + "# " + "x" * 20000 + "\ne: \x00\n")
    with pytest.raises(InputError) as e:
        validate_file(str(bad))
    assert [(d.line, d.col) for d in e.value.diagnostics] == [(5, 2)]
    assert e.value.diagnostics[0].message.startswith("invalid YAML:")
