"""Loading profiles from YAML: schema + semantic checks with FILE:LINE:COL diagnostics."""

from __future__ import annotations

import hashlib
import os
from dataclasses import replace
from decimal import Decimal
from typing import Any

from ..load import schema, yamlsrc
from ..load.diagnostics import Diagnostic, InputError, UsageError
from ..load.durations import parse_duration
from . import codec, model, units
from .model import (
    IDENTITY_OBJECTS,
    CommitAction,
    HealthCheck,
    IdentityCheck,
    IdentityObject,
    Limits,
    Parameter,
    Precondition,
    Profile,
)

# ---- loading ------------------------------------------------------------------------------

_BUILTIN_DIR = os.path.join(os.path.dirname(os.path.dirname(__file__)), "profiles")


def builtin_profile_ids() -> list[str]:
    return sorted(f[: -len(".yaml")] for f in os.listdir(_BUILTIN_DIR) if f.endswith(".yaml"))


def unknown_profile(id_: str, relative_to: str | os.PathLike[str] | None = None, kind: str = "recipe") -> str:
    """Why ``id_`` names no profile, and how to name a profile file instead (users often forget '.yaml').

    ``kind``: what ``relative_to`` is (paths in a recipe or an inventory are relative to that file).
    """
    known = ", ".join(builtin_profile_ids())
    base = _profile_base(relative_to)
    where = f"the {kind}" if relative_to else "the current directory"
    guess = next((id_ + ext for ext in (".yaml", ".yml") if os.path.isfile(os.path.join(base, id_ + ext))), None)
    hint = f"did you mean '{guess}'?" if guess else f"e.g. '{id_}.yaml'"
    return (f"unknown built-in profile '{id_}' (built-in: {known}); a profile file works too: "
            f"its path relative to {where}, ending in .yaml, {hint}")


def builtin_profile(id_: str) -> Profile:
    path = os.path.join(_BUILTIN_DIR, f"{id_}.yaml")
    if not os.path.isfile(path):
        raise UsageError(unknown_profile(id_))
    prof = load_profile_file(path)
    return replace(prof, source=None)


def _profile_base(relative_to: str | os.PathLike[str] | None) -> str:
    return os.path.dirname(os.path.abspath(os.fspath(relative_to))) if relative_to else os.getcwd()


def is_profile_path(ref: str) -> bool:
    """Whether a profile reference names a file (else it is a built-in id)."""
    return ref.endswith((".yaml", ".yml", ".json")) or os.sep in ref or "/" in ref


def resolve_profile(ref: str, relative_to: str | os.PathLike[str] | None = None, kind: str = "recipe") -> Profile:
    """A built-in id, or a profile file (relative to the directory of ``relative_to``, a ``kind`` file)."""
    if not is_profile_path(ref):
        if not os.path.isfile(os.path.join(_BUILTIN_DIR, f"{ref}.yaml")):
            raise UsageError(unknown_profile(ref, relative_to, kind))
        return builtin_profile(ref)
    return load_profile_file(os.path.normpath(os.path.join(_profile_base(relative_to), ref)))


def parse_register(value: object) -> int:
    """1103 / 0x1103 (YAML int) / "1103h" / "0x1103" -> int."""
    if isinstance(value, int):
        return value
    text = str(value).strip()
    if text[-1:] in "hH":
        return int(text[:-1], 16)
    if text[:2].lower() == "0x":
        return int(text[2:], 16)
    return int(text)


# modicon references: the leading digit names the table (0xxxx coils, 1xxxx discrete inputs,
# 3xxxx input registers, 4xxxx holding registers)
_MODICON_DIGIT = {"coil": 0, "discrete": 1, "input": 3, "holding": 4}
_TABLE_WORDS = {"coil": "coil", "discrete": "discrete-input", "input": "input-register", "holding": "holding-register"}
_PLURAL = {"coil": "coils", "discrete": "discrete inputs", "input": "input registers", "holding": "holding registers"}


