"""Import a SunSpec information model (pysunspec2's model definitions) as a profile.

A SunSpec device lays its models one after the other from holding register 40000 ("SunS"),
so a model's points sit at fixed offsets from the address of its ``ID`` point. pysunspec2
ships the official model definitions as JSON; this module reads those files with our own loader
rather than ``sunspec2.mdef`` so that every problem points at a line of the model file (the
package is an optional extra: ``pip install 'modbus-deployer[sunspec]'``).

Scale factors (``sf``) name another point whose value the device reports at run time; a
profile's scale is fixed, so give the values you know (``--sf WMax_SF=0``), else the point is
imported unscaled and its description says which scale factor applies.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from decimal import Decimal
from typing import Any

from ...load import yamlsrc
from ...load.diagnostics import Diagnostic, InputError, UsageError
from .. import units
from ..emit import Draft, Origin

SUNSPEC_BASE = 40000  # protocol address of "SunS"; the first model's ID follows at 40002

_TYPES: dict[str, tuple[str, int]] = {  # SunSpec type -> (our type, registers)
    "uint16": ("uint16", 1), "int16": ("int16", 1), "uint32": ("uint32", 2), "int32": ("int32", 2),
    "uint64": ("uint64", 4), "int64": ("int64", 4), "float32": ("float32", 2), "float64": ("float64", 4),
    "acc16": ("uint16", 1), "acc32": ("uint32", 2), "acc64": ("uint64", 4),
    "enum16": ("uint16", 1), "enum32": ("uint32", 2), "bitfield16": ("uint16", 1), "bitfield32": ("uint32", 2),
    "sunssf": ("int16", 1), "pad": ("uint16", 1), "count": ("uint16", 1), "ipaddr": ("uint32", 2),
    "eui48": ("uint64", 4), "ipv6addr": ("string", 8), "string": ("string", 0),
}
_UNITS = {"Secs": "s", "Sec": "s", "mSecs": "ms", "C": "degC", "Pct": "%", "Degrees": "deg", "W/m2": "W/m**2",
          "WH": "Wh", "AH": "Ah", "ohms": "ohm", "HPa": "hPa", "mps": "m/s"}


def models_dir() -> str:
    try:
        import sunspec2
    except ImportError:
        raise UsageError("SunSpec import needs the pysunspec2 package: "
                         "pip install 'modbus-deployer[sunspec]'") from None
    return os.path.join(os.path.dirname(sunspec2.__file__), "models", "json")


def model_path(model: str) -> str:
    """A model number or name (121, 'settings'), or a model JSON file."""
    if model.endswith(".json") or os.sep in model:
        return model
    directory = models_dir()
    if model.isascii() and model.isdigit():
        path = os.path.join(directory, f"model_{int(model)}.json")
        if not os.path.isfile(path):
            raise UsageError(f"no SunSpec model {model} in pysunspec2's definitions")
        return path
    for f in sorted(os.listdir(directory)):
        if f.startswith("model_") and f.endswith(".json"):
            with open(os.path.join(directory, f), encoding="utf-8") as fh:
                if json.load(fh).get("group", {}).get("name") == model:
                    return os.path.join(directory, f)
    raise UsageError(f"no SunSpec model named '{model}' in pysunspec2's definitions")


def scale_factor_points(model: str) -> list[str]:
    """The model's top-level scale-factor points (type sunssf): what --device reads."""
    data, _ = yamlsrc.load(model_path(model), yamlsrc.read_text(model_path(model)).expandtabs(1))
    return [str(p["name"]) for p in data["group"]["points"] if p.get("type") == "sunssf"]


