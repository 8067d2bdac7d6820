"""Import a SunSpec information model (pysunspec2's model definitions) as a profile.

A SunSpec device lays its models one after the other from holding register 40000 ("SunS"),
so a model's points sit at fixed offsets from the address of its ``ID`` point. pysunspec2
ships the official model definitions as JSON; this module reads those files with our own loader
rather than ``sunspec2.mdef`` so that every problem points at a line of the model file (the
package is an optional extra: ``pip install 'modbus-deployer[sunspec]'``).

Scale factors (``sf``) name another point whose value the device reports at run time; a
profile's scale is fixed, so give the values you know (``--sf WMax_SF=0``), else the point is
imported raw: without a unit (a unit would convert engineering values with a wrong scale) and
with a description that says which scale factor applies.

Repeating groups are bounded before they are laid out: a count (from the model, ``--count`` or
the device) that would run past register 65535 or declare more than 65,536 parameters is an
error at the count, not a list of millions of fields.
"""

from __future__ import annotations

import json
import os
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from decimal import Decimal
from typing import Any

from ...errors import Diagnostic, InputError, UsageError
from ...load import messages, yamlsrc
from .. import units
from ..emit import Draft, Origin

SUNSPEC_BASE = 40000  # protocol address of "SunS"; the first model's ID follows at 40002
SF_RANGE = range(-10, 11)  # the SunSpec specification's scale factors (sunssf); 0x8000 means "not implemented"
MAX_REGISTERS = 0x10000

_TYPES: dict[str, tuple[str, int]] = {  # SunSpec type -> (our type, registers)
    "uint16": ("uint16", 1),
    "int16": ("int16", 1),
    "uint32": ("uint32", 2),
    "int32": ("int32", 2),
    "uint64": ("uint64", 4),
    "int64": ("int64", 4),
    "float32": ("float32", 2),
    "float64": ("float64", 4),
    "acc16": ("uint16", 1),
    "acc32": ("uint32", 2),
    "acc64": ("uint64", 4),
    "enum16": ("uint16", 1),
    "enum32": ("uint32", 2),
    "bitfield16": ("uint16", 1),
    "bitfield32": ("uint32", 2),
    "sunssf": ("int16", 1),
    "pad": ("uint16", 1),
    "count": ("uint16", 1),
    "ipaddr": ("uint32", 2),
    "eui48": ("uint64", 4),
    "ipv6addr": ("string", 8),
    "string": ("string", 0),
}
_UNITS = {
    "Secs": "s",
    "Sec": "s",
    "mSecs": "ms",
    "C": "degC",
    "Pct": "%",
    "Degrees": "deg",
    "W/m2": "W/m**2",
    "WH": "Wh",
    "AH": "Ah",
    "ohms": "ohm",
    "HPa": "hPa",
    "mps": "m/s",
}


def models_dir() -> str:
    try:
        import sunspec2
    except ImportError:
        raise UsageError(
            "SunSpec import needs the pysunspec2 package: pip install 'modbus-deployer[sunspec]' "
            "(from a clone of the repository: pip install -e '.[sunspec]')"
        ) from None
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