def wire_address(number: int, addressing: str, register_type: str = "holding") -> int:
    """Profile address -> 0-based protocol address. Raises ValueError with a user message."""
    if addressing == "address":
        return number
    if addressing == "register-number":
        if number < 1:
            raise ValueError(f"register number {number} is below 1 (addressing: register-number)")
        return number - 1
    # modicon: Dxxxx (5 digits) or Dxxxxx (6 digits), D the table's digit. A coil's 0xxxx/0xxxxx
    # reference is, as a number, just 1..65536.
    d = _MODICON_DIGIT[register_type]
    if d == 0 and 1 <= number <= 65536:
        return number - 1
    if d and d * 10000 + 1 <= number <= d * 10000 + 9999:
        return number - d * 10000 - 1
    if d and d * 100000 + 1 <= number <= d * 100000 + 65536:
        return number - d * 100000 - 1
    other = _modicon_table(number)
    if other == "input" and register_type == "holding":
        hint = "; 3xxxx references are input registers, which cannot be written"
    elif other is not None and other != "coil":
        hint = f"; {_MODICON_DIGIT[other]}xxxx references are {_PLURAL[other]}: set register_type: {other}"
    elif register_type == "holding" and number < 40001:
        hint = "; for 0-based addresses use addressing: address, for 1-based numbers addressing: register-number"
    else:
        hint = ""
    if d == 0:
        accepts = "00001-65536 (addresses 0-65535)"
    else:
        lo5, lo6 = d * 10000 + 1, d * 100000 + 1
        accepts = (f"{lo5:05d}-{lo5 + 9998:05d} (5 digits, addresses 0-9998) or {lo6:06d}-{lo6 + 65535:06d} "
                   "(6 digits, addresses 0-65535)")
    raise ValueError(f"{number} is not a {_TABLE_WORDS[register_type]} reference: addressing: modicon accepts "
                     f"{accepts}{hint}")


def _modicon_table(number: int) -> str | None:
    """The table a modicon reference's leading digit names (None: no reference at all)."""
    for table, d in _MODICON_DIGIT.items():
        if d and (d * 10000 + 1 <= number <= d * 10000 + 9999 or d * 100000 + 1 <= number <= d * 100000 + 65536):
            return table
    return "coil" if 1 <= number <= 9999 else None


def _hex(n: int) -> str:
    return f"0x{n:04X}"


def load_profile(ref: str | os.PathLike[str]) -> Profile:
    """A profile by reference: a built-in id (``example-inverter``) or a profile file's path.

    Raises InputError (an invalid file, every problem with its position) or UsageError (an
    unknown built-in id). A reference is a file when it ends in .yaml/.yml/.json or has a slash.
    """
    return resolve_profile(os.fspath(ref))


def load_profile_file(path: str | os.PathLike[str], text: str | None = None) -> Profile:
    """Load and check a profile file (or ``text`` shown as that file); all problems at once as an InputError."""
    p = os.fspath(path)
    if text is None:
        text = yamlsrc.read_text(p)
    data, src = yamlsrc.load(p, text)
    return profile_from_data(p, text, data, src)


def profile_from_data(path: str, text: str, data: Any, src: yamlsrc.Source) -> Profile:
    """A profile from its text already read as data (the importers compare that data with what they wrote)."""
    if not isinstance(data, dict):
        raise InputError([src.error((), "a profile must be a mapping (profile: ..., parameters: ...)")])
    errors = schema.validate(data, "profile", src)
    if errors:
        raise InputError(errors)
    return replace(_build_profile(data, src), digest=hashlib.sha256(text.encode("utf-8")).hexdigest())


def profile_ref(profile: Profile) -> str:
    """The one well-defined name of a profile: its file's absolute path, or its built-in id."""
    return profile.source or profile.id


