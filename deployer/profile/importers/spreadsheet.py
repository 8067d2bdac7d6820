"""Import a vendor's register list (CSV, or an Excel workbook) as a profile, and write a profile
back as such a list.

Columns are found by header name (case and spaces ignored); ``columns`` maps our names to
other headers. Every problem points at its cell: FILE:LINE:COL (FILE[SHEET]:ROW:COL).

    name, address, type, unit, scale, min, max, access, description   (+ range, bits, count, values, byte_order ...)

Cells are read as vendors write them: a resolution with its unit (``0.01 s``), a range
(``0 to 40000``, ``0-400.00``, ``0...100 %``), limits with units, decimal commas where they are
unambiguous. Every input is bounded while it is read, before anything is built from it: rows,
cells per row, characters per cell and per CSV record, and for workbooks the sizes the zip
archive declares (the sheet's own ``dimension`` is not trusted; cells are streamed, never padded).
"""

from __future__ import annotations

import csv
import io
import os
import re
import stat
import zipfile
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from typing import Any

from ...errors import Diagnostic, InputError, UsageError
from ...load import messages, yamlsrc
from .. import codec, units
from ..emit import MAX_DIGITS, Draft, Origin

MAX_ROWS = 131_072  # rows read, blank and comment rows included (a profile holds at most 65,536 parameters)
MAX_PARAMETERS = yamlsrc.MAX_ENTRIES
MAX_COLUMNS = 256  # cells in one row
MAX_CELL = 65_536  # characters in one cell
MAX_XLSX_CELLS = 2_000_000  # cell elements of a sheet, empty ones included (65,536 rows of 30 columns)
MAX_RECORD = 1 << 20  # characters in one CSV record (a row, with the lines a quoted cell spans)
MAX_XLSX_BYTES = 32 * 1024 * 1024  # uncompressed bytes of a workbook's parts, summed (what the zip declares)
MAX_XLSX_PARTS = 1000  # files in a workbook's zip
MAX_NUMBER = 100  # characters of a number cell

# our column -> headers vendors use for it (lower case, spaces and underscores removed)
COLUMNS: dict[str, tuple[str, ...]] = {
    "name": ("name", "parameter", "parametername", "tag", "symbol", "point"),
    "address": ("address", "register", "addr", "registeraddress", "reg", "modbusaddress"),
    "type": ("type", "datatype", "format", "dtype"),
    "unit": ("unit", "units", "uom"),
    "scale": ("scale", "resolution", "factor", "multiplier", "gain"),
    "min": ("min", "minimum", "low", "rangemin"),
    "max": ("max", "maximum", "high", "rangemax"),
    "range": (
        "range",
        "settingrange",
        "setrange",
        "valuerange",
        "limits",
        "adjustablerange",
        "datarange",
        "setpointrange",
    ),
    "access": ("access", "rw", "r/w", "mode", "accesstype"),
    "description": ("description", "desc", "comment", "label"),
    "bits": ("bits", "bit"),
    "count": ("count", "registers", "length", "size", "words"),
    "values": ("values", "enum", "enumeration", "options"),
    "byte_order": ("byteorder", "layout", "endianness", "swap"),
    "default": ("default", "defaultvalue", "initial", "factorydefault", "factorysetting"),
    "encoding": ("encoding", "charset"),
    "padding": ("padding", "pad"),
    "stage": ("stage",),
    "restart": ("restart", "powercycle", "restartrequired"),
}
REQUIRED = ("name", "address", "type")

TYPES: dict[str, str] = {
    **{k: "uint16" for k in ("uint16", "u16", "unsigned16", "word", "uint", "ushort", "unsigned")},
    **{k: "int16" for k in ("int16", "s16", "i16", "signed16", "int", "short", "signed")},
    **{k: "uint32" for k in ("uint32", "u32", "udint", "dword", "unsigned32", "ulong")},
    **{k: "int32" for k in ("int32", "s32", "i32", "dint", "signed32", "long")},
    **{k: "uint64" for k in ("uint64", "u64", "ulint", "lword")},
    **{k: "int64" for k in ("int64", "s64", "i64", "lint")},
    **{k: "float32" for k in ("float32", "float", "real", "f32", "single", "ieee754")},
    **{k: "float64" for k in ("float64", "double", "lreal", "f64")},
    **{k: "string" for k in ("string", "str", "char", "ascii", "text")},
    **{k: "bool" for k in ("bool", "boolean", "bit", "flag")},
}
ACCESS: dict[str, str] = {
    **{k: "read-only" for k in ("r", "ro", "read", "readonly", "read-only")},
    **{k: "write-only" for k in ("w", "wo", "write", "writeonly", "write-only")},
    **{k: "read-write" for k in ("rw", "r/w", "wr", "read-write", "readwrite", "read/write")},
}
_NAME_OK = re.compile(r"^[A-Za-z_][A-Za-z0-9_.-]*$")
_DIGITS = re.compile(r"[0-9]{1,9}")  # small counts; str.isdigit() also accepts digits of other scripts
_ADDRESS = re.compile(r"(?:0[xX][0-9A-Fa-f]{1,8}|[0-9A-Fa-f]{1,8}[hH]|[0-9]{1,9})")
_NUM = r"[-+]?(?:[0-9](?:[0-9.,']*[0-9])?|[.,][0-9]+)(?:[eE][-+]?[0-9]+)?"
_QUANTITY = re.compile(rf"\s*(?P<num>{_NUM})\s*(?P<unit>[^\d\s.,+-][^\d]*?)?\s*")
_RANGE = re.compile(
    rf"\s*(?P<lo>{_NUM})\s*(?P<lou>[^\d\s.,+\-~–—…][^\d]*?)?\s*"
    r"(?:\bto\b|\bbis\b|\.\.\.?|…|~|–|—|-)"
    rf"\s*(?P<hi>{_NUM})\s*(?P<hiu>[^\d\s.,+-][^\d]*?)?\s*",
    re.IGNORECASE,
)
_FORMULA_CHARS = "=+-@\t\r"  # a cell starting with one of these is a formula to a spreadsheet program
_FORMULA_STARTS = tuple(_FORMULA_CHARS)


