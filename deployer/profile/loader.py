"""Loading profiles from YAML: schema + semantic checks with FILE:LINE:COL diagnostics."""

from __future__ import annotations

import hashlib
import os
from dataclasses import replace
from decimal import Decimal
from typing import Any

from ..errors import CodecError, Diagnostic, InputError, UsageError
from ..load import messages, schema, yamlsrc
from ..load.durations import parse_duration
from . import codec, firmware, model, units, values
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
    return (
        f"unknown built-in profile '{id_}' (built-in: {known}); a profile file works too: "
        f"its path relative to {where}, ending in .yaml, {hint}"
    )


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
        accepts = (
            f"{lo5:05d}-{lo5 + 9998:05d} (5 digits, addresses 0-9998) or {lo6:06d}-{lo6 + 65535:06d} "
            "(6 digits, addresses 0-65535)"
        )
    raise ValueError(
        f"{number} is not a {_TABLE_WORDS[register_type]} reference: addressing: modicon accepts {accepts}{hint}"
    )


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


class _Checks:
    """What the validators of one profile share: where the file is, how it counts registers, the errors."""

    def __init__(self, data: dict[str, Any], src: yamlsrc.Source) -> None:
        self.data = data
        self.src = src
        self.errors: list[Diagnostic] = []
        self.addressing: str = data.get("addressing", "address")
        self.rounding = data.get("rounding")
        self.layout = _layout(data, ("big", False), (), src, self.errors)

    def error(self, at: yamlsrc.Path_, message: str) -> None:
        self.errors.append(self.src.error(at, message))

    def address_of(
        self, value: object, at: yamlsrc.Path_, extra: int = 0, register_type: str = "holding"
    ) -> int | None:
        """A register reference as the profile's addressing counts it -> its wire address (None: an error)."""
        try:
            number = parse_register(value)
        except ValueError:
            self.error(at, f"not a register: {value!r}")
            return None
        try:
            wire = wire_address(number, self.addressing, register_type) + extra
        except ValueError as e:  # the message says which references the addressing accepts
            self.error(at, str(e))
            return None
        if wire > 0xFFFF:
            self.error(at, f"wire address {wire} is beyond 65535")
            return None
        return wire


def _build_profile(data: dict[str, Any], src: yamlsrc.Source) -> Profile:
    c = _Checks(data, src)
    limits = _limits(c)
    params = _parameters(c)
    _tables(c, params)
    _overlaps(c, params)
    identity, identity_objects = _identity(c)
    preconditions = _preconditions(c)
    health = _health(c, params)
    stage_waits = _stages(c)
    commits, unlock, lock = _actions(c, "commit"), _actions(c, "unlock"), _actions(c, "lock")
    fw = _firmware(c, params)
    if c.errors:
        raise InputError(c.errors)
    return Profile(
        id=str(data["profile"]),
        description=str(data.get("description", "")),
        addressing=c.addressing,  # type: ignore[arg-type]
        word_order=c.layout[0],
        byte_swap=c.layout[1],
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
        endurance=int(data["endurance"]) if "endurance" in data else None,
        firmware=fw,
    )


def _limits(c: _Checks) -> Limits:
    limit_data = dict(c.data.get("limits", {}))
    for key in ("pause_after_connect", "pause_between_requests"):
        if key in limit_data:
            try:
                limit_data[key] = round(parse_duration(limit_data[key], bare="ms") * 1000)
            except ValueError as e:
                c.error(("limits", key), f"limits.{key}: {e}")
                limit_data[key] = 0
    limits = Limits(**limit_data)
    if limits.write_registers < 1:
        c.error(("limits",), "limits leave no room for a single register per write")
    return limits


# ---- parameters ---------------------------------------------------------------------------------

_NOT_FOR_BITS = (
    "bits",
    "mask",
    "scale",
    "offset",
    "unit",
    "cycles_as_angles",
    "count",
    "encoding",
    "padding",
    "byte_order",
    "swap",
    "word_order",
)