def _build_profile(data: dict[str, Any], src: yamlsrc.Source) -> Profile:
    errors: list[Diagnostic] = []
    addressing = data.get("addressing", "address")
    rounding = data.get("rounding")
    limit_data = dict(data.get("limits", {}))
    for key in ("pause_after_connect", "pause_between_requests"):
        if key in limit_data:
            try:
                limit_data[key] = round(parse_duration(limit_data[key], bare="ms") * 1000)
            except ValueError as e:
                errors.append(src.error(("limits", key), f"limits.{key}: {e}"))
                limit_data[key] = 0
    limits = Limits(**limit_data)
    if limits.write_registers < 1:
        errors.append(src.error(("limits",), "limits leave no room for a single register per write"))

    def address_of(value: object, at: yamlsrc.Path_, extra: int = 0, register_type: str = "holding") -> int | None:
        try:
            number = parse_register(value)
        except ValueError:
            errors.append(src.error(at, f"not a register: {value!r}"))
            return None
        try:
            wire = wire_address(number, addressing, register_type) + extra
        except ValueError as e:  # the message says which references the addressing accepts
            errors.append(src.error(at, str(e)))
            return None
        if wire > 0xFFFF:
            errors.append(src.error(at, f"wire address {wire} is beyond 65535"))
            return None
        return wire

    params: list[Parameter] = []

    default_layout = _layout(data, ("big", False), (), src, errors)

    def make(name: str, spec: dict[str, Any], address: int, at: yamlsrc.Path_,
             eng_offset: object = 0) -> None:
        table = spec.get("register_type", "holding")
        local: list[Diagnostic] = []
        if "type" not in spec and table not in model.BIT_TABLES:
            local.append(src.error(at, f"{name}: 'type' is required for {_PLURAL[table]} (uint16, int32, "
                                       "float32 ...); only coils and discrete inputs are bool without it"))
        type_ = spec.get("type", codec.BOOL if table in model.BIT_TABLES else "uint16")
        order, swap = _layout(spec, default_layout, at, src, local)
        access = spec.get("access", "read-only" if table in ("discrete", "input") else "read-write")
        mask = 0
        if table in model.BIT_TABLES:
            if type_ != codec.BOOL:
                local.append(src.error((*at, "type"), f"a {table} is one bit: type bool (or no type), not {type_}"))
            for key in ("bits", "mask", "scale", "offset", "unit", "count", "encoding", "padding",
                        "byte_order", "swap", "word_order"):
                if key in spec:
                    local.append(src.error((*at, key), f"'{key}' does not apply to a {table} (one bit, 0 or 1)"))
        if table in ("discrete", "input") and access != "read-only":
            what = "a discrete input" if table == "discrete" else "an input register"
            local.append(src.error((*at, "access"), f"{what} is read-only (it cannot be written)"))
        if table in model.BIT_TABLES:
            pass
        elif "bits" in spec or "mask" in spec:
            try:
                mask = codec.parse_bits(spec["bits"]) if "bits" in spec else int(spec["mask"])
                codec.mask_shift(mask)
            except ValueError as e:
                local.append(src.error((*at, "bits" if "bits" in spec else "mask"), str(e)))
                mask = 0xFFFF
            if type_ not in ("uint16", "int16", codec.BOOL):
                local.append(src.error((*at, "type"), f"a bit field is uint16, int16 or bool, not {type_}"))
            elif type_ == codec.BOOL and mask and mask & (mask - 1):
                local.append(src.error((*at, "type"), "a bool field is one bit"))
            if spec.get("access") == "write-only":  # its register is written whole: the other bits come from a read
                local.append(src.error((*at, "access"), "a bit field must be readable: apply reads its register "
                                                        "to keep the other bits"))
        elif type_ == codec.BOOL:
            local.append(src.error((*at, "type"), "type bool is a one-bit field: give 'bits: N'"))
        if type_ == codec.STRING:
            if "count" not in spec:
                local.append(src.error(at, f"{name}: a string needs 'count' (its registers)"))
            for key in ("scale", "unit", "min", "max", "values"):
                if key in spec:
                    local.append(src.error((*at, key), f"'{key}' does not apply to a string"))
        elif "count" in spec or "encoding" in spec or "padding" in spec:
            key = next(k for k in ("count", "encoding", "padding") if k in spec)
            local.append(src.error((*at, key), f"'{key}' applies to strings only (type: string)"))
        param = Parameter(
            name=name,
            address=address,
            type=type_,
            word_order=order,
            byte_swap=swap,
            scale=Decimal(spec.get("scale", 1)),
            offset=Decimal(eng_offset),  # type: ignore[arg-type]
            unit=units.normalize(spec["unit"]) if "unit" in spec else None,
            min=_dec(spec.get("min")),
            max=_dec(spec.get("max")),
            access=access,
            values=tuple((str(k), int(v)) for k, v in (spec.get("values") or {}).items()),
            stage=int(spec.get("stage", 0)),
            rounding=spec.get("rounding", rounding),
            description=spec.get("description", ""),
            line=src.pos(at, key=True)[0],
            col=src.pos(at, key=True)[1],
            mask=mask,
            size=int(spec.get("count", 1)),
            encoding=spec.get("encoding", "ascii"),
            padding=spec.get("padding", "nul"),
            restart=bool(spec.get("restart", False)),
            register_type=table,
        )
        if local:  # the rest of the checks assume a well-formed parameter
            errors.extend(local)
            params.append(param)
            return
        if param.scale == 0:
            local.append(src.error((*at, "scale"), "scale must not be 0"))
        if address + param.count > 0x10000:
            local.append(src.error(at, f"{name}: registers {address}..{address + param.count - 1} run past 65535"))
        if "unit" in spec:
            problem = units.check(spec["unit"])
            if problem:
                local.append(src.error((*at, "unit"), problem))
        if param.min is not None and param.max is not None and param.min > param.max:
            local.append(src.error((*at, "min"), f"min {param.min} is greater than max {param.max}"))
        if not local:
            for key in ("min", "max"):
                bound = getattr(param, key)
                if bound is None:
                    continue
                try:
                    param.to_raw(bound, rounding="nearest")
                except codec.CodecError as e:
                    local.append(src.error((*at, key), f"{key} {_fmt(bound)} is not representable: {e}"))
        rng = param.type_range()
        for label, raw in param.values:
            if rng and not rng[0] <= raw <= rng[1]:
                width = codec.mask_shift(mask)[1] if mask else 0
                what = f"{width} bit{'s' if width != 1 else ''}" if mask else type_
                local.append(src.error((*at, "values", label), f"value {raw} of '{label}' does not fit in {what}"))
        if "default" in spec and not local and param.is_string:
            try:
                param.encode_text(str(spec["default"]))
                param = replace(param, default=str(spec["default"]))
            except codec.CodecError as e:
                local.append(src.error((*at, "default"), f"default: {e}"))
        elif "default" in spec and not local:
            d = spec["default"]
            try:
                if isinstance(d, bool):
                    default_eng = Decimal(int(d))
                elif isinstance(d, str):
                    labels = dict(param.values)
                    if d not in labels:
                        raise codec.CodecError(f"'{d}' is not one of the labels {', '.join(labels) or '(none)'}")
                    default_eng = codec.from_raw(labels[d], param.scale, param.offset)
                else:
                    default_eng = Decimal(d)
                    param.to_raw(default_eng)
                if (param.min is not None and default_eng < param.min) or (
                    param.max is not None and default_eng > param.max
                ):
                    raise codec.CodecError(f"{_fmt(default_eng)} is outside {_fmt(param.min)}..{_fmt(param.max)}")
                param = replace(param, default=default_eng)
            except codec.CodecError as e:
                local.append(src.error((*at, "default"), f"default: {e}"))
        errors.extend(local)
        params.append(param)

    for name, spec in (data.get("parameters") or {}).items():
        at: yamlsrc.Path_ = ("parameters", name)
        addr = address_of(spec["register"], (*at, "register"), register_type=spec.get("register_type", "holding"))
        if addr is not None:
            make(name, spec, addr, at, spec.get("offset", 0))

    # hostile input: tables multiply (count x fields); refuse before building millions of parameters
    declared = len(data.get("parameters") or {})
    for tname, table in (data.get("tables") or {}).items():
        declared += int(table["count"]) * len(table["fields"])
        if declared > yamlsrc.MAX_ENTRIES:
            errors.append(src.error(("tables", tname, "count"),
                                    f"table {tname}: the profile would declare at least {declared} parameters; at "
                                    f"most {yamlsrc.MAX_ENTRIES} (a device has {yamlsrc.MAX_ENTRIES} registers)"))
            raise InputError(errors)

    for tname, table in (data.get("tables") or {}).items():
        tat: yamlsrc.Path_ = ("tables", tname)
        table_types = {f.get("register_type", "holding") for f in table["fields"].values()}
        if len(table_types) > 1:
            errors.append(src.error((*tat, "fields"), f"table {tname}: its fields are in one Modbus table "
                                                      f"(register_type), not {', '.join(sorted(table_types))}"))
            continue
        base = address_of(table["base"], (*tat, "base"), register_type=table_types.pop() if table_types else "holding")
        if base is None:
            continue
        count, stride = table["count"], table["stride"]
        last_end = base + (count - 1) * stride + max(
            f["offset"] + _spec_count(f) for f in table["fields"].values()
        )
        if last_end > 0x10000:
            errors.append(src.error(tat, f"table {tname}: entry {count - 1} ends at register {last_end - 1}, "
                                         "beyond 65535"))
            continue
        for fname, fspec in table["fields"].items():
            if fspec["offset"] + _spec_count(fspec) > stride:
                errors.append(src.error((*tat, "fields", fname, "offset"),
                                        f"field {fname} runs past the table's stride {stride}"))
        for i in range(count):
            for fname, fspec in table["fields"].items():
                make(f"{tname}[{i}].{fname}", fspec, base + i * stride + fspec["offset"],
                     (*tat, "fields", fname))

    # overlapping registers: name both parameters and both lines. Bit fields of one register
    # share it when their bits do not overlap; a field never shares with a whole-register value.
    # each Modbus table is its own address space: sort by key (table, address)
    params.sort(key=lambda q: (q.key, q.line, q.name))  # of two at one address, the later one is reported
    prev: Parameter | None = None
    reported = 0
    fields_at: dict[int, list[Parameter]] = {}
    for q in params:
        if prev is not None and prev.register_type != q.register_type:
            prev = None  # another table: another address space
        if q.mask and prev is not None and prev.mask and prev.address == q.address:
            mates = fields_at[q.address]
            clash = next((f for f in mates if f.mask & q.mask), None)
            if clash is not None:
                errors.append(Diagnostic(src.path, q.line, q.col,
                                         f"{q.name} (bits {_bits(q.mask)} of register {_hex(q.address)}) overlaps "
                                         f"{clash.name} (bits {_bits(clash.mask)}, line {clash.line})"))
            other = next((f for f in mates if f.stage != q.stage), None)
            if other is not None:
                errors.append(Diagnostic(src.path, q.line, q.col,
                                         f"{q.name} is in stage {q.stage} but {other.name} (line {other.line}) of the "
                                         f"same register {_hex(q.address)} is in stage {other.stage}: a register is "
                                         "written as one unit"))
            mates.append(q)
            continue
        if q.mask:
            fields_at[q.address] = [q]
        if prev is not None and q.address < prev.end and (q.mask or prev.mask) and reported < 20:
            if q.mask:
                what = (f"{q.name} (bits {_bits(q.mask)} of register {_hex(q.address)}) shares its register with "
                        f"{prev.name} (line {prev.line}), which is not a bit field")
            else:
                what = (f"{q.name} (registers {_hex(q.address)}-{_hex(q.end - 1)}) overlaps the bit field {prev.name} "
                        f"(bits {_bits(prev.mask)} of register {_hex(prev.address)}, line {prev.line})")
            errors.append(Diagnostic(src.path, q.line, q.col, f"{what}: only bit fields share a register"))
            reported += 1
        elif prev is not None and q.address < prev.end:
            if reported < 20:  # a bad table can overlap thousands of times; the first ones say it
                errors.append(Diagnostic(
                    src.path, q.line, q.col,
                    f"{q.name} ({_span(q)}) overlaps {prev.name} ({_span(prev)}, line {prev.line})"))
            reported += 1
        if prev is None or q.end > prev.end:
            prev = q

    identity = []
    identity_objects = []
    for i, item in enumerate(data.get("identity") or []):
        if ("register" in item) == ("object" in item):
            errors.append(src.error(("identity", i), "an identity check is either {register: R, raw: N} or "
                                                     "{object: vendor|product_code|revision|..., equals: TEXT}"))
            continue
        if "object" in item:
            obj = item["object"]
            oid = IDENTITY_OBJECTS[obj] if isinstance(obj, str) else int(obj)
            identity_objects.append(IdentityObject(oid, str(item["equals"]).strip(), item.get("description", "")))
            continue
        table = item.get("register_type", "holding")
        a = address_of(item["register"], ("identity", i, "register"), register_type=table)
        if a is not None:
            identity.append(IdentityCheck(a, int(item["raw"]), item.get("description", ""), table))
    def actions(key: str) -> tuple[CommitAction, ...]:
        out = []
        for i, item in enumerate(data.get(key) or []):
            at2: yamlsrc.Path_ = (key, i)
            a = address_of(item["register"], (*at2, "register"))
            raw = item["raw"]
            try:
                regs = tuple(int(r) for r in raw) if isinstance(raw, list) else codec.encode(
                    int(raw), item.get("type", "uint16"), default_layout[0], default_layout[1])
            except codec.CodecError as e:
                errors.append(src.error((*at2, "raw"), str(e)))
                continue
            if a is not None:
                out.append(CommitAction(a, regs, item.get("description", ""), int(item.get("wait", 0))))
        return tuple(out)

    preconditions = []
    for i, item in enumerate(data.get("preconditions") or []):
        at3: yamlsrc.Path_ = ("preconditions", i)
        a = address_of(item["register"], (*at3, "register"))
        try:
            mask = codec.parse_bits(item["bits"]) if "bits" in item else int(item.get("mask", 0xFFFF))
            lo, hi = codec.field_range(mask)
        except ValueError as e:
            errors.append(src.error((*at3, "bits" if "bits" in item else "mask"), str(e)))
            continue
        if not lo <= int(item["equals"]) <= hi:
            errors.append(src.error((*at3, "equals"),
                                    f"{item['equals']} does not fit in the selected bits ({lo}..{hi})"))
        elif a is not None:
            preconditions.append(Precondition(a, mask, int(item["equals"]), item.get("description", "")))
    health = []
    for i, item in enumerate(data.get("health") or []):
        at4: yamlsrc.Path_ = ("health", i)
        a = address_of(item["register"], (*at4, "register"), register_type=item.get("register_type", "holding"))
        try:
            mask = codec.parse_bits(item["bits"]) if "bits" in item else int(item.get("mask", 0xFFFF))
            lo, hi = codec.field_range(mask)
        except ValueError as e:
            errors.append(src.error((*at4, "bits" if "bits" in item else "mask"), str(e)))
            continue
        bad = not any(k in item for k in ("equals", "min", "max"))
        if bad:
            errors.append(src.error(at4, "a health check needs 'equals' (a value) or 'min'/'max' (a raw range)"))
        for key in ("equals", "min", "max"):
            if key in item and not lo <= int(item[key]) <= hi:
                errors.append(src.error((*at4, key), f"{item[key]} does not fit in the selected bits ({lo}..{hi})"))
                bad = True
        if "equals" in item and ("min" in item or "max" in item):
            bound = "min" if "min" in item else "max"
            errors.append(src.error((*at4, bound), f"'equals' and '{bound}' exclude each other: a check is one "
                                                   "value or a range"))
            bad = True
        elif "min" in item and "max" in item and int(item["min"]) > int(item["max"]):
            errors.append(src.error((*at4, "min"), f"min {item['min']} is greater than max {item['max']}"))
            bad = True
        if a is not None and not bad:
            health.append(HealthCheck(a, mask, _int_or_none(item.get("equals")), _int_or_none(item.get("min")),
                                      _int_or_none(item.get("max")), item.get("register_type", "holding"),
                                      item.get("description", "")))
    stage_waits = tuple((int(w["stage"]), int(w["wait"])) for w in data.get("stages") or [])
    seen_stages: dict[int, int] = {}
    for i, (stage, _) in enumerate(stage_waits):
        if stage in seen_stages:
            errors.append(src.error(("stages", i, "stage"),
                                    f"stage {stage} is already set (stages item {seen_stages[stage]})"))
        seen_stages.setdefault(stage, i)
    commits, unlock, lock = actions("commit"), actions("unlock"), actions("lock")
    if errors:
        raise InputError(errors)
    return Profile(
        id=str(data["profile"]),
        description=str(data.get("description", "")),
        addressing=addressing,
        word_order=default_layout[0],
        byte_swap=default_layout[1],
        limits=limits,
        identity=tuple(identity),
        identity_objects=tuple(identity_objects),
        parameters=tuple(params),
        commit=commits,
        source=os.path.abspath(src.path),
        preconditions=tuple(preconditions),
        unlock=unlock,
        lock=lock,
        stage_waits=stage_waits,
        health=tuple(health),
    )