def read_model(
    model: str,
    *,
    at: int = SUNSPEC_BASE + 2,
    scale_factors: Mapping[str, int] | None = None,
    counts: Mapping[str, int] | None = None,
    profile_id: str | None = None,
    point_values: Mapping[str, int] | None = None,
    length: int | None = None,
    prefix: str = "",
) -> tuple[Draft, list[str]]:
    """The model as a Draft profile with its ID point at protocol address ``at``, and warnings.

    ``counts``: repetitions of groups whose count the device reports (group name -> N, from --count).
    ``point_values``: count points as a device reports them (``N`` -> 4); ``length``: the model's L as
    the device reports it (a group of count 0 fills the rest of the model). ``prefix``: put before every
    name (a device's chain of models in one profile).
    """
    counts = dict(counts or {})
    for g, n in counts.items():
        if not 1 <= n < MAX_REGISTERS:
            raise UsageError(f"--count {messages.clip(g)}={n}: a group repeats 1 to 65535 times")
    for k, n in (scale_factors or {}).items():
        if n not in SF_RANGE:
            raise UsageError(f"--sf {messages.clip(k)}={n}: a SunSpec scale factor is -10 to 10")
    path = model_path(model)
    # JSON allows tabs where YAML (our loader, which keeps positions) does not: same columns with spaces
    data, src = yamlsrc.load(path, yamlsrc.read_text(path).expandtabs(1))
    problems = _schema_problems(data, src)
    if problems:
        raise InputError(problems)
    group = data["group"]
    if "points" not in group:
        raise InputError([src.error(("group",), "not a SunSpec model definition (expected group.points)")])
    model_id = int(data.get("id", 0) or next((p.get("value", 0) for p in group["points"] if p["name"] == "ID"), 0))
    r = _ModelReader(path, src, at, prefix, dict(scale_factors or {}), counts, dict(point_values or {}), length)
    r.top_points(group)
    r.groups(group)
    if r.length_spec is not None:
        r.length_spec["default"] = r.offset - 2  # the registers after ID and L
    for name, spec, _ in r.parameters:
        if name[len(prefix) :] in r.count_points and name.startswith(prefix):
            spec["default"] = r.count_points[name[len(prefix) :]]
    if r.errors:
        raise InputError(r.errors)
    if at + r.offset > MAX_REGISTERS:
        raise UsageError(f"--at {at}: model {model_id} is {r.offset} registers long and would end past register 65535")
    return Draft(_header(r, group, model_id, profile_id), r.parameters, r.tables), r.warnings


def _header(r: _ModelReader, group: Mapping[str, Any], model_id: int, profile_id: str | None) -> dict[str, Any]:
    """The profile's own keys; the first model (right after "SunS") also gets the marker as identity."""
    at = r.at
    identity = [{"register": at, "raw": model_id, "description": f"SunSpec model ID {model_id}"}]
    if at == SUNSPEC_BASE + 2:  # the first model: the "SunS" marker right before it is part of the map
        marker = {
            "description": "SunSpec marker 'SunS'",
            "type": "string",
            "count": 2,
            "access": "read-only",
            "default": "SunS",
        }
        r.parameters.insert(0, ("SunS", {"register": SUNSPEC_BASE, **marker}, Origin(r.path, 1, 1)))
        identity[:0] = [
            {"register": SUNSPEC_BASE, "raw": 0x5375, "description": "'Su' of the SunS marker"},
            {"register": SUNSPEC_BASE + 1, "raw": 0x6E53, "description": "'nS' of the SunS marker"},
        ]
    return {
        "profile": profile_id or f"sunspec-{model_id}-{group.get('name', 'model')}",
        "description": f"SunSpec model {model_id} ({group.get('label', group.get('name'))}) at address {at}, "
        "imported from pysunspec2's model definitions",
        "addressing": "address",
        "identity": identity,
    }