def _key(header: str) -> str:
    return re.sub(r"[\s_]+", "", header.strip().lower())


def _show(text: str) -> str:
    """A cell's text in a message: quoted, cut, control characters visible."""
    return messages.clipped_repr(text)


@dataclass
class Row:
    line: int  # the line (sheet row) it starts on
    cells: list[str]
    starts: list[int]  # each cell's column
    formulas: dict[int, str] | None = None  # cell index -> formula of a cell that has no saved value

    def column(self, i: int) -> int:
        """Where cell ``i`` starts (1 for a cell after a line break inside a quoted cell: its row's first line
        is what the columns are counted on)."""
        return self.starts[i] if i < len(self.starts) else 1


class _Stop(Exception):
    """A bound was hit while reading: the diagnostics so far, and this one, are the answer."""

    def __init__(self, diagnostic: Diagnostic) -> None:
        self.diagnostic = diagnostic


# ---------------------------------------------------------------------------------------------- CSV


def _cell_starts(line: str, delimiter: str) -> list[int]:
    """1-based column where each cell of a physical CSV line starts (quotes respected)."""
    starts, quoted = [1], False
    for i, ch in enumerate(line):
        if ch == '"' and (quoted or i + 1 == starts[-1]):  # as the csv module: a quote opens only a cell
            quoted = not quoted
        elif ch == delimiter and not quoted:
            starts.append(i + 2)
    return starts


def read_csv(
    path: str,
    *,
    profile_id: str,
    columns: Mapping[str, str] | None = None,
    addressing: str = "address",
    delimiter: str | None = None,
    byte_order: str | None = None,
    decimal: str | None = None,
) -> tuple[Draft, list[str]]:
    """The register list at ``path`` as a Draft profile and warnings; InputError with every bad cell at once.

    ``decimal``: "comma" or "point" for the decimal mark of every number cell; None: a comma is a decimal
    mark only where it cannot be a thousands separator (``3,000`` is then an error at its cell).
    """
    text = yamlsrc.read_text(path)
    nul = text.find("\0")
    if nul >= 0:
        line = text.count("\n", 0, nul) + 1
        col = nul - (text.rfind("\n", 0, nul) + 1) + 1
        raise InputError(
            [
                Diagnostic(
                    path,
                    line,
                    col,
                    "a NUL character: is this UTF-16 text without a byte-order "
                    "mark? Save the list as UTF-8 (CSV UTF-8 in Excel)",
                )
            ]
        )
    if delimiter is None:
        try:
            delimiter = csv.Sniffer().sniff(text[:4096], delimiters=",;\t").delimiter
        except csv.Error:
            delimiter = ","
    if len(delimiter) != 1:
        raise UsageError(f"--delimiter {delimiter!r}: one character")
    return _draft(
        path,
        _csv_rows(path, text, delimiter),
        profile_id=profile_id,
        columns=columns,
        addressing=addressing,
        byte_order=byte_order,
        decimal=decimal,
    )


_LINE = re.compile(r"[^\r\n]*(?:\r\n|\r|\n)|[^\r\n]+\Z")


@dataclass
class _Record:
    line: int = 0  # physical lines read so far
    chars: int = 0  # characters of the record being read
    first: str = ""  # its first physical line


def _csv_rows(path: str, text: str, delimiter: str) -> Iterator[Row]:
    """The CSV's records, each checked against the bounds before the next is read."""
    # lines as the csv module counts them (\r too), one at a time (io.StringIO would copy the text 4 bytes a character)
    physical = (m.group() for m in _LINE.finditer(text))
    state = _Record()

    def lines() -> Iterator[str]:
        for ln in physical:
            state.line += 1
            if not state.chars:
                state.first = ln
            state.chars += len(ln)
            if state.chars > MAX_RECORD:
                raise _Stop(
                    Diagnostic(
                        path,
                        state.line,
                        1,
                        f"a row of more than {MAX_RECORD:,} characters (a register list's rows are short)",
                    )
                )
            yield ln

    old = csv.field_size_limit()
    csv.field_size_limit(MAX_RECORD + 1)  # the record bound comes first; cells are checked once read
    reader = csv.reader(lines(), delimiter=delimiter)
    try:
        n = 0
        while True:
            start = state.line + 1
            try:
                cells = next(reader)
            except StopIteration:
                return
            except csv.Error as e:
                raise _Stop(Diagnostic(path, state.line, 1, f"not a CSV row: {e}")) from None
            n += 1
            if n > MAX_ROWS:
                raise _Stop(Diagnostic(path, start, 1, f"more than {MAX_ROWS:,} rows"))
            if len(cells) > MAX_COLUMNS:
                starts = _cell_starts(state.first[:MAX_RECORD], delimiter)
                raise _Stop(
                    Diagnostic(
                        path,
                        start,
                        starts[MAX_COLUMNS] if len(starts) > MAX_COLUMNS else 1,
                        f"a row of {len(cells):,} cells; at most {MAX_COLUMNS}",
                    )
                )
            starts = _cell_starts(state.first, delimiter)
            for i, c in enumerate(cells):
                if len(c) > MAX_CELL:
                    raise _Stop(
                        Diagnostic(
                            path,
                            start,
                            starts[i] if i < len(starts) else 1,
                            f"a cell of {len(c):,} characters; at most {MAX_CELL:,}",
                        )
                    )
            yield Row(start, cells, starts)
            state.chars = 0
    finally:
        csv.field_size_limit(old)


