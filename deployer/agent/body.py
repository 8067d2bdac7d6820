"""A request's JSON body, checked before a handler sees it: every malformed body is a 400 that names what is wrong.

Refused: bytes that are not UTF-8 or not JSON; ``NaN``, ``Infinity`` and numbers beyond a float (JSON has no such
numbers; Python's parser takes them); nesting deeper than ``MAX_DEPTH`` (the parser would recurse; at 100,000
levels it gives up with a RecursionError); anything but an object; and anything the route's request schema in
``openapi.json`` does not allow (a key it does not know, a value of the wrong type or range), each error with
the key it is at. The route's schema is the one the API document publishes, so the document and the check agree.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator
from functools import cache
from typing import TYPE_CHECKING, Any

from aiohttp import web

from ..load.messages import clip
from .model import ApiError

if TYPE_CHECKING:
    import jsonschema

BODY = "deployer.body"  # where the request carries its body once checked (server._bind puts it there)
MAX_DEPTH = 32  # the API's bodies nest 3 levels; a saved plan in a body about 8

# keys earlier clients sent that the agent no longer takes, and why
GONE = {"client": "the agent knows who sends a request from its credential; a client no longer names itself"}


def _constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number JSON allows")


def _float(text: str) -> float:
    v = float(text)
    if not math.isfinite(v):
        raise ValueError(f"{clip(text, 40)} is beyond the numbers the agent takes")
    return v


def parse(raw: bytes) -> dict[str, Any]:
    """The body as a JSON object, or ApiError (400) naming what is wrong; an empty body is ``{}``."""
    if not raw.strip():
        return {}
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ApiError("usage", f"the request body is not UTF-8 text (byte {e.start})", status=400) from None
    try:
        data = json.loads(text, parse_constant=_constant, parse_float=_float)
    except RecursionError:
        raise ApiError("usage", f"the request body nests deeper than {MAX_DEPTH} levels", status=400) from None
    except json.JSONDecodeError as e:
        raise ApiError(
            "usage", f"the request body is not JSON: {e.msg} at line {e.lineno} column {e.colno}", status=400
        ) from None
    except ValueError as e:  # a constant or number refused above
        raise ApiError("usage", f"the request body is not JSON the agent takes: {e}", status=400) from None
    if not isinstance(data, dict):
        raise ApiError("usage", "the request body must be a JSON object ({...})", status=400)
    if _depth(data) > MAX_DEPTH:
        raise ApiError("usage", f"the request body nests deeper than {MAX_DEPTH} levels", status=400)
    return data


def _depth(value: Any) -> int:
    """How deeply ``value`` nests (iteratively: the parser's own limit bounds it at about a thousand)."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        v, d = stack.pop()
        if isinstance(v, dict | list):
            deepest = max(deepest, d)
            stack.extend((x, d + 1) for x in (v.values() if isinstance(v, dict) else v))
    return deepest


@cache
def _document() -> dict[str, Any]:
    with open(os.path.join(os.path.dirname(__file__), "openapi.json"), encoding="utf-8") as f:
        doc: dict[str, Any] = json.load(f)
    return doc


@cache
def _validator(path: str, method: str) -> jsonschema.protocols.Validator | None:
    """The validator of the route's request body schema in the API document; None when it takes no body."""
    import jsonschema

    op = (_document()["paths"].get(path) or {}).get(method.lower()) or {}
    sch = (((op.get("requestBody") or {}).get("content") or {}).get("application/json") or {}).get("schema")
    if sch is None:
        return None
    root = {**sch, "components": _document()["components"]}  # the $refs point into the document's components
    v: jsonschema.protocols.Validator = jsonschema.Draft202012Validator(root)
    return v


def _problems(data: dict[str, Any], path: str, method: str) -> Iterator[str]:
    for key in GONE.keys() & data.keys():
        yield f"{key}: not taken any more: {GONE[key]}"
    v = _validator(path, method)
    if v is None:
        if data:
            yield f"this route takes no body (it got the keys {', '.join(sorted(map(repr, data))[:5])})"
        return
    for err in sorted(v.iter_errors({k: x for k, x in data.items() if k not in GONE}), key=lambda e: list(e.path)):
        at = ".".join(str(p) for p in err.absolute_path)
        if err.validator == "additionalProperties":
            allowed = sorted((err.schema.get("properties") or {}) if isinstance(err.schema, dict) else ())
            extra = sorted(set(err.instance) - set(allowed)) if isinstance(err.instance, dict) else []
            for k in extra:
                where = f"{at}.{k}" if at else k
                yield f"{clip(where, 80)}: not a key of this request (it takes {', '.join(allowed) or 'none'})"
            continue
        yield f"{clip(at, 80) + ': ' if at else ''}{clip(err.message, 200)}"


async def read(request: web.Request) -> dict[str, Any]:
    """The request's body, parsed and checked against its route's schema (ApiError 400 otherwise)."""
    raw = await request.read() if request.can_read_body else b""
    data = parse(raw)
    route = request.match_info.route.resource
    problems = list(_problems(data, route.canonical if route is not None else request.path, request.method))
    if problems:
        raise ApiError(
            "usage",
            f"the request body is not what {request.method} {request.path[:100]} takes: " + "; ".join(problems[:10]),
            status=400,
        )
    return data