def _parameters(c: _Checks) -> list[Parameter]:
    params: list[Parameter] = []
    for name, spec in (c.data.get("parameters") or {}).items():
        at: yamlsrc.Path_ = ("parameters", name)
        addr = c.address_of(spec["register"], (*at, "register"), register_type=spec.get("register_type", "holding"))
        if addr is not None:
            params.append(_parameter(c, name, spec, addr, at, spec.get("offset", 0)))
    return params


def _parameter(
    c: _Checks, name: str, spec: dict[str, Any], address: int, at: yamlsrc.Path_, eng_offset: object = 0
) -> Parameter:
    """One parameter (a table entry's field too); its problems go to ``c.errors``."""
    table = spec.get("register_type", "holding")
    src = c.src
    local: list[Diagnostic] = []
    if "type" not in spec and table not in model.BIT_TABLES:
        local.append(
            src.error(
                at,
                f"{name}: 'type' is required for {_PLURAL[table]} (uint16, int32, "
                "float32 ...); only coils and discrete inputs are bool without it",
            )
        )
    type_ = spec.get("type", codec.BOOL if table in model.BIT_TABLES else "uint16")
    order, swap = _layout(spec, c.layout, at, src, local)
    access = spec.get("access", "read-only" if table in ("discrete", "input") else "read-write")
    local += _shape_problems(src, spec, at, table, type_, access)
    mask = _mask(src, spec, at, table, local)
    param = Parameter(
        name=name,
        address=address,
        type=type_,
        word_order=order,
        byte_swap=swap,
        scale=Decimal(spec.get("scale", 1)),
        offset=Decimal(eng_offset),  # type: ignore[arg-type]
        unit=units.normalize(spec["unit"]) if "unit" in spec else None,
        cycles_as_angles=bool(spec.get("cycles_as_angles", False)),
        min=_dec(spec.get("min")),
        max=_dec(spec.get("max")),
        access=access,
        values=tuple((str(k), int(v)) for k, v in (spec.get("values") or {}).items()),
        stage=int(spec.get("stage", 0)),
        rounding=spec.get("rounding", c.rounding),
        description=spec.get("description", ""),
        line=src.pos(at, key=True)[0],
        col=src.pos(at, key=True)[1],
        mask=mask,
        size=int(spec.get("count", 1)),
        encoding=spec.get("encoding", "ascii"),
        padding=spec.get("padding", "nul"),
        restart=bool(spec.get("restart", False)),
        per_unit=bool(spec.get("per_unit", False)),
        tolerance=Decimal(str(spec.get("tolerance", 0))),
        endurance=int(spec["endurance"]) if "endurance" in spec else None,
        register_type=table,
        firmware=None if spec.get("firmware") is None else str(spec["firmware"]),
        action=bool(spec.get("action", False)),
        **_manual(spec),
    )
    if local:  # the rest of the checks assume a well-formed parameter
        c.errors.extend(local)
        return param
    local = _range_problems(src, param, spec, at)
    if "default" in spec and not local:
        param = _with_default(src, param, spec["default"], at, local)
    c.errors.extend(local)
    return param


def _manual(spec: dict[str, Any]) -> dict[str, str]:
    """``manual: {number: "3-41", text: Ramp 1 Ramp Up Time}``: the Parameter's manual_number and manual_text.
    A number written bare is kept as written (``22.10``: the YAML reader makes decimals from their text)."""
    m = spec.get("manual")
    if not isinstance(m, dict):
        return {}
    return {"manual_number": str(m.get("number", "")).strip(), "manual_text": str(m.get("text", "")).strip()}