# --------------------------------------------------------------------------------------------- xlsx


def read_xlsx(
    path: str,
    *,
    profile_id: str,
    sheet: str | None = None,
    columns: Mapping[str, str] | None = None,
    addressing: str = "address",
    byte_order: str | None = None,
    decimal: str | None = None,
) -> tuple[Draft, list[str]]:
    """A register list in an Excel workbook (openpyxl, the 'xlsx' extra); problems point at FILE[SHEET]:ROW:COLUMN."""
    try:
        import openpyxl
    except ImportError:
        raise UsageError(
            "reading .xlsx needs openpyxl: pip install 'modbus-deployer[xlsx]' "
            "(from a clone of the repository: pip install -e '.[xlsx]')"
        ) from None
    _regular_file(path)
    try:
        with zipfile.ZipFile(path) as z:
            infos = z.infolist()
    except (zipfile.BadZipFile, OSError, ValueError) as e:
        raise InputError([Diagnostic(path, 1, 1, f"not an Excel workbook (.xlsx is a zip archive): {e}")]) from None
    if len(infos) > MAX_XLSX_PARTS:
        raise InputError(
            [Diagnostic(path, 1, 1, f"the workbook's zip holds {len(infos):,} files; at most {MAX_XLSX_PARTS:,}")]
        )
    total = sum(i.file_size for i in infos)
    if total > MAX_XLSX_BYTES:
        biggest = max(infos, key=lambda i: i.file_size)
        raise InputError(
            [
                Diagnostic(
                    path,
                    1,
                    1,
                    f"the workbook unpacks to {total / 1e6:.1f} MB (its largest part "
                    f"{_show(biggest.filename)}: {biggest.file_size / 1e6:.1f} MB); at "
                    f"most {MAX_XLSX_BYTES // (1024 * 1024)} MiB",
                )
            ]
        )
    try:
        book = openpyxl.load_workbook(path, read_only=True, data_only=True)
    except Exception as e:  # openpyxl raises its own, zipfile's and XML errors for files it cannot read
        raise InputError([Diagnostic(path, 1, 1, f"cannot read the workbook: {messages.clip(str(e), 200)}")]) from None
    try:
        if sheet is not None and sheet not in book.sheetnames:
            raise InputError(
                [
                    Diagnostic(
                        path,
                        1,
                        1,
                        f"no sheet {_show(sheet)} (sheets: {messages.clip(', '.join(book.sheetnames), 200)})",
                    )
                ]
            )
        ws = book[sheet] if sheet is not None else book.worksheets[0]
        where = f"{path}[{ws.title}]"
        part = getattr(ws, "_worksheet_path", None)  # openpyxl's read-only sheet knows its part in the zip
        if not isinstance(part, str):
            raise InputError([Diagnostic(where, 1, 1, "not a worksheet (a chart sheet?)")])
        strings = list(getattr(ws, "_shared_strings", None) or [])
    finally:
        book.close()
    with zipfile.ZipFile(path) as z:
        return _draft(
            where,
            _sheet_rows(where, z, part, strings),
            profile_id=profile_id,
            columns=columns,
            addressing=addressing,
            byte_order=byte_order,
            decimal=decimal,
        )


