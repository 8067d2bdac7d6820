"""YAML (and JSON) loading that remembers where every key and value came from.

PyYAML's node tree carries marks; we build plain Python values from it ourselves so that:
  * only safe, standard tags are accepted (no Python object tags),
  * decimal numbers become ``Decimal`` built from the text (``10.005`` stays exact),
  * duplicate keys are errors, not silent overwrites,
  * every value and key has a (line, col), so schema and semantic errors print
    ``FILE:LINE:COL: error: message``.
"""

from __future__ import annotations

import difflib
import json
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation
from typing import Any

import jsonschema
import yaml

from .diagnostics import Diagnostic, InputError

MAX_FILE_BYTES = 4 * 1024 * 1024  # a recipe or profile is kilobytes; refuse runaway files early

Path_ = tuple[str | int, ...]

_STD = "tag:yaml.org,2002:"
_SCALAR_TAGS = {f"{_STD}{t}" for t in ("str", "int", "float", "bool", "null", "timestamp")}


@dataclass
class Source:
    """Positions of one loaded document: path tuple -> (line, col), 1-based."""

    path: str
    values: dict[Path_, tuple[int, int]] = field(default_factory=dict)
    keys: dict[Path_, tuple[int, int]] = field(default_factory=dict)

    def pos(self, at: Path_, *, key: bool = False) -> tuple[int, int]:
        """Position of the value (or key) at ``at``; falls back to the nearest parent."""
        table = self.keys if key else self.values
        p = tuple(at)
        while p:
            if p in table:
                return table[p]
            if p in self.values:
                return self.values[p]
            p = p[:-1]
        return self.values.get((), (1, 1))

    def error(self, at: Path_, message: str, *, key: bool = False) -> Diagnostic:
        line, col = self.pos(at, key=key)
        return Diagnostic(self.path, line, col, message)


def _mark(node: yaml.Node) -> tuple[int, int]:
    return node.start_mark.line + 1, node.start_mark.column + 1


class _Builder:
    def __init__(self, src: Source) -> None:
        self.src = src
        self.errors: list[Diagnostic] = []
        self._resolver = yaml.SafeLoader  # for implicit scalar resolution helpers

    def err(self, node: yaml.Node, message: str) -> None:
        line, col = _mark(node)
        self.errors.append(Diagnostic(self.src.path, line, col, message))

    def build(self, node: yaml.Node, at: Path_) -> Any:
        self.src.values[at] = _mark(node)
        if isinstance(node, yaml.MappingNode):
            if node.tag != f"{_STD}map":
                self.err(node, f"tag {node.tag!r} is not allowed")
                return None
            out: dict[str, Any] = {}
            for knode, vnode in node.value:
                if knode.tag == f"{_STD}merge":
                    self.err(knode, "YAML merge keys ('<<') are not supported; use 'extends'")
                    continue
                if not isinstance(knode, yaml.ScalarNode):
                    self.err(knode, "a mapping key must be a plain scalar")
                    continue
                key = str(knode.value)
                if key in out:
                    line, _ = self.src.keys[(*at, key)]
                    self.err(knode, f"duplicate key '{key}' (first at line {line})")
                    continue
                self.src.keys[(*at, key)] = _mark(knode)
                out[key] = self.build(vnode, (*at, key))
            return out
        if isinstance(node, yaml.SequenceNode):
            if node.tag != f"{_STD}seq":
                self.err(node, f"tag {node.tag!r} is not allowed")
                return None
            return [self.build(v, (*at, i)) for i, v in enumerate(node.value)]
        assert isinstance(node, yaml.ScalarNode)
        return self.scalar(node)

    def scalar(self, node: yaml.ScalarNode) -> Any:
        tag = node.tag
        if tag not in _SCALAR_TAGS:
            self.err(node, f"tag {tag!r} is not allowed")
            return None
        text = node.value
        if tag == f"{_STD}str" or tag == f"{_STD}timestamp":
            return str(text)
        if tag == f"{_STD}null":
            return None
        if tag == f"{_STD}bool":
            return text.lower() in ("true", "yes", "on", "y")
        if tag == f"{_STD}int":
            try:
                return _int(text)
            except (ValueError, TypeError):
                self.err(node, f"not an integer: {text!r}")
                return None
        # float: keep the exact decimal text
        t = text.replace("_", "")
        if t.lower() in (".inf", "+.inf", "-.inf", ".nan"):
            self.err(node, f"{text} is not a finite number")
            return None
        try:
            return Decimal(t)
        except InvalidOperation:
            self.err(node, f"not a number: {text!r}")
            return None