def _shape_problems(
    src: yamlsrc.Source, spec: dict[str, Any], at: yamlsrc.Path_, table: str, type_: str, access: str
) -> list[Diagnostic]:
    """Keys that do not fit the parameter's table or type (a coil's scale, a string's unit ...)."""
    out: list[Diagnostic] = []
    if table in model.BIT_TABLES:
        if type_ != codec.BOOL:
            out.append(src.error((*at, "type"), f"a {table} is one bit: type bool (or no type), not {type_}"))
        out += [
            src.error((*at, key), f"'{key}' does not apply to a {table} (one bit, 0 or 1)")
            for key in _NOT_FOR_BITS
            if key in spec
        ]
    if table in ("discrete", "input") and access != "read-only":
        what = "a discrete input" if table == "discrete" else "an input register"
        out.append(src.error((*at, "access"), f"{what} is read-only (it cannot be written)"))
    if table not in model.BIT_TABLES and ("bits" in spec or "mask" in spec):
        if type_ not in ("uint16", "int16", codec.BOOL):
            out.append(src.error((*at, "type"), f"a bit field is uint16, int16 or bool, not {type_}"))
        if spec.get("access") == "write-only":  # its register is written whole: the other bits come from a read
            out.append(
                src.error(
                    (*at, "access"), "a bit field must be readable: apply reads its register to keep the other bits"
                )
            )
    elif table not in model.BIT_TABLES and type_ == codec.BOOL:
        out.append(src.error((*at, "type"), "type bool is a one-bit field: give 'bits: N'"))
    if type_ == codec.STRING:
        if "count" not in spec:
            out.append(src.error(at, f"{at[-1]}: a string needs 'count' (its registers)"))
        out += [
            src.error((*at, key), f"'{key}' does not apply to a string")
            for key in ("scale", "unit", "min", "max", "values")
            if key in spec
        ]
    elif "count" in spec or "encoding" in spec or "padding" in spec:
        key = next(k for k in ("count", "encoding", "padding") if k in spec)
        out.append(src.error((*at, key), f"'{key}' applies to strings only (type: string)"))
    return out


def _mask(src: yamlsrc.Source, spec: dict[str, Any], at: yamlsrc.Path_, table: str, local: list[Diagnostic]) -> int:
    """A bit field's mask (0: the whole value)."""
    if table in model.BIT_TABLES or not ("bits" in spec or "mask" in spec):
        return 0
    key = "bits" if "bits" in spec else "mask"
    try:
        mask = codec.parse_bits(spec["bits"]) if key == "bits" else int(spec["mask"])
        codec.mask_shift(mask)
    except ValueError as e:
        local.append(src.error((*at, key), str(e)))
        return 0xFFFF
    if spec.get("type") == codec.BOOL and mask & (mask - 1):
        local.append(src.error((*at, "type"), "a bool field is one bit"))
    return mask


def _range_problems(src: yamlsrc.Source, param: Parameter, spec: dict[str, Any], at: yamlsrc.Path_) -> list[Diagnostic]:
    """Scale, span, unit, min/max and the labels' raw values of a well-formed parameter."""
    out: list[Diagnostic] = []
    if param.scale == 0:
        out.append(src.error((*at, "scale"), "scale must not be 0"))
    if param.address + param.count > 0x10000:
        out.append(
            src.error(at, f"{param.name}: registers {param.address}..{param.address + param.count - 1} run past 65535")
        )
    problem = units.check(spec["unit"]) if "unit" in spec else None
    if problem:
        out.append(src.error((*at, "unit"), problem))
    elif param.cycles_as_angles and (param.unit is None or not units.turns_apply(param.unit)):
        out.append(
            src.error(
                (*at, "cycles_as_angles"),
                "'cycles_as_angles' is for a parameter whose unit is an "
                "angle (rad, deg, rad/s) or a cycle (rev, rpm, Hz)" + ("" if param.unit else "; this one has no unit"),
            )
        )
    why = None if param.firmware is None else firmware.check_range(param.firmware)
    if why:
        out.append(src.error((*at, "firmware"), f"firmware: {why}"))
    if param.action and not param.writable:
        out.append(src.error((*at, "action"), "an action is a command sent to the device: it must be writable"))
    if param.min is not None and param.max is not None and param.min > param.max:
        out.append(src.error((*at, "min"), f"min {param.min} is greater than max {param.max}"))
    if not out:
        for key in ("min", "max"):
            bound = getattr(param, key)
            try:
                if bound is not None:
                    param.to_raw(bound, rounding="nearest")
            except CodecError as e:
                out.append(src.error((*at, key), f"{key} {_fmt(bound)} is not representable: {e}"))
    rng = param.type_range()
    for label, raw in param.values:
        if rng and not rng[0] <= raw <= rng[1]:
            width = codec.mask_shift(param.mask)[1] if param.mask else 0
            what = f"{width} bit{'s' if width != 1 else ''}" if param.mask else param.type
            out.append(src.error((*at, "values", label), f"value {raw} of '{label}' does not fit in {what}"))
    return out