def _regular_file(path: str) -> None:
    """A workbook is opened only when it is a regular file within the size bound (a FIFO would block)."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise InputError([Diagnostic(path, 0, 0, "no such file")]) from None
    except OSError as e:
        raise InputError([Diagnostic(path, 0, 0, f"cannot read: {e.strerror}")]) from None
    if not stat.S_ISREG(st.st_mode):
        raise InputError([Diagnostic(path, 0, 0, "not a regular file (a directory, device, FIFO or socket)")])
    if st.st_size > MAX_XLSX_BYTES:
        raise InputError(
            [
                Diagnostic(
                    path,
                    1,
                    1,
                    f"file too large ({st.st_size / 1e6:.1f} MB; limit {MAX_XLSX_BYTES // (1024 * 1024)} MiB)",
                )
            ]
        )


_REF = re.compile(r"([A-Z]{1,3})([0-9]{1,7})\Z")


def _column_number(letters: str) -> int:
    n = 0
    for ch in letters:
        n = n * 26 + ord(ch) - 64
    return n


class _SheetReader:
    """The sheet's XML read with expat's callbacks, keeping only the row being read: a row of a million
    cells, a cell at XFD1048576 or a lying ``dimension`` cost what their XML costs, never a padded grid
    (openpyxl's read-only rows are padded to the dimension's width) nor a tree of elements."""

    def __init__(self, where: str, strings: list[str]) -> None:
        self.where = where
        self.strings = strings
        self.done: list[Row] = []
        self.n_rows = 0
        self.n_cells = 0
        self.line = 0
        self.cells: dict[int, str] = {}
        self.formulas: dict[int, str] = {}
        self.col = 0
        self.kind = "n"
        self.value: list[str] | None = None  # text of the cell's <v> (or inline <t>)
        self.formula: list[str] | None = None
        self.text: list[str] | None = None  # the element whose characters are collected
        self.has_formula = False
        self.inline = False
        self.in_phonetic = False

    def start(self, tag: str, attrs: dict[str, str]) -> None:
        tag = tag.rpartition(":")[2]
        if tag == "c":
            self.n_cells += 1
            if self.n_cells > MAX_XLSX_CELLS:
                raise _Stop(
                    Diagnostic(
                        self.where, self.line, self.col + 1, f"more than {MAX_XLSX_CELLS:,} cells, empty ones included"
                    )
                )
            ref = _REF.match(attrs.get("r", ""))
            self.col = _column_number(ref[1]) if ref else self.col + 1
            self.kind = attrs.get("t", "n")
            self.value = self.formula = None
            self.has_formula = self.inline = False
        elif tag == "v":
            self.value = self.text = []
        elif tag == "f":
            self.has_formula = True
            self.formula = self.text = []
        elif tag == "is":
            self.inline = True
            self.value = []
        elif tag == "t" and self.inline and not self.in_phonetic:
            self.text = self.value
        elif tag == "rPh":
            self.in_phonetic = True
        elif tag == "row":
            self.n_rows += 1
            if self.n_rows > MAX_ROWS:
                raise _Stop(Diagnostic(self.where, self.line + 1, 1, f"more than {MAX_ROWS:,} rows"))
            r = attrs.get("r", "")
            self.line = int(r) if r.isdigit() and len(r) <= 7 else self.line + 1
            self.cells, self.formulas, self.col = {}, {}, 0

    def chars(self, data: str) -> None:
        if self.text is not None:
            self.text.append(data)
            if len(self.text) > 64 and sum(map(len, self.text)) > MAX_CELL:
                raise _Stop(Diagnostic(self.where, self.line, self.col, f"a cell of more than {MAX_CELL:,} characters"))

    def end(self, tag: str) -> None:
        tag = tag.rpartition(":")[2]
        if tag in ("v", "f", "t"):
            self.text = None
        elif tag == "rPh":
            self.in_phonetic = False
        elif tag == "c":
            value = self._value()
            if value is None and not self.has_formula:
                return
            if self.col > MAX_COLUMNS:
                raise _Stop(
                    Diagnostic(
                        self.where,
                        self.line,
                        self.col,
                        f"a cell in column {self.col:,}; a register list has at most {MAX_COLUMNS} columns",
                    )
                )
            if value is not None and len(value) > MAX_CELL:
                raise _Stop(
                    Diagnostic(
                        self.where, self.line, self.col, f"a cell of {len(value):,} characters; at most {MAX_CELL:,}"
                    )
                )
            self.cells[self.col] = value or ""
            if value is None:
                self.formulas[self.col - 1] = "=" + "".join(self.formula or [])
        elif tag == "row":
            width = max(self.cells, default=0)
            self.done.append(
                Row(
                    self.line,
                    [self.cells.get(i, "") for i in range(1, width + 1)],
                    list(range(1, width + 1)),
                    self.formulas or None,
                )
            )

    def _value(self) -> str | None:
        """The cell's saved value as text; None when it has none (empty, or a formula never calculated)."""
        if self.inline:
            return "".join(self.value or [])
        v = "".join(self.value) if self.value is not None else ""
        if v == "":
            return None
        if self.kind == "s":
            i = int(v) if v.isdigit() and len(v) <= 9 else -1
            return self.strings[i] if 0 <= i < len(self.strings) else f"#REF! (shared string {messages.clip(v, 20)})"
        if self.kind == "b":
            return "true" if v.strip() == "1" else "false"
        if self.kind == "n":
            try:
                x = float(v)
            except ValueError:
                return v
            return str(int(x)) if x.is_integer() and abs(x) < 1e16 else repr(x)
        return v  # str (a formula's text result), e (an error such as #DIV/0!), d (an ISO date)


def _sheet_rows(where: str, z: zipfile.ZipFile, part: str, strings: list[str]) -> Iterator[Row]:
    """The sheet's rows, each yielded once read (bounds checked while the XML is read)."""
    from xml.parsers import expat

    reader = _SheetReader(where, strings)
    parser = expat.ParserCreate()
    parser.buffer_text = True
    parser.StartElementHandler = reader.start
    parser.EndElementHandler = reader.end
    parser.CharacterDataHandler = reader.chars
    try:
        with z.open(part) as f:
            while True:
                chunk = f.read(1 << 16)
                parser.Parse(chunk, not chunk)
                yield from reader.done
                reader.done.clear()
                if not chunk:
                    return
    except expat.ExpatError as e:
        raise _Stop(
            Diagnostic(
                where,
                1,
                1,
                f"the sheet's XML ({part}) is broken at its line {e.lineno}, column "
                f"{e.offset + 1}: {expat.ErrorString(e.code)}",
            )
        ) from None
    except (zipfile.BadZipFile, OSError, EOFError) as e:
        raise _Stop(Diagnostic(where, 1, 1, f"cannot read the sheet from the workbook: {e}")) from None


# ------------------------------------------------------------------------------------------ the rows