def _int_or_none(v: object) -> int | None:
    return None if v is None else int(v)  # type: ignore[call-overload]


def _dec(v: object) -> Decimal | None:
    return None if v is None else Decimal(v)  # type: ignore[arg-type]


def _fmt(d: Decimal | None) -> str:
    return "-" if d is None else codec.format_decimal(d)


def _spec_count(spec: dict[str, Any]) -> int:
    """Registers a parameter spec occupies, before it is checked (strings: count, bit fields, coils: 1)."""
    type_ = spec.get("type", codec.BOOL)
    if type_ == codec.STRING:
        return int(spec.get("count", 1))
    if type_ == codec.BOOL or "bits" in spec or "mask" in spec or spec.get("register_type") in model.BIT_TABLES:
        return 1
    return codec.register_count(type_)


def _span(p: Parameter) -> str:
    """'registers 0x0010-0x0011', 'input registers 0x0010-0x0011', 'coil 0x0005'."""
    if p.is_bit:
        return f"{'coil' if p.register_type == 'coil' else 'discrete input'} {_hex(p.address)}"
    what = "input registers" if p.register_type == "input" else "registers"
    return f"{what} {_hex(p.address)}-{_hex(p.end - 1)}"


def _bits(mask: int) -> str:
    shift, width = codec.mask_shift(mask)
    return str(shift) if width == 1 else f"{shift}..{shift + width - 1}"


def _layout(spec: dict[str, Any], default: tuple[str, bool], at: yamlsrc.Path_, src: yamlsrc.Source,
            errors: list[Diagnostic]) -> tuple[str, bool]:
    """(word_order, byte_swap) from ``byte_order`` (ABCD ...), ``swap`` (Home Assistant) or ``word_order``."""
    given = [k for k in ("byte_order", "swap", "word_order") if k in spec]
    if len(given) > 1:
        errors.append(src.error((*at, given[1]), f"'{given[0]}' and '{given[1]}' both set the layout: keep one"))
    if "byte_order" in spec:
        return codec.LAYOUTS[spec["byte_order"]]
    if "swap" in spec:
        return codec.SWAPS[spec["swap"]]
    if "word_order" in spec:
        return str(spec["word_order"]), default[1]
    return default