def _with_default(
    src: yamlsrc.Source, param: Parameter, d: object, at: yamlsrc.Path_, local: list[Diagnostic]
) -> Parameter:
    """``param`` with its factory default, checked like a recipe value."""
    try:
        if param.is_string:
            param.encode_text(str(d))
            return replace(param, default=str(d))
        if isinstance(d, bool):
            default_eng = Decimal(int(d))
        elif isinstance(d, str):
            labels = dict(param.values)
            if d not in labels:
                raise CodecError(f"'{d}' is not one of the labels {messages.label_list(labels) or '(none)'}")
            default_eng = codec.from_raw(labels[d], param.scale, param.offset)
        else:
            default_eng = Decimal(d)  # type: ignore[arg-type]
            param.to_raw(default_eng)
        if (param.min is not None and default_eng < param.min) or (param.max is not None and default_eng > param.max):
            raise CodecError(f"{_fmt(default_eng)} is outside {_fmt(param.min)}..{_fmt(param.max)}")
        return replace(param, default=default_eng)
    except CodecError as e:
        local.append(src.error((*at, "default"), f"default: {e}"))
        return param


def _tables(c: _Checks, params: list[Parameter]) -> None:
    """Table entries expanded into ``params`` (``name[i].field``)."""
    tables = c.data.get("tables") or {}
    # hostile input: tables multiply (count x fields); refuse before building millions of parameters
    declared = len(c.data.get("parameters") or {})
    for tname, table in tables.items():
        declared += int(table["count"]) * len(table["fields"])
        if declared > yamlsrc.MAX_ENTRIES:
            c.error(
                ("tables", tname, "count"),
                f"table {tname}: the profile would declare at least {declared} parameters; at "
                f"most {yamlsrc.MAX_ENTRIES} (a device has {yamlsrc.MAX_ENTRIES} registers)",
            )
            raise InputError(c.errors)
    for tname, table in tables.items():
        tat: yamlsrc.Path_ = ("tables", tname)
        table_types = {f.get("register_type", "holding") for f in table["fields"].values()}
        if len(table_types) > 1:
            c.error(
                (*tat, "fields"),
                f"table {tname}: its fields are in one Modbus table "
                f"(register_type), not {', '.join(sorted(table_types))}",
            )
            continue
        base = c.address_of(
            table["base"], (*tat, "base"), register_type=table_types.pop() if table_types else "holding"
        )
        if base is None:
            continue
        count, stride = table["count"], table["stride"]
        last_end = base + (count - 1) * stride + max(f["offset"] + _spec_count(f) for f in table["fields"].values())
        if last_end > 0x10000:
            c.error(tat, f"table {tname}: entry {count - 1} ends at register {last_end - 1}, beyond 65535")
            continue
        for fname, fspec in table["fields"].items():
            if fspec["offset"] + _spec_count(fspec) > stride:
                c.error((*tat, "fields", fname, "offset"), f"field {fname} runs past the table's stride {stride}")
        for i in range(count):
            for fname, fspec in table["fields"].items():
                params.append(
                    _parameter(
                        c, f"{tname}[{i}].{fname}", fspec, base + i * stride + fspec["offset"], (*tat, "fields", fname)
                    )
                )