def _int(text: str) -> int:
    """YAML 1.1 integers as PyYAML resolves them: 0x1F, 0o17 / 017, 0b101, 1_000, +5."""
    t = text.replace("_", "")
    sign = -1 if t.startswith("-") else 1
    t = t.lstrip("+-")
    if t.startswith(("0x", "0X")):
        return sign * int(t[2:], 16)
    if t.startswith(("0b", "0B")):
        return sign * int(t[2:], 2)
    if t.startswith(("0o", "0O")):
        return sign * int(t[2:], 8)
    if ":" in t:  # sexagesimal 1:30 -> 90
        total = 0
        for part in t.split(":"):
            total = total * 60 + int(part)
        return sign * total
    if len(t) > 1 and t.startswith("0"):
        return sign * int(t, 8)
    return sign * int(t)


def read_text(path: str) -> str:
    """Read a UTF-8 file; problems become diagnostics."""
    try:
        size = os.path.getsize(path)
        if size > MAX_FILE_BYTES:
            raise InputError(
                [Diagnostic(path, 1, 1, f"file too large ({size / 1e6:.1f} MB; limit "
                                       f"{MAX_FILE_BYTES // (1024 * 1024)} MiB)")]
            )
        with open(path, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        raise InputError([Diagnostic(path, 0, 0, "no such file")]) from None
    except IsADirectoryError:
        raise InputError([Diagnostic(path, 0, 0, "is a directory, not a file")]) from None
    except OSError as e:
        raise InputError([Diagnostic(path, 0, 0, f"cannot read: {e.strerror}")]) from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        before = data[: e.start]
        line = before.count(b"\n") + 1
        col = e.start - (before.rfind(b"\n") + 1) + 1
        raise InputError(
            [Diagnostic(path, line, col, f"not UTF-8 text (byte 0x{data[e.start]:02x})")]
        ) from None


def load(path: str | os.PathLike[str], text: str | None = None) -> tuple[Any, Source]:
    """Load one YAML (or JSON, a subset) document. Raises InputError."""
    p = os.fspath(path)
    if text is None:
        text = read_text(p)
    src = Source(p)
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        line, col = (mark.line + 1, mark.column + 1) if mark else (1, 1)
        raise InputError([Diagnostic(p, line, col, f"invalid YAML: {e.problem or e.context}")]) from None
    except yaml.YAMLError as e:
        raise InputError([Diagnostic(p, 1, 1, f"invalid YAML: {e}")]) from None
    if node is None:
        raise InputError([Diagnostic(p, 1, 1, "the file is empty")])
    b = _Builder(src)
    value = b.build(node, ())
    if b.errors:
        raise InputError(b.errors)
    return value, src


# ---- JSON Schema with positions ---------------------------------------------------------


def _is_number(_checker: Any, instance: Any) -> bool:
    return isinstance(instance, int | float | Decimal) and not isinstance(instance, bool)


def _is_integer(_checker: Any, instance: Any) -> bool:
    if isinstance(instance, bool):
        return False
    if isinstance(instance, int):
        return True
    return isinstance(instance, Decimal) and instance == instance.to_integral_value()


_TYPE_CHECKER = jsonschema.Draft202012Validator.TYPE_CHECKER.redefine_many(
    {"number": _is_number, "integer": _is_integer}
)
_Validator = jsonschema.validators.extend(  # type: ignore[no-untyped-call]
    jsonschema.Draft202012Validator, type_checker=_TYPE_CHECKER
)


def schema(name: str) -> dict[str, Any]:
    """A bundled JSON Schema by name ('profile', 'recipe', 'inventory', 'plan', 'report')."""
    here = os.path.join(os.path.dirname(__file__), "schemas", f"{name}.schema.json")
    with open(here, encoding="utf-8") as f:
        data: dict[str, Any] = json.load(f)
    return data


def validate(value: Any, schema_name: str, src: Source) -> list[Diagnostic]:
    """All schema errors of ``value``, each at the position of the offending key or value."""
    validator = _Validator(schema(schema_name))
    out: list[Diagnostic] = []
    for err in validator.iter_errors(value):
        out.extend(_explain(err, src))
    return out


def _leaves(err: jsonschema.ValidationError) -> Iterator[jsonschema.ValidationError]:
    """For oneOf/anyOf, the errors of the most plausible branch (deepest path)."""
    if err.validator in ("oneOf", "anyOf") and err.context:
        best = max(err.context, key=lambda e: (len(e.absolute_path), -len(list(e.context or []))))
        depth = len(best.absolute_path)
        if depth > len(err.absolute_path):
            yield from _leaves(best)
            return
    yield err


def _where(err: jsonschema.ValidationError) -> str:
    parts = [str(p) if isinstance(p, str) else f"[{p}]" for p in err.absolute_path]
    return ".".join(parts).replace(".[", "[")


def _explain(err: jsonschema.ValidationError, src: Source) -> Iterable[Diagnostic]:
    for e in _leaves(err):
        at: Path_ = tuple(e.absolute_path)
        where = _where(e)
        prefix = f"{where}: " if where else ""
        if e.validator == "additionalProperties" and isinstance(e.instance, Mapping):
            sch: Any = e.schema
            allowed = list((sch.get("properties") or {}).keys())
            patterns = list((sch.get("patternProperties") or {}).keys())
            import re

            for k in e.instance:
                if k in allowed or any(re.search(p, k) for p in patterns):
                    continue
                hint = difflib.get_close_matches(k, allowed, n=1)
                msg = f"unknown key '{k}'" + (f" in {where}" if where else "")
                msg += f"; did you mean '{hint[0]}'?" if hint else (
                    f" (expected one of: {', '.join(allowed)})" if allowed else "")
                yield src.error((*at, k), msg, key=True)
        elif e.validator == "required":
            yield src.error(at, f"{prefix}{e.message}")
        elif e.validator == "type":
            yield src.error(at, f"{prefix}expected {_type_words(e.validator_value)}, got {_describe(e.instance)}")
        elif e.validator == "enum":
            vv: Any = e.validator_value
            options = ", ".join(str(v) for v in vv)
            yield src.error(at, f"{prefix}{_describe(e.instance)} is not one of: {options}")
        elif e.validator in ("oneOf", "anyOf"):
            yield src.error(at, f"{prefix}{_describe(e.instance)} is not valid here")
        elif e.validator == "propertyNames":
            yield src.error(at, f"{prefix}{e.message}", key=True)
        else:
            yield src.error(at, f"{prefix}{e.message}")


def _type_words(t: Any) -> str:
    names = {"object": "a mapping", "array": "a list", "string": "a string", "number": "a number",
             "integer": "an integer", "boolean": "true or false", "null": "nothing"}
    if isinstance(t, list):
        return " or ".join(names.get(str(x), str(x)) for x in t)
    return names.get(t, str(t))


def _describe(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if v is None:
        return "nothing (null)"
    if isinstance(v, Mapping):
        return "a mapping"
    if isinstance(v, Sequence) and not isinstance(v, str):
        return "a list"
    if isinstance(v, str):
        return repr(v)
    return str(v)


def closest(name: str, choices: Iterable[str]) -> str | None:
    hits = difflib.get_close_matches(name, list(choices), n=1, cutoff=0.6)
    return hits[0] if hits else None
