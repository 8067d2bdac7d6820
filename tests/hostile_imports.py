"""Hostile register lists, workbooks and SunSpec models (issue #24): the worst inputs for the importers.

``WORST`` lists the inputs of the issue at their full size (the benchmark `bench_import` measures each
command's time and peak memory; tests/test_import_hostile.py runs them bounded). ``write_corpus`` writes
the small ones of the malformed-file corpus, tests/bad/import/ (``python -m tests.hostile_imports``).
"""

from __future__ import annotations

import functools
import io
import json
import sys
import zipfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

HEADER = "name,address,type,unit,scale,min,max\n"


@functools.cache
def _base_workbook() -> dict[str, bytes]:
    """The parts of a one-sheet workbook openpyxl writes (cell A1 = 'name'), by name."""
    import openpyxl

    wb = openpyxl.Workbook()
    wb.active.title = "Sheet1"
    wb.active["A1"] = "name"
    buf = io.BytesIO()
    wb.save(buf)
    with zipfile.ZipFile(buf) as z:
        return {n: z.read(n) for n in z.namelist()}


NS = 'xmlns="http://schemas.openxmlformats.org/spreadsheetml/2006/main"'


def write_xlsx(path: Path, sheet: Iterable[bytes], strings: Iterable[bytes] | None = None) -> None:
    """A workbook whose first sheet's XML is ``sheet`` (streamed into the zip), and shared strings."""
    parts = _base_workbook()
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in parts.items():
            if name == "xl/worksheets/sheet1.xml" or (name == "xl/sharedStrings.xml" and strings is not None):
                continue
            z.writestr(name, data)
        with z.open("xl/worksheets/sheet1.xml", "w", force_zip64=True) as f:
            for chunk in sheet:
                f.write(chunk)
        if strings is not None:
            with z.open("xl/sharedStrings.xml", "w", force_zip64=True) as f:
                for chunk in strings:
                    f.write(chunk)


def _sheet(rows: Iterable[bytes], dimension: str = "A1:C3") -> Iterable[bytes]:
    yield f'<?xml version="1.0" encoding="UTF-8"?>\n<worksheet {NS}><dimension ref="{dimension}"/><sheetData>'.encode()
    yield from rows
    yield b"</sheetData></worksheet>"


def _row(r: int, cells: Iterable[tuple[str, str]]) -> bytes:
    """A row of inline-string cells (reference, text)."""
    inner = "".join(f'<c r="{ref}" t="inlineStr"><is><t>{text}</t></is></c>' for ref, text in cells)
    return f'<row r="{r}">{inner}</row>'.encode()


def _head(r: int = 1) -> bytes:
    return _row(r, [("A1", "name"), ("B1", "address"), ("C1", "type")])


def xlsx_dimension_bomb(path: Path) -> None:
    """<dimension ref="A1:XFD1048576"/> and one cell at XFD1048576 (openpyxl's read-only rows pad to it)."""
    write_xlsx(
        path,
        _sheet(
            [
                _head(),
                _row(2, [("A2", "speed"), ("B2", "1"), ("C2", "U16")]),
                b'<row r="1048576"><c r="XFD1048576"><v>1</v></c></row>',
            ],
            "A1:XFD1048576",
        ),
    )


