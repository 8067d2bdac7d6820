"""Profile files written by the importers: one line per parameter, so a problem in the result
can be traced back to the row (or model point) it came from.

Every importer builds data (a ``Draft``) and this module alone turns it into text: each key
and value is written by ``key``/``scalar``, which leave a word plain only when it matches a
whitelist and quote everything else (YAML double quotes, every character outside the printable
set escaped), so no name or cell text can add structure. ``check`` then reads the text back and
refuses it unless it is exactly the draft's data.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from decimal import Decimal
from typing import Any

from ..errors import Diagnostic, InputError
from ..load import messages, yamlsrc
from .loader import profile_from_data
from .model import Profile

MAX_NAME = 256  # characters of a parameter, table, field or label name (YAML's keys stop at 1024)
MAX_DIGITS = 30  # digits of an integer written into a profile (registers, counts, raw values, limits)


@dataclass(frozen=True)
class Origin:
    """Where an imported parameter came from (a CSV row and cell, a model point)."""

    path: str
    line: int
    col: int = 1


@dataclass
class Draft:
    """A profile being imported: header keys, parameters and tables in source order, and their origins."""

    header: dict[str, Any]
    parameters: list[tuple[str, dict[str, Any], Origin]]
    tables: list[tuple[str, dict[str, Any], Origin]]

    def data(self) -> dict[str, Any]:
        """The profile as data: what the text must read back as."""
        out: dict[str, Any] = dict(self.header)
        if self.parameters:
            out["parameters"] = {name: spec for name, spec, _ in self.parameters}
        if self.tables:
            out["tables"] = {name: spec for name, spec, _ in self.tables}
        return out

    def problems(self) -> list[Diagnostic]:
        """Names the profile schema refuses or YAML cannot carry, and numbers no profile holds, at their origins."""
        errors: list[Diagnostic] = []
        seen: dict[tuple[str, str], Origin] = {}
        for section, items in (("parameter", self.parameters), ("table", self.tables)):
            pattern = _PARAM_NAME if section == "parameter" else _TABLE_NAME
            for name, spec, origin in items:
                why = _name_problem(name, pattern)
                if why:
                    errors.append(Diagnostic(origin.path, origin.line, origin.col, f"{section} name {why}"))
                elif (section, name) in seen:
                    first = seen[section, name]
                    errors.append(
                        Diagnostic(
                            origin.path,
                            origin.line,
                            origin.col,
                            f"{section} '{name}' is already defined at {first.path}:{first.line}:{first.col}",
                        )
                    )
                seen.setdefault((section, name), origin)
                for fname in spec.get("fields", {}) if section == "table" else ():
                    why = _name_problem(fname, _TABLE_NAME)
                    if why:
                        errors.append(Diagnostic(origin.path, origin.line, origin.col, f"{name}: field name {why}"))
                for what in _bad_values(spec):
                    errors.append(Diagnostic(origin.path, origin.line, origin.col, f"{name}: {what}"))
        return errors

    def text(self, comment: str = "") -> tuple[str, dict[int, Origin]]:
        """The profile as YAML, and the source of each generated line."""
        lines = [f"# {_comment(c)}" for c in comment.splitlines()] if comment else []
        origins: dict[int, Origin] = {}
        for k, v in self.header.items():
            lines.append(f"{key(k)}: {flow(v)}")
        for section, items in (("parameters", self.parameters), ("tables", self.tables)):
            if not items:
                continue
            lines.append(f"{section}:")
            for name, spec, origin in items:
                if section == "tables":
                    head = {k: v for k, v in spec.items() if k != "fields"}
                    lines.append(
                        f"  {key(name)}: {{{', '.join(f'{key(k)}: {flow(v)}' for k, v in head.items())}, fields: {{"
                    )
                    origins[len(lines)] = origin
                    for fname, fspec in spec["fields"].items():
                        lines.append(f"    {key(fname)}: {flow(fspec)},")
                        origins[len(lines)] = origin
                    lines.append("  }}")
                    continue
                lines.append(f"  {key(name)}: {flow(spec)}")
                origins[len(lines)] = origin
        return "\n".join(lines) + "\n", origins


_PARAM_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_.-]*\Z")  # the profile schema's propertyNames patterns
_TABLE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_-]*\Z")
_PLAIN = re.compile(r"[A-Za-z_][A-Za-z0-9_.-]*\Z")
# plain words YAML 1.1 reads as something other than text
_YAML_WORDS = {"y", "n", "yes", "no", "on", "off", "true", "false", "null"}
# YAML's printable set, less what a double-quoted scalar must escape anyway (line and paragraph separators,
# NEL and the byte-order mark are line breaks or invisible to a reader)
_SAFE_CHAR = re.compile("[ !#-\\[\\]-~\u00a0-\u2027\u202a-\ud7ff\ue000-\ufefe\uff00-\ufffd\U00010000-\U0010ffff]*\\Z")


def _name_problem(name: str, pattern: re.Pattern[str]) -> str | None:
    if len(name) > MAX_NAME:
        return f"of {len(name)} characters: at most {MAX_NAME} ({messages.clip(name, 40)})"
    if not pattern.match(name):
        allowed = "_ . -" if pattern is _PARAM_NAME else "_ -"
        return f"{messages.clipped_repr(name, 60)}: letters, digits and {allowed}, starting with a letter or '_'"
    return None


def _bad_values(v: Any) -> list[str]:
    """Numbers a profile cannot hold (not finite, too many digits) and labels too long to be keys.
    (Concrete type checks: a draft holds dicts, lists and scalars, and ABC checks cost 65,536 rows seconds.)"""
    out: list[str] = []
    stack = [v]
    while stack:
        x = stack.pop()
        t = type(x)
        if t is str or t is bool or x is None:
            continue
        if t is int:
            if abs(x) >= _INT_LIMIT:
                out.append(f"a number of more than {MAX_DIGITS} digits")
        elif t is dict:
            for k, y in x.items():
                if len(str(k)) > MAX_NAME:
                    out.append(f"the key {messages.clip(str(k), 40)} is longer than {MAX_NAME} characters")
                stack.append(y)
        elif t is list or t is tuple:
            stack.extend(x)
        elif t is float or t is Decimal:
            d = Decimal(repr(x)) if t is float else x
            if not d.is_finite():
                out.append(f"{x} is not a finite number")
            elif (d and abs(d) < _SMALLEST) or abs(d) >= _INT_LIMIT:
                out.append(f"{x} is outside the range a profile holds (1e-30 .. 1e30)")
    return out


_INT_LIMIT = 10**MAX_DIGITS
_SMALLEST = Decimal("1e-30")


def key(k: str) -> str:
    """A mapping key: plain when it is a name YAML reads as that text, else quoted."""
    if _PLAIN.match(k) and k.lower() not in _YAML_WORDS:
        return k
    return quoted(k)


def quoted(s: str) -> str:
    """``s`` as a YAML double-quoted scalar on one line: every character outside the safe set escaped."""
    if _SAFE_CHAR.match(s) and '"' not in s and "\\" not in s:
        return f'"{s}"'
    out = ['"']
    for ch in s:
        if ch in '"\\':
            out.append("\\" + ch)
        elif _SAFE_CHAR.match(ch):
            out.append(ch)
        elif ord(ch) <= 0xFF:
            out.append(f"\\x{ord(ch):02x}")
        elif ord(ch) <= 0xFFFF:
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(f"\\U{ord(ch):08x}")
    out.append('"')
    return "".join(out)


def scalar(v: Any) -> str:
    """A value as YAML: text always quoted, numbers as numbers (``1.0e-07``: YAML 1.1 needs the dot)."""
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float | Decimal):
        if not math.isfinite(v):
            raise ValueError(f"{v} is not a finite number")  # Draft.problems says where; text() never sees it
        text = repr(float(v)) if isinstance(v, float) else str(v)
        mantissa, e, exponent = text.lower().partition("e")
        if "." not in mantissa:
            mantissa += ".0"
        if e and exponent[:1] not in "+-":
            exponent = "+" + exponent
        return f"{mantissa}e{exponent}" if e else mantissa
    return quoted(str(v))


def flow(v: Any) -> str:
    """A value in YAML flow style; registers in hex like the manuals."""
    if isinstance(v, dict):
        return "{" + ", ".join(f"{key(str(k))}: {_hex(v[k]) if k == 'register' else flow(v[k])}" for k in v) + "}"
    if isinstance(v, list | tuple):
        return "[" + ", ".join(flow(x) for x in v) + "]"
    return scalar(v)


def _hex(v: Any) -> str:
    return f"0x{v:04X}" if isinstance(v, int) and not isinstance(v, bool) and v >= 0 else scalar(v)


def _comment(c: str) -> str:
    """A comment line with every character YAML would not read as comment text escaped."""
    return quoted(c)[1:-1]


def _same(a: Any, b: Any) -> bool:
    """Data equal as YAML reads it back (floats are read as exact decimals)."""
    if isinstance(a, dict):
        return isinstance(b, dict) and list(map(str, a)) == list(map(str, b)) and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return isinstance(b, list | tuple) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float):
        return not isinstance(b, bool) and isinstance(b, int | float | Decimal) and Decimal(repr(a)) == b
    return (type(a) is type(b) and a == b) or (isinstance(a, int) and isinstance(b, Decimal) and a == b)


def check(draft: Draft, out_path: str, comment: str = "") -> tuple[str, Profile]:
    """The draft's text, loaded as a profile; its problems point at the source rows."""
    problems = draft.problems()
    if problems:
        raise InputError(problems)
    text, origins = draft.text(comment)
    try:
        data, src = yamlsrc.load(out_path, text)
        if not _same(draft.data(), data):  # the writer's promise, checked: nothing added, nothing lost
            raise InputError(
                [
                    Diagnostic(
                        out_path,
                        1,
                        1,
                        "internal error: the written profile does not read back as imported; please report this input",
                    )
                ]
            )
        prof = profile_from_data(out_path, text, data, src)
    except InputError as e:
        raise InputError(traced(e.diagnostics, origins, out_path)) from None
    return text, prof


def traced(diagnostics: Sequence[Diagnostic], origins: Mapping[int, Origin], out_path: str) -> list[Diagnostic]:
    out = []
    for d in diagnostics:
        o = origins.get(d.line) if os.path.abspath(d.path) == os.path.abspath(out_path) else None
        if o is None:
            out.append(d)
            continue
        # "... (line N)" names another generated line: say its source line instead
        message = re.sub(
            r"\bline (\d+)", lambda m: f"line {origins[int(m[1])].line}" if int(m[1]) in origins else m[0], d.message
        )
        out.append(Diagnostic(o.path, o.line, o.col, message))
    return out