def _overlaps(c: _Checks, params: list[Parameter]) -> None:
    """Overlapping registers: name both parameters and both lines. Bit fields of one register share it when
    their bits do not overlap; a field never shares with a whole-register value. Each Modbus table is its
    own address space: ``params`` ends sorted by key (table, address)."""
    params.sort(key=lambda q: (q.key, q.line, q.name))  # of two at one address, the later one is reported
    prev: Parameter | None = None
    reported = 0
    fields_at: dict[int, list[Parameter]] = {}
    for q in params:
        if prev is not None and prev.register_type != q.register_type:
            prev = None  # another table: another address space
        if q.mask and prev is not None and prev.mask and prev.address == q.address:
            _field_mates(c, q, fields_at[q.address])
            continue
        if q.mask:
            fields_at[q.address] = [q]
        if prev is not None and q.address < prev.end:
            if reported < 20:  # a bad table can overlap thousands of times; the first ones say it
                c.errors.append(Diagnostic(c.src.path, q.line, q.col, _overlap_text(q, prev)))
            reported += 1
        if prev is None or q.end > prev.end:
            prev = q


def _field_mates(c: _Checks, q: Parameter, mates: list[Parameter]) -> None:
    """A bit field beside other fields of its register: bits apart, and one stage."""
    clash = next((f for f in mates if f.mask & q.mask), None)
    if clash is not None:
        c.errors.append(
            Diagnostic(
                c.src.path,
                q.line,
                q.col,
                f"{q.name} (bits {_bits(q.mask)} of register {_hex(q.address)}) overlaps "
                f"{clash.name} (bits {_bits(clash.mask)}, line {clash.line})",
            )
        )
    other = next((f for f in mates if f.stage != q.stage), None)
    if other is not None:
        c.errors.append(
            Diagnostic(
                c.src.path,
                q.line,
                q.col,
                f"{q.name} is in stage {q.stage} but {other.name} (line {other.line}) of the "
                f"same register {_hex(q.address)} is in stage {other.stage}: a register is "
                "written as one unit",
            )
        )
    mates.append(q)


def _overlap_text(q: Parameter, prev: Parameter) -> str:
    if q.mask:
        return (
            f"{q.name} (bits {_bits(q.mask)} of register {_hex(q.address)}) shares its register with "
            f"{prev.name} (line {prev.line}), which is not a bit field: only bit fields share a register"
        )
    if prev.mask:
        return (
            f"{q.name} (registers {_hex(q.address)}-{_hex(q.end - 1)}) overlaps the bit field {prev.name} "
            f"(bits {_bits(prev.mask)} of register {_hex(prev.address)}, line {prev.line}): only bit fields "
            "share a register"
        )
    return f"{q.name} ({_span(q)}) overlaps {prev.name} ({_span(prev)}, line {prev.line})"


# ---- identity, preconditions, actions, stages ------------------------------------------------------------


def _identity(c: _Checks) -> tuple[list[IdentityCheck], list[IdentityObject]]:
    identity: list[IdentityCheck] = []
    identity_objects: list[IdentityObject] = []
    for i, item in enumerate(c.data.get("identity") or []):
        if ("register" in item) == ("object" in item):
            c.error(
                ("identity", i),
                "an identity check is either {register: R, raw: N} or "
                "{object: vendor|product_code|revision|..., equals: TEXT}",
            )
            continue
        if "object" in item:
            obj = item["object"]
            oid = IDENTITY_OBJECTS[obj] if isinstance(obj, str) else int(obj)
            identity_objects.append(IdentityObject(oid, str(item["equals"]).strip(), item.get("description", "")))
            continue
        table = item.get("register_type", "holding")
        a = c.address_of(item["register"], ("identity", i, "register"), register_type=table)
        if a is not None:
            identity.append(IdentityCheck(a, int(item["raw"]), item.get("description", ""), table))
    return identity, identity_objects


