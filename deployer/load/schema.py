"""JSON Schema checks of loaded files, each error at the position of its key or value."""

from __future__ import annotations

import difflib
import json
import os
import re
from collections.abc import Iterable, Iterator, Mapping, Sequence
from decimal import Decimal
from functools import cache
from typing import TYPE_CHECKING, Any

from ..errors import Diagnostic
from .messages import MAX_ECHO, clip, clipped_repr
from .yamlsrc import Path_, Source

if TYPE_CHECKING:
    import jsonschema


def _is_number(_checker: Any, instance: Any) -> bool:
    return isinstance(instance, int | float | Decimal) and not isinstance(instance, bool)


def _is_integer(_checker: Any, instance: Any) -> bool:
    if isinstance(instance, bool):
        return False
    if isinstance(instance, int):
        return True
    return isinstance(instance, Decimal) and instance == instance.to_integral_value()


def document_of(data: object) -> str | None:
    """Which deployer document a file's ``schema`` member names: "plan" (``deployer.plan/N``), "fleetplan"
    (``deployer.fleetplan/N``), "report" (``deployer.report/N``), else None (the other files are told by their
    keys)."""
    kind = str(data.get("schema", "")) if isinstance(data, dict) else ""
    return next((k for k in ("plan", "fleetplan", "report") if kind.startswith(f"deployer.{k}/")), None)


@cache
def schema(name: str) -> dict[str, Any]:
    """A bundled JSON Schema by name ('profile', 'recipe', 'inventory', 'plan', 'report').

    Cached: callers must not modify it.
    """
    here = os.path.join(os.path.dirname(os.path.dirname(__file__)), "schemas", f"{name}.schema.json")
    with open(here, encoding="utf-8") as f:
        data: dict[str, Any] = json.load(f)
    return data


@cache
def validator(name: str) -> jsonschema.protocols.Validator:
    """The validator of a bundled schema, built once per process (building one costs milliseconds)."""
    import jsonschema  # only commands that check files pay for importing it

    checker = jsonschema.Draft202012Validator.TYPE_CHECKER.redefine_many({"number": _is_number, "integer": _is_integer})
    cls = jsonschema.validators.extend(
        jsonschema.Draft202012Validator,  # type: ignore[no-untyped-call]
        type_checker=checker,
    )
    v: jsonschema.protocols.Validator = cls(schema(name))
    return v


@cache
def _fast_validator(name: str) -> Any:
    """jsonschema-rs's validator of a bundled schema, or None when the package is missing."""
    try:
        import jsonschema_rs
    except ImportError:  # pragma: no cover - a declared dependency; still usable without it
        return None
    return jsonschema_rs.validator_for(schema(name))


def is_valid(value: Any, schema_name: str) -> bool | None:
    """jsonschema-rs's verdict (about 100x faster than jsonschema); None when it cannot say."""
    fast = _fast_validator(schema_name)
    if fast is None:
        return None
    try:
        return bool(fast.is_valid(value))
    except Exception:  # values it cannot convert: let jsonschema decide
        return None


def validate(value: Any, schema_name: str, src: Source) -> list[Diagnostic]:
    """All schema errors of ``value``, each at the position of the offending key or value.

    A valid document (the common case) is confirmed by jsonschema-rs alone; jsonschema (and
    its precise, positioned messages) runs only on documents that have errors.
    """
    if is_valid(value, schema_name):
        return []
    out: list[Diagnostic] = []
    for err in validator(schema_name).iter_errors(value):
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
            for k in e.instance:
                if k in allowed or any(re.search(p, k) for p in patterns):
                    continue
                hint = difflib.get_close_matches(k, allowed, n=1)
                msg = f"unknown key '{clip(k)}'" + (f" in {where}" if where else "")
                msg += (
                    f"; did you mean '{hint[0]}'?"
                    if hint
                    else (f" (expected one of: {', '.join(allowed)})" if allowed else "")
                )
                yield src.error((*at, k), msg, key=True)
        elif e.validator == "required":
            yield src.error(at, f"{prefix}{_clip_message(e)}")
        elif e.validator == "type":
            yield src.error(at, f"{prefix}expected {_type_words(e.validator_value)}, got {_describe(e.instance)}")
        elif e.validator == "enum":
            vv: Any = e.validator_value
            options = ", ".join(str(v) for v in vv)
            yield src.error(at, f"{prefix}{_describe(e.instance)} is not one of: {options}")
        elif e.validator in ("oneOf", "anyOf"):
            yield src.error(at, f"{prefix}{_describe(e.instance)} is not valid here")
        elif e.validator == "propertyNames":
            yield src.error(at, f"{prefix}{_clip_message(e)}", key=True)
        else:
            yield src.error(at, f"{prefix}{_clip_message(e)}")


def _clip_message(e: jsonschema.ValidationError) -> str:
    """jsonschema's message with the offending value cut (it repeats the value whole)."""
    whole = repr(e.instance)
    if len(whole) > MAX_ECHO and whole in e.message:
        return e.message.replace(whole, clip(whole))
    return clip(e.message, 300)


def _type_words(t: Any) -> str:
    names = {
        "object": "a mapping",
        "array": "a list",
        "string": "a string",
        "number": "a number",
        "integer": "an integer",
        "boolean": "true or false",
        "null": "nothing",
    }
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
        return clipped_repr(v)
    return clip(str(v))
