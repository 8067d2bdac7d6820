"""Device profiles: the object dictionary of one device type (where each parameter lives).

The data model below is shared by every module. Loading from YAML (schema + semantic
checks with FILE:LINE:COL diagnostics) lives in this module too.
"""

from __future__ import annotations

import hashlib
import math
import os
from dataclasses import dataclass, field, replace
from decimal import Decimal
from typing import Any, Literal

from . import codec, units, yamlsrc
from .diagnostics import Diagnostic, InputError, UsageError

Access = Literal["read-write", "read-only", "write-only"]
Addressing = Literal["address", "register-number", "modicon"]

PROTOCOL_MAX_WRITE = 123  # FC16: 0x7B registers (Modbus Application Protocol v1.1b3, 6.12)
PROTOCOL_MAX_READ = 125  # FC03: 0x7D registers (6.3)
ASCII_MAX_CHARS = 513  # ':' + 2 x (address + 253-byte PDU) + LRC + CR LF (Modbus over serial line 2.5.2.1)


@dataclass(frozen=True)
class Limits:
    max_write_registers: int = PROTOCOL_MAX_WRITE
    max_read_registers: int = PROTOCOL_MAX_READ
    max_frame_bytes: int = 256  # whole RTU frame: unit id + PDU + CRC
    write_function: Literal[6, 16] = 16
    max_ascii_chars: int = ASCII_MAX_CHARS  # whole ASCII frame: ':' + hex pairs + LRC + CR LF
    # reads may span up to this many consecutive undeclared registers (0: never; DESIGN planning rule 5)
    max_read_gap: int = 0

    @property
    def write_registers(self) -> int:
        """Registers one write request may carry (DESIGN.md, planning rule 2)."""
        if self.write_function == 6:
            return 1
        # FC16 RTU frame: unit(1) fc(1) addr(2) qty(2) bytecount(1) data(2n) crc(2) = 9 + 2n;
        # the same in ASCII: ':' + 2 x (7 + 2n) + LRC(2) + CR LF(2) = 19 + 4n characters
        return max(0, min(PROTOCOL_MAX_WRITE, self.max_write_registers, (self.max_frame_bytes - 9) // 2,
                          (self.max_ascii_chars - 19) // 4))

    @property
    def read_registers(self) -> int:
        """Registers one FC03 request may ask for; the answer frame is 5 + 2n bytes (11 + 4n ASCII characters)."""
        return max(0, min(PROTOCOL_MAX_READ, self.max_read_registers, (self.max_frame_bytes - 5) // 2,
                          (self.max_ascii_chars - 11) // 4))


@dataclass(frozen=True)
class Parameter:
    """One parameter at its wire address (0-based protocol address)."""

    name: str  # "F07", or "operation_data[3].position" for table entries
    address: int
    type: str  # a codec.TYPE_NAMES member
    word_order: str = "big"
    scale: Decimal = Decimal(1)
    offset: Decimal = Decimal(0)
    unit: str | None = None  # pint unit text; None = dimensionless
    min: Decimal | None = None  # engineering units, inclusive
    max: Decimal | None = None
    access: Access = "read-write"
    values: tuple[tuple[str, int], ...] = ()  # enumeration: label -> raw value
    stage: int = 0
    default: Decimal | None = None  # engineering; the simulator's power-on value
    rounding: Literal["exact", "nearest"] | None = None
    description: str = ""
    line: int = 0  # where the parameter is defined in the profile file (1-based)
    col: int = 0

    @property
    def count(self) -> int:
        return codec.register_count(self.type)

    @property
    def end(self) -> int:
        """One past the last register."""
        return self.address + self.count

    @property
    def readable(self) -> bool:
        return self.access != "write-only"

    @property
    def writable(self) -> bool:
        return self.access != "read-only"

    def label_for(self, raw: codec.Raw) -> str | None:
        for label, value in self.values:
            if value == raw:
                return label
        return None

    def raw_bounds(self) -> tuple[codec.Raw, codec.Raw] | None:
        """Inclusive raw range allowed by min/max (and the type); None for unbounded floats."""
        rng = codec.raw_range(self.type)
        lo: codec.Raw | None = rng[0] if rng else None
        hi: codec.Raw | None = rng[1] if rng else None
        for bound in (self.min, self.max):
            if bound is None:
                continue
            r = (bound - self.offset) / self.scale
            # a negative scale swaps which engineering bound limits which raw bound
            is_low = (bound is self.min) == (self.scale > 0)
            raw_b: codec.Raw
            if codec.is_float(self.type):
                raw_b = float(r)
            else:  # the nearest raw value inside the range
                raw_b = math.ceil(r) if is_low else math.floor(r)
            if is_low:
                lo = raw_b if lo is None else max(lo, raw_b)
            else:
                hi = raw_b if hi is None else min(hi, raw_b)
        if lo is None or hi is None:
            return None
        return lo, hi

    def encode(self, raw: codec.Raw) -> tuple[int, ...]:
        return codec.encode(raw, self.type, self.word_order)

    def decode(self, registers: tuple[int, ...] | list[int]) -> codec.Raw:
        return codec.decode(registers, self.type, self.word_order)

    def to_engineering(self, registers: tuple[int, ...] | list[int]) -> Decimal:
        return codec.registers_to_engineering(
            registers, self.type, self.scale, self.offset, self.word_order
        )

    def format_registers(self, registers: tuple[int, ...] | list[int]) -> str:
        """Human text for a register value: '10 s', 'coast', '1000' ..."""
        raw = self.decode(registers)
        label = self.label_for(raw)
        if label is not None:
            return label
        text = codec.format_decimal(self.to_engineering(registers))
        return f"{text} {self.unit}" if self.unit else text


@dataclass(frozen=True)
class IdentityCheck:
    """A register read before any write; a different value means the wrong device."""

    address: int
    raw: int
    description: str = ""


@dataclass(frozen=True)
class CommitAction:
    """Written after a fully verified apply (e.g. 'store to EEPROM')."""

    address: int
    registers: tuple[int, ...]
    description: str = ""


@dataclass(frozen=True)
class Profile:
    id: str
    description: str = ""
    addressing: Addressing = "address"
    word_order: str = "big"
    limits: Limits = field(default_factory=Limits)
    identity: tuple[IdentityCheck, ...] = ()
    # sorted by address; table entries expanded to "table[i].field"
    parameters: tuple[Parameter, ...] = ()
    commit: tuple[CommitAction, ...] = ()
    source: str | None = None  # file the profile came from (None for built-ins and profiles built in code)
    digest: str | None = None  # sha256 of the profile file's text: snapshots record it, rollback compares it

    def __post_init__(self) -> None:
        object.__setattr__(self, "_by_name", {p.name: p for p in self.parameters})

    def parameter(self, name: str) -> Parameter:
        by_name: dict[str, Parameter] = self._by_name  # type: ignore[attr-defined]
        return by_name[name]

    def get(self, name: str) -> Parameter | None:
        by_name: dict[str, Parameter] = self._by_name  # type: ignore[attr-defined]
        return by_name.get(name)

    def names(self) -> list[str]:
        return [p.name for p in self.parameters]


# ---- loading ------------------------------------------------------------------------------

_BUILTIN_DIR = os.path.join(os.path.dirname(__file__), "profiles")


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
    prof = load_profile(path)
    return replace(prof, source=None)


def _profile_base(relative_to: str | os.PathLike[str] | None) -> str:
    return os.path.dirname(os.path.abspath(os.fspath(relative_to))) if relative_to else os.getcwd()


def resolve_profile(ref: str, relative_to: str | os.PathLike[str] | None = None, kind: str = "recipe") -> Profile:
    """A built-in id, or a profile file (relative to the directory of ``relative_to``, a ``kind`` file)."""
    looks_like_path = ref.endswith((".yaml", ".yml", ".json")) or os.sep in ref or "/" in ref
    if not looks_like_path:
        if not os.path.isfile(os.path.join(_BUILTIN_DIR, f"{ref}.yaml")):
            raise UsageError(unknown_profile(ref, relative_to, kind))
        return builtin_profile(ref)
    return load_profile(os.path.normpath(os.path.join(_profile_base(relative_to), ref)))


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


def wire_address(number: int, addressing: str) -> int:
    """Profile address -> 0-based protocol address. Raises ValueError with a user message."""
    if addressing == "address":
        return number
    if addressing == "register-number":
        if number < 1:
            raise ValueError(f"register number {number} is below 1 (addressing: register-number)")
        return number - 1
    # modicon: 4xxxx (5 digits) or 4xxxxx (6 digits) holding-register references
    if 40001 <= number <= 49999:
        return number - 40001
    if 400001 <= number <= 465536:
        return number - 400001
    if 30001 <= number <= 39999 or 300001 <= number <= 365536:
        hint = "; 3xxxx references are input registers, which cannot be written"
    elif number < 40001:
        hint = "; for 0-based addresses use addressing: address, for 1-based numbers addressing: register-number"
    else:
        hint = ""
    raise ValueError(f"{number} is not a holding-register reference: addressing: modicon accepts 40001-49999 "
                     f"(5 digits, addresses 0-9998) or 400001-465536 (6 digits, addresses 0-65535){hint}")


def _hex(n: int) -> str:
    return f"0x{n:04X}"


def load_profile(path: str | os.PathLike[str]) -> Profile:
    """Load and check a profile file; all problems at once as an InputError."""
    p = os.fspath(path)
    text = yamlsrc.read_text(p)
    data, src = yamlsrc.load(p, text)
    if not isinstance(data, dict):
        raise InputError([src.error((), "a profile must be a mapping (profile: ..., parameters: ...)")])
    errors = yamlsrc.validate(data, "profile", src)
    if errors:
        raise InputError(errors)
    return replace(_build_profile(data, src), digest=hashlib.sha256(text.encode("utf-8")).hexdigest())


def profile_ref(profile: Profile) -> str:
    """The one well-defined name of a profile: its file's absolute path, or its built-in id."""
    return profile.source or profile.id


def _build_profile(data: dict[str, Any], src: yamlsrc.Source) -> Profile:
    errors: list[Diagnostic] = []
    addressing = data.get("addressing", "address")
    word_order = data.get("word_order", "big")
    rounding = data.get("rounding")
    limits = Limits(**data.get("limits", {}))
    if limits.write_registers < 1:
        errors.append(src.error(("limits",), "limits leave no room for a single register per write"))

    def address_of(value: object, at: yamlsrc.Path_, extra: int = 0) -> int | None:
        try:
            wire = wire_address(parse_register(value), addressing) + extra
        except ValueError as e:
            errors.append(src.error(at, str(e) if "holding" in str(e) or "below" in str(e)
                                    else f"not a register: {value!r}"))
            return None
        if wire > 0xFFFF:
            errors.append(src.error(at, f"wire address {wire} is beyond 65535"))
            return None
        return wire

    params: list[Parameter] = []

    def make(name: str, spec: dict[str, Any], address: int, at: yamlsrc.Path_,
             eng_offset: object = 0) -> None:
        type_ = spec["type"]
        param = Parameter(
            name=name,
            address=address,
            type=type_,
            word_order=spec.get("word_order", word_order),
            scale=Decimal(spec.get("scale", 1)),
            offset=Decimal(eng_offset),  # type: ignore[arg-type]
            unit=units.normalize(spec["unit"]) if "unit" in spec else None,
            min=_dec(spec.get("min")),
            max=_dec(spec.get("max")),
            access=spec.get("access", "read-write"),
            values=tuple((str(k), int(v)) for k, v in (spec.get("values") or {}).items()),
            stage=int(spec.get("stage", 0)),
            rounding=spec.get("rounding", rounding),
            description=spec.get("description", ""),
            line=src.pos(at, key=True)[0],
            col=src.pos(at, key=True)[1],
        )
        local: list[Diagnostic] = []
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
                    codec.to_raw(bound, type_, param.scale, param.offset, rounding="nearest")
                except codec.CodecError as e:
                    local.append(src.error((*at, key), f"{key} {_fmt(bound)} is not representable: {e}"))
        rng = codec.raw_range(type_)
        for label, raw in param.values:
            if rng and not rng[0] <= raw <= rng[1]:
                local.append(src.error((*at, "values", label), f"value {raw} of '{label}' does not fit in {type_}"))
        if "default" in spec and not local:
            d = spec["default"]
            try:
                if isinstance(d, str):
                    labels = dict(param.values)
                    if d not in labels:
                        raise codec.CodecError(f"'{d}' is not one of the labels {', '.join(labels) or '(none)'}")
                    default_eng = codec.from_raw(labels[d], param.scale, param.offset)
                else:
                    default_eng = Decimal(d)
                    codec.to_raw(default_eng, type_, param.scale, param.offset)
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
        addr = address_of(spec["register"], (*at, "register"))
        if addr is not None:
            make(name, spec, addr, at, spec.get("offset", 0))

    for tname, table in (data.get("tables") or {}).items():
        tat: yamlsrc.Path_ = ("tables", tname)
        base = address_of(table["base"], (*tat, "base"))
        if base is None:
            continue
        count, stride = table["count"], table["stride"]
        last_end = base + (count - 1) * stride + max(
            f["offset"] + codec.register_count(f["type"]) for f in table["fields"].values()
        )
        if last_end > 0x10000:
            errors.append(src.error(tat, f"table {tname}: entry {count - 1} ends at register {last_end - 1}, "
                                         "beyond 65535"))
            continue
        for fname, fspec in table["fields"].items():
            if fspec["offset"] + codec.register_count(fspec["type"]) > stride:
                errors.append(src.error((*tat, "fields", fname, "offset"),
                                        f"field {fname} runs past the table's stride {stride}"))
        for i in range(count):
            for fname, fspec in table["fields"].items():
                make(f"{tname}[{i}].{fname}", fspec, base + i * stride + fspec["offset"],
                     (*tat, "fields", fname))

    # overlapping registers: name both parameters and both lines
    params.sort(key=lambda q: (q.address, q.name))
    prev: Parameter | None = None
    reported = 0
    for q in params:
        if prev is not None and q.address < prev.end:
            if reported < 20:  # a bad table can overlap thousands of times; the first ones say it
                errors.append(Diagnostic(
                    src.path, q.line, q.col,
                    f"{q.name} (registers {_hex(q.address)}-{_hex(q.end - 1)}) overlaps {prev.name} "
                    f"(registers {_hex(prev.address)}-{_hex(prev.end - 1)}, line {prev.line})"))
            reported += 1
        if prev is None or q.end > prev.end:
            prev = q

    identity = []
    for i, item in enumerate(data.get("identity") or []):
        a = address_of(item["register"], ("identity", i, "register"))
        if a is not None:
            identity.append(IdentityCheck(a, int(item["raw"]), item.get("description", "")))
    commits = []
    for i, item in enumerate(data.get("commit") or []):
        at2: yamlsrc.Path_ = ("commit", i)
        a = address_of(item["register"], (*at2, "register"))
        raw = item["raw"]
        try:
            regs = tuple(int(r) for r in raw) if isinstance(raw, list) else codec.encode(
                int(raw), item.get("type", "uint16"), word_order)
        except codec.CodecError as e:
            errors.append(src.error((*at2, "raw"), str(e)))
            continue
        if a is not None:
            commits.append(CommitAction(a, regs, item.get("description", "")))
    if errors:
        raise InputError(errors)
    return Profile(
        id=str(data["profile"]),
        description=str(data.get("description", "")),
        addressing=addressing,
        word_order=word_order,
        limits=limits,
        identity=tuple(identity),
        parameters=tuple(params),
        commit=tuple(commits),
        source=os.path.abspath(src.path),
    )


def _dec(v: object) -> Decimal | None:
    return None if v is None else Decimal(v)  # type: ignore[arg-type]


def _fmt(d: Decimal | None) -> str:
    return "-" if d is None else codec.format_decimal(d)