def _actions(c: _Checks, key: str) -> tuple[CommitAction, ...]:
    out = []
    for i, item in enumerate(c.data.get(key) or []):
        at: yamlsrc.Path_ = (key, i)
        table = item.get("register_type", "holding")
        a = c.address_of(item["register"], (*at, "register"), register_type=table)
        raw = item["raw"]
        secret = ""
        if isinstance(raw, dict):  # {env: NAME} or {file: PATH}: a password kept out of the profile
            secret, raw = _secret(c, raw, (*at, "raw"))
            if raw is None:
                continue
        if table == "coil":
            coil = _coil_value(c, item, raw, secret, at)
            if coil is not None and a is not None:
                out.append(
                    CommitAction(a, (coil,), item.get("description", ""), int(item.get("wait", 0)), secret, "coil")
                )
            continue
        if isinstance(raw, bool):
            c.error(
                (*at, "raw"),
                "true/false is a coil's value: a register's raw value is an integer (register_type: coil for a coil)",
            )
            continue
        try:
            regs = (
                tuple(int(r) for r in raw)
                if isinstance(raw, list)
                else codec.encode(int(raw), item.get("type", "uint16"), c.layout[0], c.layout[1])
            )
        except (CodecError, ValueError) as e:
            # a secret's value is never echoed: say where it came from
            c.error(
                (*at, "raw"), f"the value from {secret} does not fit {item.get('type', 'uint16')}" if secret else str(e)
            )
            continue
        if a is not None:
            out.append(CommitAction(a, regs, item.get("description", ""), int(item.get("wait", 0)), secret))
    return tuple(out)


def _coil_value(c: _Checks, item: dict[str, Any], raw: object, secret: str, at: yamlsrc.Path_) -> int | None:
    """A coil action's value, 0 or 1 (``raw: 1``, ``raw: true``); None after an error."""
    if "type" in item:
        c.error((*at, "type"), "a coil is one bit: 'type' does not apply (raw: 1 or 0, true or false)")
        return None
    if isinstance(raw, bool) or raw in (0, 1):
        return 1 if raw else 0
    c.error(
        (*at, "raw"),
        f"a coil is written 1 or 0 (true or false), not "
        f"{'the value from ' + secret if secret else messages.clipped_repr(raw)}",
    )
    return None


def _secret(c: _Checks, raw: dict[str, Any], at: yamlsrc.Path_) -> tuple[str, int | list[int] | None]:
    """(where it came from, the value: an integer, or registers written as '1 2 3') of ``{env: ...}``/``{file: ...}``.

    Read when the profile loads, so that a missing secret stops everything before the first byte."""
    if "env" in raw:
        name = str(raw["env"])
        where = f"environment variable {name}"
        text = os.environ.get(name)
        if text is None:
            c.error(at, f"{where} is not set (it holds this value; set it before running)")
            return where, None
    else:
        path = os.path.join(os.path.dirname(os.path.abspath(c.src.path)), os.path.expanduser(str(raw["file"])))
        where = f"file {raw['file']}"
        try:
            with open(path, encoding="utf-8") as f:
                text = f.read(4096)
        except OSError as e:
            c.error(at, f"cannot read {where}: {e.strerror or e}")
            return where, None
    words = text.split()
    try:
        value: int | list[int] = parse_register(words[0]) if len(words) == 1 else [parse_register(w) for w in words]
    except (ValueError, IndexError):
        c.error(at, f"{where} does not hold an integer (or registers separated by spaces)")
        return where, None
    return where, value


def _preconditions(c: _Checks) -> list[Precondition]:
    preconditions = []
    for i, item in enumerate(c.data.get("preconditions") or []):
        at: yamlsrc.Path_ = ("preconditions", i)
        a = c.address_of(item["register"], (*at, "register"))
        try:
            mask = codec.parse_bits(item["bits"]) if "bits" in item else int(item.get("mask", 0xFFFF))
            lo, hi = codec.field_range(mask)
        except ValueError as e:
            c.error((*at, "bits" if "bits" in item else "mask"), str(e))
            continue
        if not lo <= int(item["equals"]) <= hi:
            c.error((*at, "equals"), f"{item['equals']} does not fit in the selected bits ({lo}..{hi})")
        elif a is not None:
            preconditions.append(Precondition(a, mask, int(item["equals"]), item.get("description", "")))
    return preconditions