def xlsx_rows(path: Path, n: int = 5_000_000) -> None:
    """``n`` identical rows (5M: 1.8 MB on disk, 200 MB of XML)."""

    def rows() -> Iterable[bytes]:
        yield _head()
        chunk = b"".join(f'<row r="{r}"><c r="A{r}"><v>1</v></c></row>'.encode() for r in range(2, 1002))
        for _ in range(n // 1000):
            yield chunk  # row numbers repeat per chunk: what counts is how many rows there are

    write_xlsx(path, _sheet(rows()))


def xlsx_shared_string(path: Path, size: int = 400_000_000) -> None:
    """One shared string of ``size`` characters (400 MB in a 394 KB file)."""

    def strings() -> Iterable[bytes]:
        yield f'<?xml version="1.0" encoding="UTF-8"?>\n<sst {NS} count="1" uniqueCount="1"><si><t>'.encode()
        block = b"a" * (1 << 20)
        for _ in range(size // len(block)):
            yield block
        yield b"</t></si></sst>"

    write_xlsx(path, _sheet([_head(), b'<row r="2"><c r="A2" t="s"><v>0</v></c></row>']), strings())


def xlsx_wide_row(path: Path, cells: int = 2_000_000) -> None:
    """A row of ``cells`` empty-valued cells (styled cells without values), within the zip bound."""

    def rows() -> Iterable[bytes]:
        yield _head()
        yield b'<row r="2">'
        block = b'<c s="0"/>' * 10_000
        for _ in range(cells // 10_000):
            yield block
        yield b"</row>"

    write_xlsx(path, _sheet(rows()))


def xlsx_formula(path: Path) -> None:
    """A resolution cell holding the formula =1/10 without a saved value (files written by scripts)."""
    write_xlsx(
        path,
        _sheet(
            [
                _row(1, [("A1", "name"), ("B1", "address"), ("C1", "type"), ("D1", "unit"), ("E1", "scale")]),
                b'<row r="2"><c r="A2" t="inlineStr"><is><t>F07</t></is></c><c r="B2"><v>4354</v></c>'
                b'<c r="C2" t="inlineStr"><is><t>U16</t></is></c><c r="D2" t="inlineStr"><is><t>s</t></is></c>'
                b'<c r="E2"><f>1/10</f></c></row>',
            ]
        ),
    )


def xlsx_column_far_right(path: Path) -> None:
    write_xlsx(path, _sheet([_head(), _row(2, [("A2", "speed"), ("B2", "1"), ("C2", "U16"), ("IW2", "x")])]))


def xlsx_too_many_rows(path: Path) -> None:
    """131,073 more rows after the header (1 MB of XML, 2 kB zipped): the row bound, not the zip bound."""
    write_xlsx(path, _sheet([_head(), b"<row/>" * 131_073]))


def csv_cells(path: Path, n: int = 30_000_000) -> None:
    """One row of ``n`` empty cells (30M: a 30 MB file, 1.6 GB before)."""
    with open(path, "w") as f:
        f.write(HEADER)
        f.write("," * n + "\n")


def csv_header_of_commas(path: Path, size: int = 8_000_000) -> None:
    """An 8 MB header of commas (the header search normalised each cell 18 times: 103 s)."""
    with open(path, "w") as f:
        f.write("," * size + "\n")


def csv_rows(path: Path, n: int = 1_000_000) -> None:
    """``n`` register rows (1M: 15.6 s and 1.2 GB before 'more than 65536 entries')."""
    with open(path, "w") as f:
        f.write(HEADER)
        f.writelines(f"p{i},{i % 65536},U16,s,0.1,0,100\n" for i in range(n))


def csv_header_columns(path: Path, n: int = 1_000_000) -> None:
    """A 1M-column header (its names echoed whole in a 2 MB message before)."""
    with open(path, "w") as f:
        f.write(",".join("x" for _ in range(n)) + "\n")


def csv_largest_valid(path: Path, n: int = 65_536) -> None:
    """The largest register list a profile holds: 65,536 rows of one register each."""
    with open(path, "w") as f:
        f.write(HEADER)
        f.writelines(f"p{i},{i},U16,s,0.1,0,100\n" for i in range(n))


def sunspec_inner_count(path: Path, count: int = 100_000_000) -> None:
    """A 444-byte model whose curve's points repeat ``count`` times."""
    path.write_text(
        json.dumps(
            {
                "id": 64990,
                "group": {
                    "name": "bomb",
                    "type": "group",
                    "points": [
                        {"name": "ID", "type": "uint16", "size": 1, "value": 64990, "mandatory": "M", "static": "S"},
                        {"name": "L", "type": "uint16", "size": 1, "mandatory": "M", "static": "S"},
                    ],
                    "groups": [
                        {
                            "name": "Crv",
                            "type": "group",
                            "count": 1,
                            "points": [{"name": "ActPt", "type": "uint16", "size": 1}],
                            "groups": [
                                {
                                    "name": "Pt",
                                    "type": "group",
                                    "count": count,
                                    "points": [
                                        {"name": "V", "type": "uint16", "size": 1},
                                        {"name": "Var", "type": "int16", "size": 1},
                                    ],
                                }
                            ],
                        }
                    ],
                },
            },
            indent=1,
        )
    )


@dataclass(frozen=True)
class Worst:
    """One of the issue's worst inputs: how to make it, the command, and what it must end with."""

    name: str
    file: str
    make: Callable[[Path], None]
    args: tuple[str, ...]  # after 'deployer profiles import'; {f} is the file
    expect: str  # a fragment of stderr
    code: int = 1
    quick: Callable[[Path], None] | None = None  # a smaller input of the same kind (the test's; None: the same)


WORST = [
    Worst(
        "xlsx_dimension_bomb",
        "dim.xlsx",
        xlsx_dimension_bomb,
        ("xlsx", "{f}", "--id", "x"),
        "[Sheet1]:1048576:16384: error: a cell in column 16,384",
    ),
    Worst(
        "xlsx_5M_rows",
        "rows.xlsx",
        xlsx_rows,
        ("xlsx", "{f}", "--id", "x"),
        "the workbook unpacks to",
        quick=lambda p: xlsx_rows(p, 1_000_000),
    ),
    Worst(
        "xlsx_400MB_shared_string",
        "sst.xlsx",
        xlsx_shared_string,
        ("xlsx", "{f}", "--id", "x"),
        "the workbook unpacks to",
        quick=lambda p: xlsx_shared_string(p, 40_000_000),
    ),
    Worst(
        "xlsx_2M_empty_cells_in_a_row",
        "wide.xlsx",
        xlsx_wide_row,
        ("xlsx", "{f}", "--id", "x"),
        "more than 2,000,000 cells, empty ones included",
    ),
    Worst(
        "csv_row_of_30M_cells",
        "cells.csv",
        csv_cells,
        ("csv", "{f}", "--id", "x"),
        ":2:1: error: a row of more than 1,048,576 characters",
    ),
    Worst(
        "csv_8MB_header_of_commas",
        "commas.csv",
        csv_header_of_commas,
        ("csv", "{f}", "--id", "x"),
        ":1:1: error: a row of more than 1,048,576 characters",
    ),
    Worst(
        "csv_1M_rows",
        "rows.csv",
        csv_rows,
        ("csv", "{f}", "--id", "x"),
        ":65538:1: error: more than 65,536 register rows",
        quick=lambda p: csv_rows(p, 70_000),
    ),
    Worst(
        "csv_1M_column_header",
        "header.csv",
        csv_header_columns,
        ("csv", "{f}", "--id", "x"),
        ":1:1: error: a row of more than 1,048,576 characters",
    ),
    Worst(
        "csv_65536_rows_valid",
        "valid.csv",
        csv_largest_valid,
        ("csv", "{f}", "--id", "x", "-o", "{f}.yaml"),
        "profile x with",
        0,
        quick=lambda p: csv_largest_valid(p, 5000),
    ),
    Worst(
        "sunspec_inner_count_1e8",
        "bomb.json",
        sunspec_inner_count,
        ("sunspec", "{f}"),
        "group Pt: count 100000000 repeats past register 65535",
    ),
    Worst(
        "sunspec_705_count_Pt_1e8",
        "",
        lambda p: None,
        ("sunspec", "705", "--count", "Crv=1", "--count", "Pt=100000000"),
        "a group repeats 1 to 65535 times",
    ),
]


# ------------------------------------------------------------------------------ the committed corpus

CORPUS: dict[str, Callable[[Path], None]] = {
    "xlsx-dimension-bomb.xlsx": xlsx_dimension_bomb,
    "xlsx-formula-without-value.xlsx": xlsx_formula,
    "xlsx-column-far-right.xlsx": xlsx_column_far_right,
    "xlsx-too-many-rows.xlsx": xlsx_too_many_rows,
    "xlsx-shared-string-40MB.xlsx": lambda p: xlsx_shared_string(p, 40_000_000),
    "sunspec-inner-count.json": sunspec_inner_count,
    "sunspec-negative-count.json": lambda p: _model(
        p, [], [{"name": "Crv", "type": "group", "count": -5, "points": [{"name": "V", "type": "uint16", "size": 1}]}]
    ),
    "sunspec-point-name-injection.json": lambda p: _model(
        p, [{"name": "X: {register: 7, type: uint16, access: read-write}\n  Z", "type": "uint16", "size": 1}]
    ),
    "sunspec-long-name.json": lambda p: _model(p, [{"name": "W" * 2000, "type": "uint16", "size": 1}]),
    "sunspec-sf-too-large.json": lambda p: _model(
        p, [{"name": "W", "type": "uint16", "size": 1, "sf": 1000000000, "units": "W"}]
    ),
}


def _model(path: Path, points: list[dict[str, object]], groups: list[dict[str, object]] | None = None) -> None:
    """A model definition of id 64991 with ID, L and ``points`` (and ``groups``), one key per line."""
    group: dict[str, object] = {
        "name": "hostile",
        "type": "group",
        "points": [
            {"name": "ID", "type": "uint16", "size": 1, "value": 64991, "mandatory": "M", "static": "S"},
            {"name": "L", "type": "uint16", "size": 1, "mandatory": "M", "static": "S"},
            *points,
        ],
    }
    if groups:
        group["groups"] = groups
    path.write_text(json.dumps({"id": 64991, "group": group}, indent=1) + "\n")


def write_corpus(directory: Path) -> None:
    for name, make in CORPUS.items():
        make(directory / name)


if __name__ == "__main__":
    write_corpus(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent / "bad" / "import")