class _ModelReader:
    """One model laid out from ``at``: its points, then its groups (tables); the errors and warnings found."""

    def __init__(
        self,
        path: str,
        src: yamlsrc.Source,
        at: int,
        prefix: str,
        sfs: dict[str, int],
        counts: dict[str, int],
        values: dict[str, int],
        length: int | None,
    ) -> None:
        self.path, self.src, self.at, self.prefix = path, src, at, prefix
        self.sfs, self.counts, self.values, self.length = sfs, counts, values, length
        self.errors: list[Diagnostic] = []
        self.warnings: list[str] = []
        self.parameters: list[tuple[str, dict[str, Any], Origin]] = []
        self.tables: list[tuple[str, dict[str, Any], Origin]] = []
        self.count_points: dict[str, int] = {}
        self.length_spec: dict[str, Any] | None = None
        self.offset = 0  # registers from the ID point laid out so far

    def error(self, at: yamlsrc.Path_, message: str) -> None:
        self.errors.append(self.src.error(at, message))

    # ---- one point ----------------------------------------------------------------------------

    def spec_of(self, point: dict[str, Any], at_: yamlsrc.Path_, prefix: str = "") -> tuple[dict[str, Any] | None, int]:
        """A point as a parameter spec (None: an error said), and its registers."""
        ptype = str(point.get("type"))
        size = int(point.get("size", 1))
        if ptype not in _TYPES:
            self.error((*at_, "type"), f"{point.get('name')}: SunSpec type '{ptype}' is not supported")
            return None, size
        our, count = _TYPES[ptype]
        if count and count != size:
            self.error((*at_, "size"), f"{point.get('name')}: {ptype} is {count} registers, not {size}")
            return None, size
        spec: dict[str, Any] = {"type": our}
        if our == "string":
            spec["count"] = size
            if ptype == "ipv6addr":
                spec["encoding"] = "latin-1"  # 16 raw bytes: every byte is a latin-1 character
        access = "read-write" if point.get("access") == "RW" else "read-only"
        spec["access"] = "read-only" if ptype in ("pad", "sunssf", "acc16", "acc32", "acc64") else access
        desc = " - ".join(str(point[k]) for k in ("label", "desc") if point.get(k))
        u = point.get("units")
        if u:
            unit = _UNITS.get(str(u), str(u))
            if units.check(unit) is None:
                spec["unit"] = unit
            else:
                desc = f"{desc} [{u}]"
        said = self._scale(point, at_, prefix, spec, desc)
        if said is None or not self._symbols(point, at_, ptype, spec):
            return None, size
        desc = said
        if (
            isinstance(point.get("value"), int)
            and not isinstance(point["value"], bool)
            and (abs(point["value"]) < 1 << 64)
        ):
            spec["default"] = point["value"]
        if desc:
            spec = {"description": desc, **spec}
        return spec, size

    def _scale(
        self, point: dict[str, Any], at_: yamlsrc.Path_, prefix: str, spec: dict[str, Any], desc: str
    ) -> str | None:
        """The point's scale factor: fixed, given (--sf), or unknown (imported raw, said); the description, or
        None after an error."""
        sf = point.get("sf")
        if isinstance(sf, int) and not isinstance(sf, bool):
            if sf not in SF_RANGE:
                self.error((*at_, "sf"), f"{point.get('name')}: scale factor {sf} is not -10 to 10")
                return None
            spec["scale"] = _pow10(sf)
        elif isinstance(sf, str):
            if sf in self.sfs:
                spec["scale"] = _pow10(self.sfs[sf])
            else:  # a unit would convert '10 kW' with scale 1: raw numbers only, until the factor is known
                unit_text = f" {spec.pop('unit')}" if "unit" in spec else ""
                desc = f"{desc} (raw: the value in{unit_text} is raw x 10^{sf}; import with --sf {sf}=N or --device)"
                self.warnings.append(
                    f"{prefix}{point['name']}: scale factor {sf} unknown: imported raw, without its unit"
                )
        return desc

    def _symbols(self, point: dict[str, Any], at_: yamlsrc.Path_, ptype: str, spec: dict[str, Any]) -> bool:
        symbols = point.get("symbols") or []
        if ptype in ("enum16", "enum32") and symbols:
            if not all(isinstance(sym.get("value"), int) for sym in symbols):
                self.error((*at_, "symbols"), f"{point['name']}: symbol values must be integers")
                return False
            spec["values"] = {str(sym["name"]): int(sym["value"]) for sym in symbols}
        return True

    # ---- the model's own points ---------------------------------------------------------------------

    def top_points(self, group: Mapping[str, Any]) -> None:
        for i, point in enumerate(group["points"]):
            at_: yamlsrc.Path_ = ("group", "points", i)
            spec, size = self.spec_of(point, at_)
            line, col = self.src.pos((*at_, "name"))
            if spec is not None:
                self._point(point, spec, Origin(self.path, line, col))
            self.offset += size

    def _point(self, point: dict[str, Any], spec: dict[str, Any], origin: Origin) -> None:
        name = self.prefix + str(point["name"])
        register = self.at + self.offset
        if (
            point.get("type") == "bitfield16"
            and point.get("symbols")
            and all(isinstance(sym.get("value"), int) and 0 <= sym["value"] <= 15 for sym in point["symbols"])
        ):
            for s in point["symbols"]:  # one bool field per documented bit
                field_spec = {
                    "description": f"{spec.get('description', name)}: {s['name']}",
                    "type": "bool",
                    "bits": int(s["value"]),
                    "access": spec["access"],
                }
                self.parameters.append((f"{name}.{s['name']}", {"register": register, **field_spec}, origin))
            return
        if point.get("type") == "sunssf" and point["name"] in self.sfs:
            spec["default"] = self.sfs[point["name"]]  # the value given: what a simulated device reports
        entry = {"register": register, **spec}
        self.parameters.append((name, entry, origin))
        if point["name"] == "L":
            self.length_spec = entry  # its default is the model's length, known once the groups are laid out

    # ---- repeating groups ---------------------------------------------------------------------------

    def count_of(self, sub: dict[str, Any], at_: yamlsrc.Path_, size: int | None = None) -> int | None:
        """How often a group repeats: --count, the device's count point, the model's fixed count, one;
        None when unknown (said in a warning). ``size``: registers of one repetition, for count 0."""
        name = str(sub.get("name"))
        declared = sub.get("count")
        if name in self.counts:
            if isinstance(declared, str):  # the count point says it too: what a simulated device reports
                self.count_points[declared] = self.counts[name]
            return self.counts[name]
        if declared is None:
            return 1
        if isinstance(declared, str) and declared in self.values:
            return self.values[declared]
        is_int = isinstance(declared, int) and not isinstance(declared, bool)
        if is_int and declared >= MAX_REGISTERS:
            self.error((*at_, "count"), f"group {name}: count {declared} repeats past register 65535")
            return None
        if is_int and declared > 0:
            return int(declared)
        if is_int and declared < 0:
            self.error(
                (*at_, "count"),
                f"group {name}: count {declared} is negative (a count is a number of "
                "repetitions, or 0: as many as the model's length holds)",
            )
            return None
        if declared == 0 and self.length is not None and size:
            left = self.length + 2 - self.offset
            if left >= 0 and left % size == 0:
                return left // size
        what = f"the point {declared}" if isinstance(declared, str) else "0: as many as the model's length L holds"
        self.warnings.append(
            f"group {self.prefix}{name}: its count is {what} (set by the device); not imported "
            f"(give it with --count {name}=N, or import with --device)"
        )
        return None

    def fields_of(self, sub: dict[str, Any], at_: yamlsrc.Path_, prefix: str = "") -> tuple[dict[str, Any], int] | None:
        """A group's points as table fields (offset from the entry's start), and the entry's size. A group
        nested in it (a curve's points) becomes fields Pt0_V, Pt0_Var, Pt1_V ... after the group's own."""
        out: dict[str, Any] = {}
        size = 0
        for k, point in enumerate(sub.get("points", [])):
            spec, n = self.spec_of(point, (*at_, "points", k), f"{sub.get('name')}.")
            if spec is not None and point.get("type") != "pad":
                spec.pop("default", None)
                out[f"{prefix}{point['name']}"] = {"offset": size, **spec}
            size += n
        for k, inner in enumerate(sub.get("groups") or []):
            if prefix:  # a third level: no model in pysunspec2 has one
                self.warnings.append(f"group {inner.get('name')}: groups nested twice are not imported")
                return None
            got = self._inner(inner, (*at_, "groups", k), size)
            if got is None:
                return None
            out.update(got[0])
            size += got[1]
        return out, size

    def _inner(self, inner: dict[str, Any], inner_at: yamlsrc.Path_, start: int) -> tuple[dict[str, Any], int] | None:
        """A nested group's repetitions as fields from ``start``, and their registers."""
        got = self.fields_of(inner, inner_at, "-")
        if got is None:
            return None
        inner_fields, inner_size = got
        n_inner = self.count_of(inner, inner_at)
        if n_inner is None:
            return None
        if n_inner * max(inner_size, 1) >= MAX_REGISTERS or n_inner * len(inner_fields) > yamlsrc.MAX_ENTRIES:
            where = f"--count {inner.get('name')}={n_inner}" if inner.get("name") in self.counts else "count"
            self.error(
                (*inner_at, "count"),
                f"group {inner.get('name')}: {where}: {n_inner} x {inner_size} registers run past register 65535",
            )
            return None
        out = {
            f"{inner['name']}{i}_{name[1:]}": {**spec, "offset": start + i * inner_size + spec["offset"]}
            for i in range(n_inner)
            for name, spec in inner_fields.items()
        }
        return out, n_inner * inner_size

    def groups(self, group: Mapping[str, Any]) -> None:
        """The model's repeating groups as tables, one after the other (a group that cannot be laid out ends
        it: later groups' addresses depend on it)."""
        table_prefix = self.prefix.replace(".", "_")
        for j, sub in enumerate(group.get("groups") or []):
            at_: yamlsrc.Path_ = ("group", "groups", j)
            got = self.fields_of(sub, at_)
            if got is None:
                break
            fields, stride = got
            count = self.count_of(sub, at_, stride)
            if count is None:
                break
            line, col = self.src.pos((*at_, "name"))
            if self.at + self.offset + stride * count > MAX_REGISTERS or count * len(fields) > yamlsrc.MAX_ENTRIES:
                where = f"--count {sub.get('name')}={count}" if sub.get("name") in self.counts else "count"
                self.error(
                    (*at_, "count"),
                    f"group {sub.get('name')}: {where}: {count} x {stride} registers from "
                    f"register {self.at + self.offset} run past 65535",
                )
                break
            if fields:
                self.tables.append(
                    (
                        table_prefix + str(sub["name"]),
                        {"count": count, "base": self.at + self.offset, "stride": stride, "fields": fields},
                        Origin(self.path, line, col),
                    )
                )
            self.offset += stride * count