def _draft(
    path: str,
    rows: Iterable[Row],
    *,
    profile_id: str,
    columns: Mapping[str, str] | None,
    addressing: str,
    byte_order: str | None,
    decimal: str | None,
) -> tuple[Draft, list[str]]:
    errors: list[Diagnostic] = []
    warnings: list[str] = []
    if byte_order and byte_order not in codec.LAYOUTS and byte_order not in codec.SWAPS:
        raise UsageError(
            f"--byte-order {messages.clip(byte_order)}: expected one of {', '.join([*codec.LAYOUTS, *codec.SWAPS])}"
        )
    if decimal not in (None, "comma", "point"):
        raise UsageError(f"decimal mark {_show(str(decimal))}: comma or point")
    wanted: dict[str, str] = {}  # header key -> our column
    for ours, keys in COLUMNS.items():
        for k in keys:
            wanted.setdefault(_key(k), ours)
    for ours, theirs in (columns or {}).items():
        if ours not in COLUMNS:
            raise UsageError(f"--column {messages.clip(ours)}=...: unknown column; known: {', '.join(COLUMNS)}")
        for k in [k for k, v in wanted.items() if v == ours]:
            del wanted[k]
        wanted[_key(theirs)] = ours

    def columns_of(header: list[str]) -> dict[str, int]:
        where: dict[str, int] = {}
        for i, h in enumerate(header):
            ours = wanted.get(_key(h))  # each header cell normalised once
            if ours is not None and ours not in where:
                where[ours] = i
        return where

    it = iter(rows)
    head_rows: list[Row] = []
    parameters: list[tuple[str, dict[str, Any], Origin]] = []
    try:
        # the header is the first row naming the required columns (vendor sheets open with a title block)
        header_row: Row | None = None
        where: dict[str, int] = {}
        for row in it:
            head_rows.append(row)
            where = columns_of(row.cells)
            if all(c in where for c in REQUIRED):
                header_row = row
                break
            if len(head_rows) == 20:
                break
        if not head_rows:
            raise InputError([Diagnostic(path, 1, 1, "the file is empty: expected a header row")])
        if header_row is None:
            first = head_rows[0]
            where = columns_of(first.cells)
            missing = [c for c in REQUIRED if c not in where]
            shown = messages.clip(", ".join(messages.clip(c, 30) for c in first.cells[:30]), 300)
            raise InputError(
                [
                    Diagnostic(
                        path,
                        first.line,
                        1,
                        f"no column for {', '.join(missing)} in the header "
                        f"({shown}); name it with --column {missing[0]}=HEADER",
                    )
                ]
            )
        for i, h in enumerate(header_row.cells):
            if h.strip() and where.get(wanted.get(_key(h), "")) != i:
                used = wanted.get(_key(h))
                why = (
                    f"a second '{used}' column (the first is column {header_row.column(where[used])})"
                    if used
                    else f"not a column this importer knows; name it with --column OURS={_show(h.strip())} "
                    f"(ours: {', '.join(COLUMNS)})"
                )
                warnings.append(
                    f"{path}:{header_row.line}:{header_row.column(i)}: warning: column "
                    f"{_show(h.strip())} is not used: {why}"
                )
        seen: dict[str, int] = {}
        for row in it:
            _one_row(path, row, where, seen, parameters, errors, decimal)
            if len(parameters) > MAX_PARAMETERS:
                raise _Stop(
                    Diagnostic(
                        path,
                        row.line,
                        1,
                        f"more than {MAX_PARAMETERS:,} register rows (a profile "
                        f"holds at most {MAX_PARAMETERS:,} parameters)",
                    )
                )
    except _Stop as stop:
        raise InputError([*errors, stop.diagnostic]) from None
    if errors:
        raise InputError(errors)
    if not parameters:
        raise InputError([Diagnostic(path, head_rows[-1].line, 1, "no register rows below the header")])
    head: dict[str, Any] = {"profile": profile_id, "description": f"imported from {path}", "addressing": addressing}
    if byte_order in codec.LAYOUTS:  # the default of rows without a byte_order cell
        head["byte_order"] = byte_order
    elif byte_order:
        head["swap"] = byte_order
    return Draft(head, parameters, []), warnings


def _one_row(
    path: str,
    row: Row,
    where: dict[str, int],
    seen: dict[str, int],
    parameters: list[tuple[str, dict[str, Any], Origin]],
    errors: list[Diagnostic],
    decimal: str | None,
) -> None:
    cells = row.cells
    if not any(c.strip() for c in cells) or cells[0].lstrip().startswith("#"):
        return

    def col_of(col: str) -> int:
        i = where.get(col, 0)
        return row.column(i)

    def err(col: str, message: str) -> None:
        errors.append(Diagnostic(path, row.line, col_of(col), messages.clip_message(message)))

    texts: dict[str, str] = {}  # our column -> its cell's text, each cell read once
    for col, i in where.items():
        if i >= len(cells):
            continue
        if row.formulas and i in row.formulas:
            err(
                col,
                f"the formula {_show(row.formulas[i])} has no saved value (the file was written by a program "
                "that does not calculate): open and save it in a spreadsheet program, or enter the value",
            )
        text = cells[i].strip()
        if text[:1] == "'" and text[1:2] in _FORMULA_STARTS:  # 'profiles export csv' escapes formulas
            text = text[1:]
        texts[col] = text

    def cell(col: str) -> str:
        return texts.get(col, "")

    raw_name = cell("name")
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", raw_name).strip("_")
    if name and not _NAME_OK.match(name):
        name = f"p_{name}"
    if not name:
        err("name", "empty name")
        return
    if name in seen:
        err("name", f"'{messages.clip(name)}' is already defined on line {seen[name]}")
        return
    seen[name] = row.line
    spec = _row_spec(name, raw_name, cell, err, decimal)
    if spec is not None:
        parameters.append((name, spec, Origin(path, row.line, col_of("name"))))


