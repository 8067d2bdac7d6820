"""The importers under hostile and odd input (issue #24) and vendor cells as they are (issue #22):
bounded time and memory, an error at the cell (or model point) of the cause, never a traceback,
never a silently wrong profile."""

from __future__ import annotations

import csv
import os
import sys
from decimal import Decimal
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from benchmarks.child import measured
from deployer.errors import InputError
from deployer.planning.model import Target
from deployer.planning.steps import make_plan
from deployer.profile import load_profile
from deployer.profile.emit import Draft, Origin, check
from deployer.recipe.loader import load_recipe
from tests import hostile_imports
from tests.helpers import cli, without_coverage

pytestmark = pytest.mark.timeout(300)
ROOT = Path(__file__).resolve().parent.parent
CORPUS = ROOT / "tests" / "bad" / "import"


def _expected() -> list[tuple[str, str, str]]:
    out = []
    for line in (CORPUS / "expected.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            f, where, fragment = (part.strip() for part in line.split(" | ", 2))
            out.append((f, where, fragment))
    return out


EXPECTED = _expected()
COMMAND = {".csv": "csv", ".xlsx": "xlsx", ".json": "sunspec"}


def test_corpus_is_complete() -> None:
    files = {p.name for p in CORPUS.iterdir() if p.name != "expected.txt"}
    assert files == {f for f, _, _ in EXPECTED}


@pytest.mark.parametrize(("name", "where", "fragment"), EXPECTED, ids=[f"{f}@{w}" for f, w, _ in EXPECTED])
def test_hostile_file(name: str, where: str, fragment: str, capsys: pytest.CaptureFixture[str]) -> None:
    """Each file ends in exit 1 with its error at the exact position, short lines, no traceback, and the
    importer's own outcome (no device is involved in an import)."""
    pytest.importorskip("openpyxl")
    pytest.importorskip("sunspec2")
    path = CORPUS / name
    kind = COMMAND[path.suffix]
    args = ["profiles", "import", kind, str(path)] + (["--id", "x"] if kind != "sunspec" else [])
    code, out, err = cli(capsys, *args)
    assert code == 1 and out == ""
    assert f"{path}{where if where.startswith('[') else ':' + where}: error: {fragment}" in err, err
    assert "Traceback" not in err and "no profile was written" in err and "sent to any device" not in err
    assert max(len(line) for line in err.splitlines()) < 400  # no cell echoed whole


@pytest.mark.parametrize("worst", hostile_imports.WORST, ids=[w.name for w in hostile_imports.WORST])
def test_worst_inputs_are_bounded(worst: hostile_imports.Worst, tmp_path: Path) -> None:
    """The issue's worst inputs (smaller ones of the same kind where making them is slow; the benchmark
    bench_import runs them at full size), each in its own process limited to 2 GiB: the expected ending,
    and a peak memory measured, not assumed."""
    pytest.importorskip("openpyxl")
    pytest.importorskip("sunspec2")
    f = tmp_path / worst.file if worst.file else None
    if f is not None:
        (worst.quick or worst.make)(f)
    args = [a.replace("{f}", str(f)) for a in worst.args]
    # without coverage's tracer (make test's COVERAGE_PROCESS_CONFIG): the memory and the bounds are the importer's,
    # and traced, these inputs took 2.5 times the CPU (27.6 s against 11.0 s), a tenth of make test's time
    env = without_coverage()
    _, _, peak_kb, code, err = measured(
        [sys.executable, "-m", "deployer", "profiles", "import", *args], cwd=str(ROOT), max_bytes=2 << 30, env=env
    )
    assert code == worst.code and worst.expect in err, err[-2000:]
    assert "Traceback" not in err
    assert peak_kb / 1024 < 400, f"{worst.name}: {peak_kb / 1024:.0f} MB"


# ---------------------------------------------------------------------------------- vendor cells


def write_csv(path: Path, rows: list[list[str]], delimiter: str = ",") -> Path:
    with open(path, "w", newline="", encoding="utf-8") as f:
        csv.writer(f, delimiter=delimiter).writerows(rows)
    return path


def test_vendor_cells_as_they_are(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A vendor's sheet: a resolution with its unit, ranges in three spellings, limits with units, and
    columns the importer does not know: every one of those named in a warning at its header cell."""
    src = write_csv(
        tmp_path / "v.csv",
        [
            ["Parameter", "Address", "Type", "Resolution", "Setting range", "Unit", "Remark", "Factory note"],
            ["F002", "2", "U16", "0.01 s", "0 to 400.00", "", "accel", "x"],
            ["F003", "3", "U16", "0.1", "0-400.00", "s", "", ""],
            ["F004", "4", "U16", "", "0...100 %", "", "", ""],
            ["F005", "5", "U16", "10 ms", "0 s to 6 s", "s", "", ""],  # converted into the unit column's unit
            ["F006", "6", "S16", "0.1", "-10 - -5", "Hz", "", ""],
        ],
    )
    out = tmp_path / "v.yaml"
    code, _, err = cli(capsys, "profiles", "import", "csv", str(src), "--id", "v", "-o", str(out))
    assert code == 0, err
    assert f"{src}:1:54: warning: column 'Remark' is not used: not a column this importer knows" in err
    assert f"{src}:1:61: warning: column 'Factory note' is not used" in err
    prof = load_profile(out)
    f2, f3, f4, f5, f6 = (prof.parameter(n) for n in ("F002", "F003", "F004", "F005", "F006"))
    assert (f2.unit, f2.scale, f2.min, f2.max) == ("s", Decimal("0.01"), Decimal(0), Decimal(400))
    assert (f3.unit, f3.scale, f3.min, f3.max) == ("s", Decimal("0.1"), Decimal(0), Decimal(400))
    assert (f4.unit, f4.min, f4.max) == ("%", Decimal(0), Decimal(100))
    assert (f5.unit, f5.scale, f5.min, f5.max) == ("s", Decimal("0.01"), Decimal(0), Decimal(6))
    assert (f6.min, f6.max) == (Decimal(-10), Decimal(-5))
    # the sheet's 30 s go out as 3000 (0.01 s) - with the resolution dropped they would be 30
    (tmp_path / "r.yaml").write_text("recipe: r\nprofile: v.yaml\nparameters:\n  F002: 30 s\n  F005: 2500 ms\n")
    plan = make_plan(load_recipe(tmp_path / "r.yaml"), Target(None, 1, str(out)))
    assert [(w.address, w.registers) for w in plan.writes] == [(2, (3000,)), (5, (250,))]


def test_decimal_marks(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """'3,000' is refused at its cell unless --decimal-comma or --decimal-point says which it is; unambiguous
    cells are read in the default mode (0,5 and 1.000,5 with a comma, 1,234.5 and 1,000,000 with a point)."""
    rows = [
        ["name", "address", "type", "scale", "min", "max"],
        ["a", "1", "FLOAT", "", "0,5", "1.000,5"],
        ["b", "3", "FLOAT", "", "1,234.5", "1,000,000"],
        ["c", "5", "U16", "", "0", "3,000"],
    ]
    src = write_csv(tmp_path / "d.csv", rows, ";")
    code, _, err = cli(capsys, "profiles", "import", "csv", str(src), "--id", "d")
    assert code == 1 and f"{src}:4:12: error: max: '3,000' is ambiguous" in err
    out = tmp_path / "d.yaml"
    code, _, err = cli(capsys, "profiles", "import", "csv", str(src), "--id", "d", "--decimal-point", "-o", str(out))
    assert code == 1 and "'0,5' is not a number (',' separates groups of three digits)" in err
    src = write_csv(tmp_path / "d.csv", [rows[0], rows[3]], ";")
    assert (
        cli(capsys, "profiles", "import", "csv", str(src), "--id", "d", "--decimal-point", "-o", str(out), "--force")[0]
        == 0
    )
    assert load_profile(out).parameter("c").max == 3000
    assert (
        cli(capsys, "profiles", "import", "csv", str(src), "--id", "d", "--decimal-comma", "-o", str(out), "--force")[0]
        == 0
    )
    assert load_profile(out).parameter("c").max == 3
    src = write_csv(tmp_path / "d.csv", rows[:3], ";")
    assert cli(capsys, "profiles", "import", "csv", str(src), "--id", "d", "-o", str(out), "--force")[0] == 0
    prof = load_profile(out)
    assert (prof.parameter("a").min, prof.parameter("a").max) == (Decimal("0.5"), Decimal("1000.5"))
    assert (prof.parameter("b").min, prof.parameter("b").max) == (Decimal("1234.5"), Decimal(1000000))


def test_xlsx_formula_with_a_saved_value_is_read(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A formula whose value the spreadsheet program saved is that value; without one, see the corpus."""
    pytest.importorskip("openpyxl")
    src = tmp_path / "f.xlsx"
    hostile_imports.write_xlsx(
        src,
        hostile_imports._sheet(
            [
                hostile_imports._row(
                    1, [("A1", "name"), ("B1", "address"), ("C1", "type"), ("D1", "unit"), ("E1", "scale")]
                ),
                b'<row r="2"><c r="A2" t="inlineStr"><is><t>F07</t></is></c><c r="B2"><v>4354</v></c>'
                b'<c r="C2" t="inlineStr"><is><t>U16</t></is></c><c r="D2" t="inlineStr"><is><t>s</t></is></c>'
                b'<c r="E2"><f>1/10</f><v>0.1</v></c></row>',
            ]
        ),
    )
    out = tmp_path / "f.yaml"
    code, _, err = cli(capsys, "profiles", "import", "xlsx", str(src), "--id", "f", "-o", str(out))
    assert code == 0, err
    assert load_profile(out).parameter("F07").scale == Decimal("0.1")


# -------------------------------------------------------------------------------------- the writer

NAMES = st.text(st.characters(codec="utf-8", exclude_categories=["Cs"]), min_size=1, max_size=40)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=NAMES, description=NAMES, label=NAMES)
def test_the_writer_never_adds_structure(name: str, description: str, label: str) -> None:
    """Whatever text a source holds, the written profile reads back as exactly the data imported, or the
    import is refused at the origin: never a parameter the source did not have."""
    spec = {"register": 1, "type": "uint16", "description": description, "values": {label: 1}}
    draft = Draft({"profile": "p", "description": description}, [(name, spec, Origin("src.csv", 2, 3))], [])
    try:
        _, prof = check(draft, "<out>")
    except InputError as e:
        assert all((d.path, d.line, d.col) == ("src.csv", 2, 3) for d in e.diagnostics), e.diagnostics
        return
    assert prof.names() == [name]
    p = prof.parameter(name)
    assert (p.address, p.description, dict(p.values)) == (1, description, {label: 1})


def test_names_longer_than_yaml_keys_are_refused_at_their_row(tmp_path: Path) -> None:
    spec = {"register": 1, "type": "uint16"}
    draft = Draft({"profile": "p"}, [("n" * 1500, spec, Origin("src.csv", 7, 1))], [])
    with pytest.raises(InputError) as e:
        check(draft, "<out>")
    (d,) = e.value.diagnostics
    assert (d.line, d.col) == (7, 1) and "parameter name of 1500 characters: at most 256" in d.message


# ------------------------------------------------------------------------------------------ export


def test_export_escapes_formulas_and_reads_back(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Cells a spreadsheet program would run get a leading apostrophe; import removes it again."""
    (tmp_path / "p.yaml").write_text(
        "profile: p\nparameters:\n"
        '  a: {register: 1, type: uint16, description: "=HYPERLINK(\\"http://x\\",\\"y\\")"}\n'
        '  b: {register: 2, type: int16, min: -10, max: 10, description: "-2+3"}\n'
        '  c: {register: 3, type: uint16, description: "@SUM(1)"}\n'
        '  d: {register: 4, type: uint16, description: "+1"}\n'
    )
    code, text, err = cli(capsys, "profiles", "export", "csv", str(tmp_path / "p.yaml"))
    assert code == 0
    rows = list(csv.reader(text.splitlines()))
    assert [r[8] for r in rows[1:]] == ['\'=HYPERLINK("http://x","y")', "'-2+3", "'@SUM(1)", "'+1"]
    assert rows[2][5:7] == ["-10", "10"]  # numbers stay numbers
    (tmp_path / "p.csv").write_text(text)
    code, _, err = cli(
        capsys, "profiles", "import", "csv", str(tmp_path / "p.csv"), "--id", "p", "-o", str(tmp_path / "back.yaml")
    )
    assert code == 0, err
    back = load_profile(tmp_path / "back.yaml")
    assert [p.description for p in back.parameters] == ['=HYPERLINK("http://x","y")', "-2+3", "@SUM(1)", "+1"]


def test_export_says_what_a_register_list_cannot_carry(capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = cli(capsys, "profiles", "export", "csv", "example-drive")
    assert code == 0
    for what in (
        "1 identity check",
        "1 precondition",
        "1 unlock write",
        "1 lock write",
        "1 commit action",
        "1 stage wait",
        "addressing: register-number",
    ):
        assert f"warning: example-drive: {what}" in err, err


# ------------------------------------------------------------------------------ clean errors, elsewhere


def _why(call: Any, *args: Any) -> str:
    """What the system says when ``call(*args)`` fails (its own words: Windows' differ from POSIX's)."""
    try:
        call(*args)
    except OSError as e:
        return str(e.strerror)
    raise AssertionError(f"{call.__name__}{args} did not fail")


def test_clean_errors_for_outputs_and_options(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    blocked = tmp_path / "a-file" / "x"  # a folder that cannot be made: its parent is a file
    (tmp_path / "a-file").write_text("")
    code, _, err = cli(capsys, "docs", "--out", str(blocked))
    assert code == 1 and f"error: cannot write the pages into {blocked}: {_why(os.makedirs, blocked)}" in err, err
    code, _, err = cli(capsys, "profiles", "new", str(tmp_path / "nodir" / "x.yaml"))
    missing = _why(open, tmp_path / "nodir" / "x.yaml", "x")
    assert code == 1 and f"x.yaml: {missing}" in err and "Traceback" not in err, err
    code, _, err = cli(capsys, "explain", "k" * 100_000)
    assert code == 1 and len(err) < 300 and "(100000 characters)" in err
    pytest.importorskip("sunspec2")
    code, _, err = cli(capsys, "profiles", "import", "sunspec", "121", "--sf", "WMax_SF=1000000000")
    assert code == 1 and "--sf WMax_SF=1000000000: a SunSpec scale factor is -10 to 10" in err
    code, _, err = cli(capsys, "profiles", "import", "sunspec", "121", "--sf", "WMax_SF=-1000000")
    assert code == 1 and "a SunSpec scale factor is -10 to 10" in err and "must not be 0" not in err
    code, _, err = cli(capsys, "profiles", "import", "sunspec", "121", "--sf", "WMax_SF=" + "9" * 5000)
    assert code == 1 and "a whole number" in err and len(err) < 400


def test_a_value_closer_to_0_than_meant_is_not_rounded_away(tmp_path: Path) -> None:
    (tmp_path / "r.yaml").write_text("recipe: r\nprofile: example-inverter\nparameters:\n  F07: 1e-999999999 s\n")
    with pytest.raises(InputError) as e:
        load_recipe(tmp_path / "r.yaml")
    (d,) = e.value.diagnostics
    assert (d.line, d.col) == (4, 8) and "1e-999999999 is too close to 0" in d.message


def test_import_reports_name_no_device(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = write_csv(tmp_path / "m.csv", [["name", "address", "type"], ["a", "zz", "U16"]])
    code, _, err = cli(capsys, "profiles", "import", "csv", str(src), "--id", "m")
    assert code == 1 and err.endswith("1 error; no profile was written\n")
    assert not os.path.exists(tmp_path / "m.yaml")


def test_a_header_cell_spanning_lines(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Found by fuzzing: a quoted header cell with a line break (its row's later cells have no column on the
    first line) and a quote inside an unquoted cell (literal, as the csv module reads it)."""
    src = tmp_path / "h.csv"
    # its own line ends, on Windows too (a CRLF file's cell is 'Remark\r\nmore', as the csv module reads it)
    src.write_text('name,address,type,Setting "range,"Remark\nmore",Note\nspeed,1,U16,,,\n', newline="")
    out = tmp_path / "h.yaml"
    code, _, err = cli(capsys, "profiles", "import", "csv", str(src), "--id", "h", "-o", str(out))
    assert code == 0, err
    assert f"{src}:1:19: warning: column 'Setting \"range' is not used" in err
    assert f"{src}:1:34: warning: column 'Remark\\nmore' is not used" in err
    assert f"{src}:1:1: warning: column 'Note' is not used" in err
    assert load_profile(out).names() == ["speed"]