def _pow10(sf: int) -> float | int:
    d = Decimal(10) ** sf
    return int(d) if sf >= 0 else float(d)


def _schema_problems(data: Any, src: yamlsrc.Source) -> list[Diagnostic]:
    """The model file checked against pysunspec2's own JSON Schema for model definitions, with positions."""
    import jsonschema

    with open(os.path.join(models_dir(), "schema.json"), encoding="utf-8") as f:
        schema = json.load(f)
    errors = sorted(jsonschema.Draft7Validator(schema).iter_errors(data), key=lambda e: list(map(str, e.path)))
    return [
        src.error(tuple(e.absolute_path), f"{'.'.join(map(str, e.absolute_path)) or 'model'}: {e.message}")
        for e in errors[:20]
    ]


# ------------------------------------------------------------------------------- a device's models

Read = Callable[[int, int], Awaitable[list[int]]]  # (protocol address, count) -> registers, from the device
MARKER = (0x5375, 0x6E53)  # "SunS"
END = 0xFFFF  # the model ID that ends the chain
MAX_MODELS = 256


@dataclass
class DeviceModel:
    """One model of a device's chain: its ID, where its ID register is, its length L and its registers."""

    model_id: int
    at: int
    length: int
    registers: list[int]


class NotThere(Exception):
    """The device answered exception 02 (illegal data address): it has no such registers. The message says so."""