class _Bad(ValueError):
    """A cell that is not what its column needs; the message says why."""


Cell = Callable[[str], str]
Err = Callable[[str, str], None]


def _row_spec(name: str, raw_name: str, cell: Cell, err: Err, decimal: str | None) -> dict[str, Any] | None:
    """One register row as a profile parameter spec; None (with the problems reported) when it cannot be."""
    spec: dict[str, Any] = {}
    desc = cell("description")
    if raw_name != name:
        desc = f"{raw_name}: {desc}" if desc else raw_name
    if desc:
        spec["description"] = desc
    type_ = _address_and_type(spec, name, cell, err)
    if type_ is None or not _layout(spec, name, type_, cell, err):
        return None
    numeric = type_ not in ("string", "bool")
    unit = cell("unit")
    if unit and numeric:
        if units.check(unit) is None:
            spec["unit"] = unit
        else:  # kept for people, not for conversions
            spec["description"] = f"{spec.get('description', name)} [{unit}]"
    if numeric:
        _quantities(spec, cell, err, decimal)
    _access_and_values(spec, type_, cell, err)
    _order_and_default(spec, type_, cell, err, decimal)
    return spec


def _address_and_type(spec: dict[str, Any], name: str, cell: Cell, err: Err) -> str | None:
    """The row's register, type and bits; None (said why) when the row cannot be a parameter."""
    address = cell("address")
    if not _ADDRESS.fullmatch(address):
        err("address", f"not a register address: {_show(address)} (a number, 0x1A2B or 1A2Bh)")
        return None
    spec["register"] = (
        int(address[2:], 16)
        if address[:2].lower() == "0x"
        else (int(address[:-1], 16) if address[-1:] in "hH" else int(address))
    )
    type_text = cell("type")
    type_ = TYPES.get(type_text.lower().replace(" ", "").replace("_", ""))
    if type_ is None:
        err(
            "type",
            f"unknown type {_show(type_text)} (known: {', '.join(sorted(set(TYPES.values())))} "
            f"and names like U16, S32, REAL, DWORD)",
        )
        return None
    bits = cell("bits")
    if type_ == "bool" and not bits:
        err("type", f"{name}: a bool needs the bit number in the 'bits' column")
        return None
    spec["type"] = type_  # bits of a 32-bit row: the profile check says a field is 16 bits, at this row
    if bits:
        if _DIGITS.fullmatch(bits):
            spec["bits"] = int(bits)
        elif re.fullmatch(r"\s*\d{1,2}\s*(\.\.|-)\s*\d{1,2}\s*", bits):
            spec["bits"] = bits
        else:
            err("bits", f"bits {_show(bits)}: a bit number (3) or a range (3..5)")
    return type_


def _layout(spec: dict[str, Any], name: str, type_: str, cell: Cell, err: Err) -> bool:
    """A string's register count and the byte order; False (said why) when the row cannot be a parameter."""
    if type_ == "string":
        n = cell("count")
        if not n:
            err("count", f"{name}: a string needs its register count in the 'count' column")
            return False
        if not _DIGITS.fullmatch(n) or not 1 <= int(n) <= 123:
            err("count", f"{name}: count {_show(n)} is not a string's register count (1 to 123)")
            return False
        spec["count"] = int(n)
    if cell("byte_order"):
        order = cell("byte_order")
        if order in codec.LAYOUTS:
            spec["byte_order"] = order
        elif order.lower() in codec.SWAPS:
            spec["swap"] = order.lower()
        else:
            err("byte_order", f"unknown byte order {_show(order)} (ABCD, CDAB, BADC, DCBA or none/byte/word/word_byte)")
    return True


def _access_and_values(spec: dict[str, Any], type_: str, cell: Cell, err: Err) -> None:
    """Access, enumeration labels, a string's encoding and padding."""
    access = cell("access")
    if access:
        a = ACCESS.get(access.lower().replace(" ", ""))
        if a is None:
            err("access", f"access {_show(access)} is not R, W or RW (read-only, write-only, read-write)")
        else:
            spec["access"] = a
    values = cell("values")
    if values:
        try:
            spec["values"] = _values(values)
        except _Bad as e:
            err("values", str(e))
    for col, choices in (("encoding", codec.ENCODINGS), ("padding", codec.PADDING)):
        v = cell(col).lower()
        if v and type_ != "string":
            err(col, f"'{col}' applies to strings only")
        elif v and v not in choices:
            err(col, f"{col} {_show(v)} is not one of {', '.join(choices)}")
        elif v:
            spec[col] = v


def _order_and_default(spec: dict[str, Any], type_: str, cell: Cell, err: Err, decimal: str | None) -> None:
    """The write stage, whether a restart is needed, and the factory default (a text, a label or a number)."""
    if cell("stage"):
        if _DIGITS.fullmatch(cell("stage")):
            spec["stage"] = int(cell("stage"))
        else:
            err("stage", f"stage {_show(cell('stage'))} is not a whole number")
    if cell("restart").lower() in ("yes", "y", "true", "1", "x"):
        spec["restart"] = True
    default = cell("default")
    if default and "default" not in spec:  # a numeric row's number (with its unit) is read with the limits
        if type_ == "string" or not re.match(r"\s*[-+.,0-9]", default):
            spec["default"] = default  # a text or a label
        else:
            try:
                spec["default"] = number(default, decimal)
            except _Bad as e:
                err("default", f"default: {e}")