def _stages(c: _Checks) -> tuple[tuple[int, int], ...]:
    stage_waits = tuple((int(w["stage"]), int(w["wait"])) for w in c.data.get("stages") or [])
    seen_stages: dict[int, int] = {}
    for i, (stage, _) in enumerate(stage_waits):
        if stage in seen_stages:
            c.error(("stages", i, "stage"), f"stage {stage} is already set (stages item {seen_stages[stage]})")
        seen_stages.setdefault(stage, i)
    return stage_waits


def _firmware(c: _Checks, params: list[Parameter]) -> firmware.FirmwareSource | None:
    """``firmware:`` where the device says its revision; required once a parameter names revisions."""
    spec = c.data.get("firmware")
    gated = next((p for p in params if p.firmware is not None), None)
    if spec is None:
        # a parameter gated by firmware: the revision comes from Function 43 unless the profile says otherwise
        return firmware.FirmwareSource() if gated is not None else None
    at: yamlsrc.Path_ = ("firmware",)
    applies = None if spec.get("applies") is None else str(spec["applies"])
    why = None if applies is None else firmware.check_range(applies)
    if why:
        c.error((*at, "applies"), f"firmware.applies: {why}")
    if "register" in spec and "object" in spec:
        c.error(
            (*at, "register"), "firmware: the revision comes from an 'object' (Function 43) or a 'register', not both"
        )
        return None
    if "register" in spec:
        table = spec.get("register_type", "holding")
        a = c.address_of(spec["register"], (*at, "register"), register_type=table)
        if a is None:
            return None
        return firmware.FirmwareSource(None, a, int(spec.get("count", 1)), table, spec.get("format") == "text", applies)
    obj = spec.get("object", "revision")
    oid = IDENTITY_OBJECTS[obj] if isinstance(obj, str) else int(obj)
    return firmware.FirmwareSource(oid, applies=applies)


# ---- health checks ------------------------------------------------------------------------------------


def _health(c: _Checks, params: list[Parameter]) -> list[HealthCheck]:
    by_name = {p.name: p for p in params}
    health = []
    for i, item in enumerate(c.data.get("health") or []):
        at: yamlsrc.Path_ = ("health", i)
        if ("register" in item) == ("parameter" in item):
            c.error(
                at,
                "a health check names either a 'parameter' (values in its units or labels) or a "
                "'register' (raw values)",
            )
            continue
        if not any(k in item for k in ("equals", "min", "max")):
            c.error(at, "a health check needs 'equals' (a value) or 'min'/'max' (a range)")
            continue
        if "equals" in item and ("min" in item or "max" in item):
            bound = "min" if "min" in item else "max"
            c.error((*at, bound), f"'equals' and '{bound}' exclude each other: a check is one value or a range")
            continue
        check = _parameter_health(c, item, at, by_name) if "parameter" in item else _raw_health(c, item, at)
        if check is not None:
            health.append(check)
    return health


def _raw_health(c: _Checks, item: dict[str, Any], at: yamlsrc.Path_) -> HealthCheck | None:
    """``{register: R, bits: ..., equals/min/max: raw}``: raw values of a holding or input register, or a coil's
    or discrete input's bit (``equals: 0``, ``equals: false``)."""
    table = item.get("register_type", "holding")
    a = c.address_of(item["register"], (*at, "register"), register_type=table)
    if table in model.BIT_TABLES:
        return _bit_health(c, item, at, a, table)
    try:
        mask = codec.parse_bits(item["bits"]) if "bits" in item else int(item.get("mask", 0xFFFF))
        lo, hi = codec.field_range(mask)
    except ValueError as e:
        c.error((*at, "bits" if "bits" in item else "mask"), str(e))
        return None
    bad = False
    for key in ("equals", "min", "max"):
        v = item.get(key)
        if v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, int):
            c.error(
                (*at, key),
                f"{key}: a raw value is an integer, not {messages.clipped_repr(v)} (values in "
                "units or labels: name the parameter, {parameter: NAME, ...})",
            )
            bad = True
        elif not lo <= v <= hi:
            c.error((*at, key), f"{v} does not fit in the selected bits ({lo}..{hi})")
            bad = True
    if not bad and "min" in item and "max" in item and int(item["min"]) > int(item["max"]):
        c.error((*at, "min"), f"min {item['min']} is greater than max {item['max']}")
        bad = True
    if a is None or bad:
        return None
    return HealthCheck(
        a,
        mask,
        _int_or_none(item.get("equals")),
        _int_or_none(item.get("min")),
        _int_or_none(item.get("max")),
        table,
        item.get("description", ""),
    )