async def device_chain(read: Read, at: int, *, search: bool = False) -> list[DeviceModel]:
    """The device's models from the 'SunS' marker at ``at - 2`` to the end marker 0xFFFF, each read whole.
    ``search``: when 'SunS' is not at ``at - 2``, look for it at 0 and 50000 too (where devices put it)."""
    candidates = [at, *(a for a in (2, 50002) if a != at)] if search else [at]
    for i, first in enumerate(candidates):
        try:
            marker = await read(first - 2, 2)
        except NotThere:
            if i == len(candidates) - 1:
                raise
            continue
        if tuple(marker) == MARKER or i == len(candidates) - 1:
            at = first
            break
    if tuple(marker) != MARKER:
        where = "40000, 0 or 50000" if search else str(at - 2)
        raise UsageError(
            f"no SunSpec marker 'SunS' at {where} (the device has {marker[0]:04X}h {marker[1]:04X}h at "
            f"{at - 2}): check --at (the first model's ID sits 2 registers after 'SunS', which devices "
            "put at 40000, 0 or 50000)"
        )
    models: list[DeviceModel] = []
    while True:
        if at + 2 > MAX_REGISTERS or len(models) >= MAX_MODELS:
            raise UsageError(f"the device's model chain runs past register {at} without its end marker 0xFFFF")
        (model_id,) = await read(at, 1)  # the end marker alone: devices need not have an L after it
        if model_id == END:
            return models
        (length,) = await read(at + 1, 1)
        if at + 2 + length > MAX_REGISTERS:
            raise UsageError(f"model {model_id} at {at}: its length L={length} runs past register 65535")
        models.append(DeviceModel(model_id, at, length, [model_id, length, *await read(at + 2, length)]))
        at += 2 + length