def _quantities(
    spec: dict[str, Any], cell: Callable[[str], str], err: Callable[[str, str], None], decimal: str | None
) -> None:
    """Resolution, limits, range and default of a numeric row; each may carry a unit ('0.01 s', '0 to 100 %')."""
    unit: str | None = spec.get("unit")

    def value(col: str, text: str, where: str | None = None) -> int | float | None:
        """A number (with an optional unit, converted to the row's unit) or None after saying why."""
        try:
            return number(text, decimal)
        except _Bad as e:
            plain = e
        m = _QUANTITY.fullmatch(text)
        if m is None or not m["unit"]:
            err(where or col, f"{col}: {plain}")
            return None
        try:
            x = number(m["num"], decimal)
        except _Bad as e:
            err(where or col, f"{col}: {e}")
            return None
        return with_unit(col, x, m["unit"], where)

    def with_unit(col: str, x: int | float, u: str | None, where: str | None = None) -> int | float | None:
        nonlocal unit
        if not u:
            return x
        u = u.strip()
        why = units.check(u)
        if why is not None:
            err(where or col, f"{col}: {why}")
            return None
        if unit is None:  # the row had no unit: the cell says it
            unit = spec["unit"] = u
            return x
        if u == unit:
            return x
        try:
            y = units.convert(Decimal(repr(x) if isinstance(x, float) else x), u, unit)
        except ValueError as e:
            err(where or col, f"{col}: {e}")
            return None
        return int(y) if y == y.to_integral_value() and isinstance(x, int) else float(y)

    for col in ("scale", "min", "max"):
        text = cell(col)
        if text:
            v = value(col, text)
            if v is not None:
                spec[col] = v
    rng = cell("range")
    if rng:
        m = _RANGE.fullmatch(rng)
        if m is None:
            err("range", f"range {_show(rng)} is not 'LOW to HIGH' (0 to 100, 0-400.00, 0...100 %)")
        else:
            lo_u, hi_u = m["lou"] or m["hiu"], m["hiu"] or m["lou"]  # '0...100 %': the unit applies to both
            try:
                lo, hi = number(m["lo"], decimal), number(m["hi"], decimal)
            except _Bad as e:
                err("range", f"range: {e}")
            else:
                for key, x, u in (("min", lo, lo_u), ("max", hi, hi_u)):
                    v = with_unit("range", x, u)
                    if v is None:
                        continue
                    if key in spec and spec[key] != v:
                        err("range", f"range {_show(rng)}: {key} {v} differs from the {key} column's {spec[key]}")
                    spec[key] = v
    default = cell("default")
    if default and re.match(r"\s*[-+.,0-9]", default):
        v = value("default", default)
        if v is not None:
            spec["default"] = v


_NUMBER = re.compile(r"([-+]?)([0-9.,]*)((?:[eE][-+]?[0-9]+)?)")
_PLAIN_INT = re.compile(r"-?[0-9]{1,18}")


def number(text: str, decimal: str | None = None) -> int | float:
    """A number cell as manuals write it: 10, -1.5, 0x1F, 1Fh, 1e3, 0,5 and 1.000,5 (decimal comma),
    1,000 and 1,234.5 (thousands separators); _Bad when it is none, or when ``3,000`` could be either
    (``decimal``: "comma" or "point" says which mark every cell uses)."""
    t = text.strip().replace("'", "")  # 1'000 (Swiss thousands)
    if _PLAIN_INT.fullmatch(t):  # most cells: no marks to decide on
        return int(t)
    if len(t) > MAX_NUMBER:
        raise _Bad(f"a number of {len(t):,} characters; at most {MAX_NUMBER}")
    if re.fullmatch(r"0[xX][0-9A-Fa-f]{1,16}|[0-9A-Fa-f]{1,16}[hH]", t):  # hex, as manuals write limits too
        return int(t[2:], 16) if t[:2].lower() == "0x" else int(t[:-1], 16)
    if t.lower().lstrip("+-") in ("inf", "infinity", "nan", "snan"):
        raise _Bad(f"{_show(text)} is not a finite number")
    m = _NUMBER.fullmatch(t)
    if m is None or not re.search(r"[0-9]", m[2]):
        raise _Bad(f"{_show(text)} is not a number")
    sign, body, exp = m[1], m[2], m[3]
    mark = _decimal_mark(body, decimal, text)
    sep = "." if mark == "," else ","
    whole, dot, frac = body.rpartition(mark) if mark in body else (body, "", "")
    if sep in whole and not re.fullmatch(rf"[0-9]{{1,3}}(\{sep}[0-9]{{3}})+", whole):
        raise _Bad(f"{_show(text)} is not a number ('{sep}' separates groups of three digits)")
    if sep in frac or mark in frac or (dot and not frac and not whole):
        raise _Bad(f"{_show(text)} is not a number")
    plain = f"{sign}{whole.replace(sep, '') or '0'}{'.' + frac if dot else ''}{exp}"
    try:
        d = Decimal(plain)
    except InvalidOperation:
        raise _Bad(f"{_show(text)} is not a number") from None
    if not d.is_finite():
        raise _Bad(f"{_show(text)} is not a finite number")
    # by its exponent: arithmetic on 1e6999999999 (abs, a comparison) overflows Decimal's context
    if d and not -30 <= d.adjusted() < MAX_DIGITS:
        raise _Bad(f"{_show(text)} is outside the range a profile holds (1e-30 .. 1e30)")
    if d == d.to_integral_value() and not dot and not exp:
        return int(d)
    return float(d)


