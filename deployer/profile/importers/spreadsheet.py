"""Import a vendor's register list (CSV, as exported from the manual's spreadsheet) as a profile,
and write a profile back as such a list.

Columns are found by header name (case and spaces ignored); ``columns`` maps our names to
other headers. Every problem points at its cell: FILE:LINE:COL.

    name, address, type, unit, scale, min, max, access, description   (+ bits, count, values, byte_order)
"""

from __future__ import annotations

import csv
import io
import re
from collections.abc import Callable, Mapping
from decimal import Decimal, InvalidOperation
from typing import Any

from ...load import yamlsrc
from ...load.diagnostics import Diagnostic, InputError, UsageError
from .. import codec, units
from ..emit import Draft, Origin
from ..loader import parse_register
from ..model import Profile

# our column -> headers vendors use for it (lower case, spaces and underscores removed)
COLUMNS: dict[str, tuple[str, ...]] = {
    "name": ("name", "parameter", "parametername", "tag", "symbol", "point"),
    "address": ("address", "register", "addr", "registeraddress", "reg", "modbusaddress"),
    "type": ("type", "datatype", "format", "dtype"),
    "unit": ("unit", "units", "uom"),
    "scale": ("scale", "resolution", "factor", "multiplier", "gain"),
    "min": ("min", "minimum", "low", "rangemin"),
    "max": ("max", "maximum", "high", "rangemax"),
    "access": ("access", "rw", "r/w", "mode", "accesstype"),
    "description": ("description", "desc", "comment", "label"),
    "bits": ("bits", "bit"),
    "count": ("count", "registers", "length", "size", "words"),
    "values": ("values", "enum", "enumeration", "options"),
    "byte_order": ("byteorder", "layout", "endianness", "swap"),
    "default": ("default", "defaultvalue", "initial"),
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
_DIGITS = re.compile(r"[0-9]+")  # str.isdigit() also accepts digits of other scripts


def _key(header: str) -> str:
    return re.sub(r"[\s_]+", "", header.strip().lower())


def _cell_starts(line: str, delimiter: str) -> list[int]:
    """1-based column where each cell of a physical CSV line starts (quotes respected)."""
    starts, quoted = [1], False
    for i, ch in enumerate(line):
        if ch == '"':
            quoted = not quoted
        elif ch == delimiter and not quoted:
            starts.append(i + 2)
    return starts


Row = tuple[int, list[str], list[int]]  # the line (sheet row) it starts on, its cells, each cell's column


def read_csv(path: str, *, profile_id: str, columns: Mapping[str, str] | None = None,
             addressing: str = "address", delimiter: str | None = None, byte_order: str | None = None) -> Draft:
    """The register list at ``path`` as a Draft profile; InputError with every bad cell at once."""
    text = yamlsrc.read_text(path)
    if delimiter is None:
        try:
            delimiter = csv.Sniffer().sniff(text[:4096], delimiters=",;\t").delimiter
        except csv.Error:
            delimiter = ","
    physical = io.StringIO(text, newline="").readlines()  # lines as the csv module counts them (\r too)
    reader = csv.reader(io.StringIO(text, newline=""), delimiter=delimiter)
    rows: list[Row] = []
    prev = 0
    try:
        for cells in reader:
            rows.append((prev + 1, cells, _cell_starts(physical[prev], delimiter)))
            prev = reader.line_num  # a quoted cell may span lines
    except csv.Error as e:
        raise InputError([Diagnostic(path, reader.line_num, 1, f"not a CSV row: {e}")]) from None
    return _draft(path, rows, profile_id=profile_id, columns=columns, addressing=addressing, byte_order=byte_order)


def read_xlsx(path: str, *, profile_id: str, sheet: str | None = None, columns: Mapping[str, str] | None = None,
              addressing: str = "address", byte_order: str | None = None) -> Draft:
    """A register list in an Excel workbook (openpyxl, the 'xlsx' extra); problems point at FILE[SHEET]:ROW:COLUMN."""
    try:
        import openpyxl
    except ImportError:
        raise UsageError("reading .xlsx needs openpyxl: pip install 'modbus-deployer[xlsx]'") from None
    try:
        book = openpyxl.load_workbook(path, read_only=True, data_only=True)
    except Exception as e:  # openpyxl raises its own, zipfile's and XML errors for files it cannot read
        raise InputError([Diagnostic(path, 0, 0, f"cannot read the workbook: {e}")]) from None
    if sheet is not None and sheet not in book.sheetnames:
        raise InputError([Diagnostic(path, 0, 0, f"no sheet '{sheet}' (sheets: {', '.join(book.sheetnames)})")])
    ws = book[sheet] if sheet is not None else book.worksheets[0]
    rows: list[Row] = []
    for r, values in enumerate(ws.iter_rows(values_only=True), 1):
        cells = [_cell_text(v) for v in values]
        rows.append((r, cells, list(range(1, len(cells) + 1))))
    book.close()
    return _draft(f"{path}[{ws.title}]", rows, profile_id=profile_id, columns=columns, addressing=addressing,
                  byte_order=byte_order)


def _cell_text(v: object) -> str:
    if v is None:
        return ""
    if isinstance(v, float) and v.is_integer():
        return str(int(v))
    return str(v)


def _draft(path: str, rows: list[Row], *, profile_id: str, columns: Mapping[str, str] | None, addressing: str,
           byte_order: str | None) -> Draft:
    errors: list[Diagnostic] = []
    if not rows:
        raise InputError([Diagnostic(path, 1, 1, "the file is empty: expected a header row")])
    wanted = {k: tuple(_key(h) for h in v) for k, v in COLUMNS.items()}
    if byte_order and byte_order not in codec.LAYOUTS and byte_order not in codec.SWAPS:
        raise InputError([Diagnostic(path, 1, 1, f"--byte-order {byte_order}: expected one of "
                                                 f"{', '.join([*codec.LAYOUTS, *codec.SWAPS])}")])
    for ours, theirs in (columns or {}).items():
        if ours not in COLUMNS:
            raise InputError([Diagnostic(path, 1, 1, f"--column {ours}=...: unknown column; known: "
                                                     f"{', '.join(COLUMNS)}")])
        wanted[ours] = (_key(theirs),)

    def columns_of(header: list[str]) -> dict[str, int]:
        where: dict[str, int] = {}
        for i, h in enumerate(header):
            for ours, keys in wanted.items():
                if _key(h) in keys and ours not in where:
                    where[ours] = i
        return where

    # the header is the first row naming the required columns (vendor sheets open with a title block)
    first = next((i for i, (_, cells, _) in enumerate(rows[:20]) if all(c in columns_of(cells) for c in REQUIRED)), 0)
    header = rows[first][1]
    where = columns_of(header)
    missing = [c for c in REQUIRED if c not in where]
    if missing:
        raise InputError([Diagnostic(path, 1, 1, f"no column for {', '.join(missing)} in the header "
                                                 f"({', '.join(header)}); name it with --column {missing[0]}=HEADER")])
    parameters: list[tuple[str, dict[str, Any], Origin]] = []
    seen: dict[str, int] = {}
    for line, row, starts in rows[first + 1:]:
        if not any(c.strip() for c in row) or row[0].lstrip().startswith("#"):
            continue

        def cell(col: str, row: list[str] = row) -> str:
            i = where.get(col)
            return row[i].strip() if i is not None and i < len(row) else ""

        def err(col: str, message: str, line: int = line, starts: list[int] = starts) -> None:
            i = where.get(col, 0)
            errors.append(Diagnostic(path, line, starts[i] if i < len(starts) else 1, message))

        raw_name = cell("name")
        name = re.sub(r"[^A-Za-z0-9_.-]+", "_", raw_name).strip("_")
        if name and not _NAME_OK.match(name):
            name = f"p_{name}"
        if not name:
            err("name", "empty name")
            continue
        if name in seen:
            err("name", f"'{name}' is already defined on line {seen[name]}")
            continue
        seen[name] = line
        spec = _row_spec(name, raw_name, cell, err)
        if spec is None:
            continue
        parameters.append((name, spec, Origin(path, line, starts[where["name"]] if where["name"] < len(starts) else 1)))
    if errors:
        raise InputError(errors)
    if not parameters:
        raise InputError([Diagnostic(path, 1, 1, "no register rows below the header")])
    head: dict[str, Any] = {"profile": profile_id, "description": f"imported from {path}", "addressing": addressing}
    if byte_order in codec.LAYOUTS:  # the default of rows without a byte_order cell
        head["byte_order"] = byte_order
    elif byte_order:
        head["swap"] = byte_order
    return Draft(head, parameters, [])


def _row_spec(name: str, raw_name: str, cell: Callable[[str], str], err: Callable[[str, str], None]
              ) -> dict[str, Any] | None:
    """One register row as a profile parameter spec; None (with the problems reported) when it cannot be."""
    spec: dict[str, Any] = {}
    desc = cell("description")
    if raw_name != name:
        desc = f"{raw_name}: {desc}" if desc else raw_name
    if desc:
        spec["description"] = desc
    try:
        spec["register"] = parse_register(cell("address"))
    except (ValueError, IndexError):
        err("address", f"not a register address: '{cell('address')}'")
        return None
    type_text = cell("type")
    type_ = TYPES.get(type_text.lower().replace(" ", "").replace("_", ""))
    if type_ is None:
        err("type", f"unknown type '{type_text}' (known: {', '.join(sorted(set(TYPES.values())))} "
                    f"and names like U16, S32, REAL, DWORD)")
        return None
    bits = cell("bits")
    if type_ == "bool" and not bits:
        err("type", f"{name}: a bool needs the bit number in the 'bits' column")
        return None
    spec["type"] = type_  # bits of a 32-bit row: the profile check says a field is 16 bits, at this row
    if bits:
        spec["bits"] = int(bits) if _DIGITS.fullmatch(bits) else bits
    if type_ == "string":
        n = cell("count")
        if not _DIGITS.fullmatch(n) or int(n) < 1:
            err("count", f"{name}: a string needs its register count in the 'count' column")
            return None
        spec["count"] = int(n)
    if cell("byte_order"):
        order = cell("byte_order")
        if order in codec.LAYOUTS:
            spec["byte_order"] = order
        elif order.lower() in codec.SWAPS:
            spec["swap"] = order.lower()
        else:
            err("byte_order", f"unknown byte order '{order}' (ABCD, CDAB, BADC, DCBA or none/byte/word/word_byte)")
    unit = cell("unit")
    if unit and type_ != "string":
        if units.check(unit) is None:
            spec["unit"] = unit
        else:  # kept for people, not for conversions
            spec["description"] = f"{spec.get('description', name)} [{unit}]"
    for col in ("scale", "min", "max"):
        v = cell(col)
        if not v or type_ == "string":
            continue
        try:
            spec[col] = _number(v)
        except InvalidOperation:
            err(col, f"{col} '{v}' is not a number")
    access = cell("access")
    if access:
        a = ACCESS.get(access.lower().replace(" ", ""))
        if a is None:
            err("access", f"access '{access}' is not R, W or RW (read-only, write-only, read-write)")
        else:
            spec["access"] = a
    values = cell("values")
    if values:
        try:
            spec["values"] = _values(values)
        except ValueError as e:
            err("values", str(e))
    for col, choices in (("encoding", codec.ENCODINGS), ("padding", codec.PADDING)):
        v = cell(col).lower()
        if v and type_ != "string":
            err(col, f"'{col}' applies to strings only")
        elif v and v not in choices:
            err(col, f"{col} '{v}' is not one of {', '.join(choices)}")
        elif v:
            spec[col] = v
    if cell("stage"):
        if _DIGITS.fullmatch(cell("stage")):
            spec["stage"] = int(cell("stage"))
        else:
            err("stage", f"stage '{cell('stage')}' is not a number")
    if cell("restart").lower() in ("yes", "y", "true", "1", "x"):
        spec["restart"] = True
    default = cell("default")
    if default:
        try:
            spec["default"] = default if type_ == "string" else _number(default)
        except InvalidOperation:
            spec["default"] = default  # a label
    return spec

def _number(text: str) -> int | float:
    if re.fullmatch(r"0[xX][0-9A-Fa-f]+|[0-9A-Fa-f]+[hH]", text):  # hex, as manuals write limits too
        return parse_register(text)
    d = Decimal(text.replace(",", ".") if text.count(",") == 1 and "." not in text else text)
    return int(d) if d == d.to_integral_value() and "." not in text and "e" not in text.lower() else float(d)


def _values(text: str) -> dict[str, int]:
    """'0=ramp; 1=coast' or 'ramp=0, coast=1' -> {label: raw}."""
    out: dict[str, int] = {}
    for part in re.split(r"[;,|]", text):
        if not part.strip():
            continue
        if "=" not in part and ":" not in part:
            raise ValueError(f"values: '{part.strip()}' is not 'N=label'")
        a, b = (x.strip() for x in re.split(r"[=:]", part, maxsplit=1))
        if re.fullmatch(r"-?\d+", a):
            out[b] = int(a)
        elif re.fullmatch(r"-?\d+", b):
            out[a] = int(b)
        else:
            raise ValueError(f"values: '{part.strip()}' has no number")
    return out


EXPORT_COLUMNS = ("name", "address", "type", "unit", "scale", "min", "max", "access", "description", "values",
                  "bits", "count", "byte_order", "default", "encoding", "padding", "stage", "restart")


def profile_to_csv(profile: Profile) -> str:
    """The profile as a register list in the columns read_csv reads (wire addresses; tables as rows)."""
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
        default = "" if p.default is None else p.default if isinstance(p.default, str) else codec.format_decimal(
            p.default)
        w.writerow([p.name, p.address, p.type, p.unit or "",
                    "" if p.scale == 1 else codec.format_decimal(p.scale),
                    "" if p.min is None else codec.format_decimal(p.min),
                    "" if p.max is None else codec.format_decimal(p.max),
                    p.access, p.description, ";".join(f"{v}={k}" for k, v in p.values), bits,
                    p.count if p.is_string else "", "" if swap == "none" else swap, default,
                    p.encoding if p.is_string else "", p.padding if p.is_string else "", p.stage or "",
                    "yes" if p.restart else ""])
    return buf.getvalue()