def read_model(model: str, *, at: int = SUNSPEC_BASE + 2, scale_factors: Mapping[str, int] | None = None,
               counts: Mapping[str, int] | None = None, profile_id: str | None = None) -> tuple[Draft, list[str]]:
    """The model as a Draft profile with its ID point at protocol address ``at``, and warnings.

    ``counts``: repetitions of groups whose count the device reports (group name -> N).
    """
    counts = dict(counts or {})
    path = model_path(model)
    # JSON allows tabs where YAML (our loader, which keeps positions) does not: same columns with spaces
    data, src = yamlsrc.load(path, yamlsrc.read_text(path).expandtabs(1))
    sfs = dict(scale_factors or {})
    warnings: list[str] = []
    errors: list[Diagnostic] = []
    problems = _schema_problems(data, src)
    if problems:
        raise InputError(problems)
    group = data["group"]
    if "points" not in group:
        raise InputError([src.error(("group",), "not a SunSpec model definition (expected group.points)")])
    model_id = int(data.get("id", 0) or next((p.get("value", 0) for p in group["points"] if p["name"] == "ID"), 0))
    parameters: list[tuple[str, dict[str, Any], Origin]] = []
    tables: list[tuple[str, dict[str, Any], Origin]] = []
    offset = 0
    length_spec: dict[str, Any] | None = None

    def spec_of(point: dict[str, Any], at_: yamlsrc.Path_, prefix: str = "") -> tuple[dict[str, Any] | None, int]:
        ptype = str(point.get("type"))
        size = int(point.get("size", 1))
        if ptype not in _TYPES:
            errors.append(src.error((*at_, "type"), f"{point.get('name')}: SunSpec type '{ptype}' is not supported"))
            return None, size
        our, count = _TYPES[ptype]
        if count and count != size:
            errors.append(src.error((*at_, "size"), f"{point.get('name')}: {ptype} is {count} registers, not {size}"))
            return None, size
        spec: dict[str, Any] = {}
        desc = " - ".join(str(point[k]) for k in ("label", "desc") if point.get(k))
        spec["type"] = our
        if our == "string":
            spec["count"] = size
            if ptype == "ipv6addr":
                spec["encoding"] = "latin-1"  # 16 raw bytes: every byte is a latin-1 character
        access = "read-write" if point.get("access") == "RW" else "read-only"
        if ptype in ("pad", "sunssf", "acc16", "acc32", "acc64"):
            access = "read-only"
        spec["access"] = access
        u = point.get("units")
        if u:
            unit = _UNITS.get(str(u), str(u))
            if units.check(unit) is None:
                spec["unit"] = unit
            else:
                desc = f"{desc} [{u}]"
        sf = point.get("sf")
        if isinstance(sf, int):
            spec["scale"] = _pow10(sf)
        elif isinstance(sf, str):
            if sf in sfs:
                spec["scale"] = _pow10(sfs[sf])
            else:
                desc = f"{desc} (raw: scaled by 10^{sf} on the device; import with --sf {sf}=N)"
                warnings.append(f"{prefix}{point['name']}: scale factor {sf} unknown, imported unscaled")
        symbols = point.get("symbols") or []
        if ptype in ("enum16", "enum32") and symbols:
            if not all(isinstance(sym.get("value"), int) for sym in symbols):
                errors.append(src.error((*at_, "symbols"), f"{point['name']}: symbol values must be integers"))
                return None, size
            spec["values"] = {str(sym["name"]): int(sym["value"]) for sym in symbols}
        if isinstance(point.get("value"), int) and not isinstance(point["value"], bool):
            spec["default"] = point["value"]
        if desc:
            spec = {"description": desc, **spec}
        return spec, size

    for i, point in enumerate(group["points"]):
        at_: yamlsrc.Path_ = ("group", "points", i)
        spec, size = spec_of(point, at_)
        line, col = src.pos(at_)
        if spec is not None:
            name = str(point["name"])
            if point.get("type") == "bitfield16" and point.get("symbols") and all(
                    isinstance(sym.get("value"), int) and 0 <= sym["value"] <= 15 for sym in point["symbols"]):
                for s in point["symbols"]:  # one bool field per documented bit
                    field_spec = {"description": f"{spec.get('description', name)}: {s['name']}",
                                  "type": "bool", "bits": int(s["value"]), "access": spec["access"]}
                    parameters.append((f"{name}.{s['name']}", {"register": at + offset, **field_spec},
                                       Origin(path, line, col)))
            else:
                if point.get("type") == "sunssf" and name in sfs:
                    spec["default"] = sfs[name]  # the value given: what a simulated device reports
                entry = {"register": at + offset, **spec}
                parameters.append((name, entry, Origin(path, line, col)))
                if name == "L":
                    length_spec = entry  # its default is the model's length, known once the groups are laid out
        offset += size
    def count_of(sub: dict[str, Any]) -> int | None:
        """How often a group repeats: the model's fixed count, one, or --count; None when unknown."""
        count = counts.get(str(sub.get("name")), 1 if sub.get("count") is None else sub.get("count"))
        if not isinstance(count, int) or count < 1:
            what = f"the point {sub.get('count')}" if isinstance(sub.get("count"), str) else "variable"
            warnings.append(f"group {sub.get('name')}: its count is {what} (set by the device); not imported "
                            f"(give it with --count {sub.get('name')}=N)")
            return None
        return count

    def fields_of(sub: dict[str, Any], at_: yamlsrc.Path_, prefix: str = "") -> tuple[dict[str, Any], int] | None:
        """A group's points as table fields (offset from the entry's start), and the entry's size. A group
        nested in it (a curve's points) becomes fields Pt0_V, Pt0_Var, Pt1_V ... after the group's own."""
        out: dict[str, Any] = {}
        size = 0
        for k, point in enumerate(sub.get("points", [])):
            spec, n = spec_of(point, (*at_, "points", k), f"{sub.get('name')}.")
            if spec is not None and point.get("type") != "pad":
                spec.pop("default", None)
                out[f"{prefix}{point['name']}"] = {"offset": size, **spec}
            size += n
        for k, inner in enumerate(sub.get("groups") or []):
            if prefix:  # a third level: no model in pysunspec2 has one
                warnings.append(f"group {inner.get('name')}: groups nested twice are not imported")
                return None
            n_inner = count_of(inner)
            got = None if n_inner is None else fields_of(inner, (*at_, "groups", k), "-")
            if n_inner is None or got is None:
                return None
            inner_fields, inner_size = got
            for i in range(n_inner):
                for name, spec in inner_fields.items():
                    out[f"{inner['name']}{i}_{name[1:]}"] = {**spec, "offset": size + i * inner_size + spec["offset"]}
            size += n_inner * inner_size
        return out, size

    for j, sub in enumerate(group.get("groups") or []):
        at_ = ("group", "groups", j)
        count = count_of(sub)
        got = None if count is None else fields_of(sub, at_)
        if count is None or got is None:
            break  # later groups' addresses depend on it
        fields, stride = got
        line, col = src.pos(at_)
        if fields:
            tables.append((str(sub["name"]), {"count": count, "base": at + offset, "stride": stride, "fields": fields},
                           Origin(path, line, col)))
        offset += stride * count
    if length_spec is not None:
        length_spec["default"] = offset - 2  # the registers after ID and L
    if at + offset > 0x10000:
        raise UsageError(f"--at {at}: model {model_id} is {offset} registers long and would end past register 65535")
    if errors:
        raise InputError(errors)
    identity = [{"register": at, "raw": model_id, "description": f"SunSpec model ID {model_id}"}]
    if at == SUNSPEC_BASE + 2:  # the first model: the "SunS" marker right before it is part of the map
        marker = {"description": "SunSpec marker 'SunS'", "type": "string", "count": 2, "access": "read-only",
                  "default": "SunS"}
        parameters.insert(0, ("SunS", {"register": SUNSPEC_BASE, **marker}, Origin(path, 1, 1)))
        identity[:0] = [{"register": SUNSPEC_BASE, "raw": 0x5375, "description": "'Su' of the SunS marker"},
                        {"register": SUNSPEC_BASE + 1, "raw": 0x6E53, "description": "'nS' of the SunS marker"}]
    header = {"profile": profile_id or f"sunspec-{model_id}-{group.get('name', 'model')}",
              "description": f"SunSpec model {model_id} ({group.get('label', group.get('name'))}) at address {at}, "
                             "imported from pysunspec2's model definitions",
              "addressing": "address",
              "identity": identity}
    return Draft(header, parameters, tables), warnings


def _pow10(sf: int) -> float | int:
    d = Decimal(10) ** sf
    return int(d) if sf >= 0 else float(d)


def _schema_problems(data: Any, src: yamlsrc.Source) -> list[Diagnostic]:
    """The model file checked against pysunspec2's own JSON Schema for model definitions, with positions."""
    import jsonschema

    with open(os.path.join(models_dir(), "schema.json"), encoding="utf-8") as f:
        schema = json.load(f)
    errors = sorted(jsonschema.Draft7Validator(schema).iter_errors(data), key=lambda e: list(map(str, e.path)))
    return [src.error(tuple(e.absolute_path), f"{'.'.join(map(str, e.absolute_path)) or 'model'}: {e.message}")
            for e in errors[:20]]