def _bit_health(c: _Checks, item: dict[str, Any], at: yamlsrc.Path_, a: int | None, table: str) -> HealthCheck | None:
    """``{register: 65, register_type: coil, equals: 0}``: one bit, healthy when it holds ``equals``."""
    for key in ("bits", "mask", "min", "max"):
        if key in item:
            c.error((*at, key), f"a {table} is one bit: '{key}' does not apply (equals: 0 or 1, true or false)")
            return None
    v = item.get("equals")
    if not (isinstance(v, bool) or v in (0, 1)):
        c.error((*at, "equals"), f"a {table} holds 0 or 1 (false or true), not {messages.clipped_repr(v)}")
        return None
    if a is None:
        return None
    return HealthCheck(a, 0xFFFF, int(v), None, None, table, item.get("description", ""))  # type: ignore[arg-type]


def _parameter_health(
    c: _Checks, item: dict[str, Any], at: yamlsrc.Path_, by_name: dict[str, Parameter]
) -> HealthCheck | None:
    """``{parameter: NAME, min: 450 V, max: 800 V}`` or ``{parameter: NAME, equals: none}``: the parameter's own
    type, scale, unit and labels, in any of the four tables."""
    name = str(item["parameter"])
    p = by_name.get(name)
    for key in ("register", "register_type", "bits", "mask"):
        if key in item:
            c.error((*at, key), f"'{key}' comes from the parameter {name}: leave it out")
            return None
    if p is None:
        hint = messages.closest(name, by_name)
        c.error((*at, "parameter"), f"unknown parameter '{name}'" + (f"; did you mean '{hint}'?" if hint else ""))
        return None
    if p.is_string or not p.readable:
        c.error(
            (*at, "parameter"),
            f"{name} is {'a string' if p.is_string else 'write-only'}: a health check reads a number",
        )
        return None
    got: dict[str, Decimal] = {}
    eq: codec.Raw | None = None
    for key in ("equals", "min", "max"):
        if key not in item:
            continue
        given = item[key]
        if p.type == codec.BOOL and isinstance(given, bool):  # a coil's on/off, true/false
            given = int(given)
        try:
            v = values.engineering(p, given, c.src.word((*at, key)) if isinstance(given, bool) else None)
            if key == "equals":  # the raw value read must be this one
                eq = v[1] if isinstance(v, tuple) else p.to_raw(v, "exact")
            else:  # a label as a bound: its engineering value
                got[key] = codec.from_raw(v[1], p.scale, p.offset) if isinstance(v, tuple) else v
        except (ValueError, CodecError) as e:
            c.error((*at, key), f"{name}: {e}")
            return None
    low, high = got.get("min"), got.get("max")
    if low is not None and high is not None and low > high:
        c.error((*at, "min"), f"min {_fmt(low)} is greater than max {_fmt(high)}")
        return None
    return HealthCheck(
        p.address, 0xFFFF, eq, None, None, p.register_type, item.get("description", ""), parameter=p, low=low, high=high
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


def _layout(
    spec: dict[str, Any], default: tuple[str, bool], at: yamlsrc.Path_, src: yamlsrc.Source, errors: list[Diagnostic]
) -> tuple[str, bool]:
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