async def device_model(read: Read, model: str, at: int) -> DeviceModel:
    """The model ``model`` at ``at`` as the device reports it (its ID checked first)."""
    path = model_path(model)
    data, _ = yamlsrc.load(path, yamlsrc.read_text(path).expandtabs(1))
    want = data.get("id") if isinstance(data, dict) else None
    model_id, length = await read(at, 2)
    if isinstance(want, int) and model_id != want:
        found = "the end marker 0xFFFF" if model_id == END else f"model {model_id}"
        raise UsageError(f"the device has {found} at {at}, not model {want}: check --at")
    if at + 2 + length > MAX_REGISTERS:
        raise UsageError(f"model {model_id} at {at}: its length L={length} runs past register 65535")
    return DeviceModel(model_id, at, length, [model_id, length, *await read(at + 2, length)])


def reported(model: str | int, dm: DeviceModel, prefix: str = "") -> tuple[dict[str, int], dict[str, int], list[str]]:
    """The scale factors and count points a device reports in its model (by point name), and warnings."""
    path = model_path(str(model))
    data, _ = yamlsrc.load(path, yamlsrc.read_text(path).expandtabs(1))
    sfs: dict[str, int] = {}
    points: dict[str, int] = {}
    warnings: list[str] = []
    offset = 0
    for point in data["group"]["points"]:
        size = int(point.get("size", 1))
        if offset < len(dm.registers):
            raw = dm.registers[offset]
            name = str(point["name"])
            if point.get("type") == "sunssf":
                value = raw - 0x10000 if raw >= 0x8000 else raw
                if value in SF_RANGE:
                    sfs[name] = value
                else:
                    why = "not implemented (8000h)" if raw == 0x8000 else f"{value}, not -10 to 10"
                    warnings.append(
                        f"{prefix}{name} at {dm.at + offset}: the device reports {why}: the points it "
                        "scales are imported raw"
                    )
            elif point.get("type") in ("count", "uint16"):
                points[name] = raw
        offset += size
    return sfs, points, warnings