def _decimal_mark(body: str, decimal: str | None, text: str) -> str:
    """Which of ',' and '.' is the decimal mark of ``body`` (digits, commas, dots)."""
    if decimal == "comma":
        return ","
    if decimal == "point":
        return "."
    if "," in body and "." in body:
        return "," if body.rfind(",") > body.rfind(".") else "."  # 1.000,5 / 1,000.5: the last one
    if body.count(",") > 1:
        return "."  # 1,000,000
    if body.count(",") == 1:
        whole, _, frac = body.partition(",")
        if len(frac) == 3 and whole.lstrip("0"):
            raise _Bad(
                f"{_show(text)} is ambiguous: {whole}{frac} with a thousands separator, or "
                f"{whole}.{frac} with a decimal comma; pass --decimal-comma or --decimal-point"
            )
        return ","
    if body.count(".") > 1:
        return ","  # 1.000.000
    return "."


def _values(text: str) -> dict[str, int]:
    """'0=ramp; 1=coast' or 'ramp=0, coast=1' -> {label: raw}."""
    out: dict[str, int] = {}
    for part in re.split(r"[;,|\n]", text):
        if not part.strip():
            continue
        if "=" not in part and ":" not in part:
            raise _Bad(f"values: {_show(part.strip())} is not 'N=label'")
        a, b = (x.strip() for x in re.split(r"[=:]", part, maxsplit=1))
        if re.fullmatch(r"-?\d{1,20}", a):
            out[b] = int(a)
        elif re.fullmatch(r"-?\d{1,20}", b):
            out[a] = int(b)
        else:
            raise _Bad(f"values: {_show(part.strip())} has no number")
    return out


# ------------------------------------------------------------------------------------------- export


EXPORT_COLUMNS = (
    "name",
    "address",
    "type",
    "unit",
    "scale",
    "min",
    "max",
    "access",
    "description",
    "values",
    "bits",
    "count",
    "byte_order",
    "default",
    "encoding",
    "padding",
    "stage",
    "restart",
)
_PLAIN_NUMBER = re.compile(r"-?[0-9]+(\.[0-9]+)?([eE][-+]?[0-9]+)?")


def _safe_cell(v: object) -> object:
    """A cell a spreadsheet program will not run: text starting with = + - @ (or a tab or CR) gets a leading
    apostrophe, which 'profiles import csv' removes again; plain numbers (-10, -0.5) stay numbers."""
    if isinstance(v, str) and v[:1] in tuple(_FORMULA_CHARS) and not _PLAIN_NUMBER.fullmatch(v):
        return "'" + v
    return v


def not_exported(profile: Any) -> list[str]:
    """What a register list cannot say about ``profile`` (each a warning for 'profiles export csv')."""
    from ..model import Limits

    lost: list[str] = []
    for what, items in (
        ("identity check", profile.identity),
        ("precondition", profile.preconditions),
        ("unlock write", profile.unlock),
        ("lock write", profile.lock),
        ("commit action", profile.commit),
        ("stage wait", profile.stage_waits),
    ):
        if items:
            lost.append(f"{len(items)} {what}{'' if len(items) == 1 else 's'}")
    if profile.limits != Limits():
        lost.append("the limits")
    if profile.addressing != "address":
        lost.append(f"addressing: {profile.addressing} (the list has wire addresses; they import as they are)")
    offsets = [p.name for p in profile.parameters if p.offset]
    if offsets:
        lost.append(f"the offset of {len(offsets)} parameter{'' if len(offsets) == 1 else 's'} ({offsets[0]} ...)")
    rounding = [p.name for p in profile.parameters if p.rounding]
    if rounding:
        lost.append(f"the rounding of {len(rounding)} parameter{'' if len(rounding) == 1 else 's'}")
    return lost


def profile_to_csv(profile: Any) -> str:
    """The profile as a register list in the columns read_csv reads (wire addresses; tables as rows).
    ``not_exported`` says what it leaves out."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(EXPORT_COLUMNS)
    swaps = {v: k for k, v in codec.SWAPS.items()}
    for p in profile.parameters:
        bits = ""
        if p.mask:
            shift, width = codec.mask_shift(p.mask)
            bits = str(shift) if width == 1 else f"{shift}..{shift + width - 1}"
        swap = swaps[(p.word_order, p.byte_swap)]
        default = (
            "" if p.default is None else p.default if isinstance(p.default, str) else codec.format_decimal(p.default)
        )
        w.writerow(
            [
                _safe_cell(c)
                for c in (
                    p.name,
                    p.address,
                    p.type,
                    p.unit or "",
                    "" if p.scale == 1 else codec.format_decimal(p.scale),
                    "" if p.min is None else codec.format_decimal(p.min),
                    "" if p.max is None else codec.format_decimal(p.max),
                    p.access,
                    p.description,
                    ";".join(f"{v}={k}" for k, v in p.values),
                    bits,
                    p.count if p.is_string else "",
                    "" if swap == "none" else swap,
                    default,
                    p.encoding if p.is_string else "",
                    p.padding if p.is_string else "",
                    p.stage or "",
                    "yes" if p.restart else "",
                )
            ]
        )
    return buf.getvalue()