def chain_draft(
    models: list[DeviceModel],
    *,
    scale_factors: Mapping[str, int] | None = None,
    counts: Mapping[str, int] | None = None,
    profile_id: str | None = None,
    source: str = "the device",
) -> tuple[Draft, list[str]]:
    """One profile of a device's whole model chain: each model's points named MODEL.POINT (common.Mn,
    inverter.W; a second model of one kind gets _2), its scale factors and counts as the device reports
    them (``scale_factors``/``counts`` given by hand win), the markers and model IDs as its identity."""
    parameters: list[tuple[str, dict[str, Any], Origin]] = []
    tables: list[tuple[str, dict[str, Any], Origin]] = []
    identity: list[dict[str, Any]] = []
    warnings: list[str] = []
    used: dict[str, int] = {}
    ids: list[str] = []
    for dm in models:
        try:
            path = model_path(str(dm.model_id))
        except UsageError:
            warnings.append(
                f"model {dm.model_id} at {dm.at} (L={dm.length}): pysunspec2 has no definition of it; "
                "its registers are not in the profile"
            )
            identity.append({"register": dm.at, "raw": dm.model_id, "description": f"SunSpec model ID {dm.model_id}"})
            ids.append(str(dm.model_id))
            continue
        data, _ = yamlsrc.load(path, yamlsrc.read_text(path).expandtabs(1))
        name = str(data["group"].get("name", f"model{dm.model_id}"))
        used[name] = used.get(name, 0) + 1
        prefix = f"{name}{'' if used[name] == 1 else '_' + str(used[name])}."
        sfs, points, said = reported(dm.model_id, dm, prefix)
        warnings.extend(said)
        sfs.update(scale_factors or {})
        draft, said = read_model(
            str(dm.model_id),
            at=dm.at,
            scale_factors=sfs,
            counts=counts,
            point_values=points,
            length=dm.length,
            prefix=prefix,
        )
        warnings.extend(said)
        laid_out = next((spec.get("default") for n, spec, _ in draft.parameters if n == f"{prefix}L"), None)
        if laid_out is not None and laid_out != dm.length:
            warnings.append(
                f"model {dm.model_id} at {dm.at}: the device says L={dm.length}, the definition lays "
                f"out {laid_out} registers"
            )
        parameters.extend(p for p in draft.parameters if p[0] != "SunS")
        tables.extend(draft.tables)
        identity.append(draft.header["identity"][-1])
        ids.append(str(dm.model_id))
    end = models[-1].at + 2 + models[-1].length if models else SUNSPEC_BASE + 2
    first = models[0].at if models else SUNSPEC_BASE + 2
    marker = {
        "register": first - 2,
        "description": "SunSpec marker 'SunS'",
        "type": "string",
        "count": 2,
        "access": "read-only",
        "default": "SunS",
    }
    here = Origin(source, 1, 1)
    parameters.insert(0, ("SunS", marker, here))
    parameters.append(
        (
            "end.ID",
            {
                "register": end,
                "description": "end of the model chain",
                "type": "uint16",
                "access": "read-only",
                "default": END,
            },
            here,
        )
    )
    parameters.append(
        (
            "end.L",
            {
                "register": end + 1,
                "description": "end of the model chain",
                "type": "uint16",
                "access": "read-only",
                "default": 0,
            },
            here,
        )
    )
    identity[:0] = [
        {"register": first - 2, "raw": MARKER[0], "description": "'Su' of the SunS marker"},
        {"register": first - 1, "raw": MARKER[1], "description": "'nS' of the SunS marker"},
    ]
    header = {
        "profile": profile_id or "sunspec-device",
        "description": f"SunSpec device with models {', '.join(ids)} (its model chain from 'SunS' at "
        f"{first - 2}), imported from {source} and pysunspec2's model definitions",
        "addressing": "address",
        "identity": identity,
    }
    return Draft(header, parameters, tables), warnings
