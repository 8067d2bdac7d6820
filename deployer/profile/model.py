"""The profile data model: one device type's parameters at their wire addresses.

Plain frozen data shared by every module; loading and importing live next to it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from decimal import Decimal
from typing import Literal

from ..errors import CodecError
from . import codec
from .firmware import FirmwareSource

Access = Literal["read-write", "read-only", "write-only"]
Addressing = Literal["address", "register-number", "modicon"]
RegisterType = Literal["holding", "coil", "discrete", "input"]

# The four Modbus tables. Each has its own 0..65535 address space; inside deployer a register map
# keys a table's address by ``space << 16 | address`` (holding registers: the address itself).
REGISTER_TYPES: tuple[RegisterType, ...] = ("holding", "coil", "discrete", "input")
SPACE: dict[str, int] = {t: i for i, t in enumerate(REGISTER_TYPES)}
READ_FUNCTION: dict[str, int] = {"holding": 3, "coil": 1, "discrete": 2, "input": 4}
TYPE_OF_READ: dict[int, RegisterType] = {3: "holding", 1: "coil", 2: "discrete", 4: "input"}
BIT_TABLES = ("coil", "discrete")

PROTOCOL_MAX_WRITE = 123  # FC16: 0x7B registers (Modbus Application Protocol v1.1b3, 6.12)
PROTOCOL_MAX_READ = 125  # FC03: 0x7D registers (6.3)
PROTOCOL_MAX_WRITE_COILS = 1968  # FC15: 0x7B0 coils (6.11)
PROTOCOL_MAX_READ_COILS = 2000  # FC01/FC02: 0x7D0 coils or inputs (6.1, 6.2)
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
    pause_after_connect: int = 0  # ms of silence the device needs after a connection opens
    pause_between_requests: int = 0  # ms from one answer to the next request, at least
    max_write_coils: int = PROTOCOL_MAX_WRITE_COILS  # per FC15; 1: every coil goes as one FC05
    max_read_coils: int = PROTOCOL_MAX_READ_COILS  # per FC01 (coils) and FC02 (discrete inputs)
    device_identification: bool = True  # asked Function 43 (False: the device has none; no request, no timeout)

    @property
    def write_registers(self) -> int:
        """Registers one write request may carry (docs/design.md, planning rule 2)."""
        if self.write_function == 6:
            return 1
        # FC16 RTU frame: unit(1) fc(1) addr(2) qty(2) bytecount(1) data(2n) crc(2) = 9 + 2n;
        # the same in ASCII: ':' + 2 x (7 + 2n) + LRC(2) + CR LF(2) = 19 + 4n characters
        return max(
            0,
            min(
                PROTOCOL_MAX_WRITE,
                self.max_write_registers,
                (self.max_frame_bytes - 9) // 2,
                (self.max_ascii_chars - 19) // 4,
            ),
        )

    @property
    def read_registers(self) -> int:
        """Registers one FC03 request may ask for; the answer frame is 5 + 2n bytes (11 + 4n ASCII characters)."""
        return max(
            0,
            min(
                PROTOCOL_MAX_READ,
                self.max_read_registers,
                (self.max_frame_bytes - 5) // 2,
                (self.max_ascii_chars - 11) // 4,
            ),
        )

    @property
    def write_coils(self) -> int:
        """Coils one FC15 request may carry: its RTU frame is 9 + ceil(n / 8) bytes (19 + 2 ceil(n / 8) ASCII)."""
        return max(
            0,
            min(
                PROTOCOL_MAX_WRITE_COILS,
                self.max_write_coils,
                (self.max_frame_bytes - 9) * 8,
                (self.max_ascii_chars - 19) // 2 * 8,
            ),
        )

    @property
    def read_coils(self) -> int:
        """Coils (or discrete inputs) one FC01/FC02 may ask for: the answer is 5 + ceil(n / 8) bytes."""
        return max(
            0,
            min(
                PROTOCOL_MAX_READ_COILS,
                self.max_read_coils,
                (self.max_frame_bytes - 5) * 8,
                (self.max_ascii_chars - 11) // 2 * 8,
            ),
        )

    def read_limit(self, register_type: str) -> int:
        return self.read_coils if register_type in BIT_TABLES else self.read_registers

    def write_limit(self, register_type: str) -> int:
        return self.write_coils if register_type == "coil" else self.write_registers


def address_text(register_type: str, address: int) -> str:
    """How plans, reports and `profiles show` write an address: '0x1102 (4354)', 'coil 0x0013 (19)'."""
    text = f"0x{address:04X} ({address})"
    return text if register_type == "holding" else f"{register_type} {text}"


@dataclass(frozen=True)
class Parameter:
    """One parameter at its wire address (0-based protocol address).

    A bit field (``mask`` != 0) is some bits of one register; several fields share a register
    and their registers hold the whole word (the planner merges, the codec extracts).
    """

    name: str  # "F07", or "operation_data[3].position" for table entries
    address: int
    type: str  # a codec.TYPE_NAMES member, codec.STRING or codec.BOOL (fields)
    word_order: str = "big"
    scale: Decimal = Decimal(1)
    offset: Decimal = Decimal(0)
    unit: str | None = None  # pint unit text; None = dimensionless
    cycles_as_angles: bool = False  # values in rev/rpm/Hz and in rad/deg/rad/s convert (one cycle = 2 pi rad)
    min: Decimal | None = None  # engineering units, inclusive
    max: Decimal | None = None
    access: Access = "read-write"
    values: tuple[tuple[str, int], ...] = ()  # enumeration: label -> raw value
    stage: int = 0
    default: Decimal | str | None = None  # engineering (text for strings); the simulator's power-on value
    rounding: Literal["exact", "nearest"] | None = None
    description: str = ""
    line: int = 0  # where the parameter is defined in the profile file (1-based)
    col: int = 0
    byte_swap: bool = False  # low byte first inside each register (layouts BADC, DCBA)
    mask: int = 0  # bit field: the bits of the register it owns; 0 = the whole value
    size: int = 0  # strings: registers
    encoding: str = "ascii"  # strings
    padding: str = "nul"  # strings
    restart: bool = False  # takes effect after a power cycle (the report says so)
    # the site agent (docs/agent.md): belongs to the unit (never restored to a replacement); drift only beyond
    # ``tolerance`` (engineering units); writes its non-volatile memory survives (None: the profile's endurance)
    per_unit: bool = False
    tolerance: Decimal = Decimal(0)
    endurance: int | None = None
    # the Modbus table: holding registers, coils (one bit each, 0/1), discrete inputs (bits, read-only),
    # input registers (read-only). A coil or input's "registers" are one value, 0 or 1.
    register_type: RegisterType = "holding"
    firmware: str | None = None  # the firmware revisions it exists in ('>=2.1'; firmware.matches)
    action: bool = False  # a momentary command (a defrost button): never pulled, never set by a recipe
    # as the manufacturer's manual names it: "3-41" and "Ramp 1 Ramp Up Time" (shown beside the key)
    manual_number: str = ""
    manual_text: str = ""

    @property
    def manual(self) -> str:
        """The manual's number and text, as one label ("3-41 Ramp 1 Ramp Up Time"); "" when the profile gives none."""
        return f"{self.manual_number} {self.manual_text}".strip()

    def __hash__(self) -> int:
        # a few fields, not all 28 (equal parameters still hash alike): snapshots and recipe texts key their
        # caches by parameter
        return hash((self.name, self.address, self.type, self.register_type))

    @property
    def key(self) -> int:
        """Where the parameter starts in a register map of all four tables (see SPACE)."""
        return SPACE[self.register_type] << 16 | self.address

    @property
    def is_bit(self) -> bool:
        """A coil or a discrete input: one bit, 0 or 1."""
        return self.register_type in BIT_TABLES

    @property
    def table_name(self) -> str:
        """'coil 0x0013' style prefix for messages; empty for holding registers."""
        return "" if self.register_type == "holding" else self.register_type

    @property
    def count(self) -> int:
        if self.register_type in BIT_TABLES or self.type == codec.BOOL:
            return 1
        if self.type == codec.STRING:
            return self.size
        if self.mask:
            return 1
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
        return self.access != "read-only" and self.register_type in ("holding", "coil")

    @property
    def is_string(self) -> bool:
        return self.type == codec.STRING

    @property
    def layout(self) -> str:
        """The manual's name of the byte layout: ABCD, CDAB, BADC, DCBA (AB/BA for 16 bits)."""
        return codec.layout_name(self.word_order, self.byte_swap, self.type)

    def label_for(self, raw: codec.Raw) -> str | None:
        for label, value in self.values:
            if value == raw:
                return label
        return None

    def type_range(self) -> tuple[int, int] | None:
        """Raw range the type (or the field's width) allows; None for floats and strings."""
        if self.is_bit:
            return 0, 1
        if self.mask:
            return codec.field_range(self.mask, self.type == "int16")
        if self.is_string:
            return None
        return codec.raw_range(self.type)

    def raw_bounds(self) -> tuple[codec.Raw, codec.Raw] | None:
        """Inclusive raw range allowed by min/max (and the type); None for unbounded floats."""
        rng = self.type_range()
        lo: codec.Raw | None = rng[0] if rng else None
        hi: codec.Raw | None = rng[1] if rng else None
        for bound in (self.min, self.max):
            if bound is None:
                continue
            r = (bound - self.offset) / self.scale
            # a negative scale swaps which engineering bound limits which raw bound
            is_low = (bound is self.min) == (self.scale > 0)
            raw_b: codec.Raw
            if self.is_float:
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

    @property
    def is_float(self) -> bool:
        return not self.mask and self.type in codec.TYPE_NAMES and codec.is_float(self.type)

    @property
    def codec_type(self) -> str:
        """The numeric type raw values are converted as (a field's bits count as uint16/int16)."""
        return "uint16" if self.type == codec.BOOL else self.type

    def to_raw(self, value: Decimal, rounding: Literal["exact", "nearest"] = "exact") -> codec.Raw:
        """Engineering -> raw; CodecError when the type (or the field's width) cannot hold it."""
        raw = codec.to_raw(value, self.codec_type, self.scale, self.offset, rounding)
        rng = self.type_range()
        if self.is_bit and raw not in (0, 1):
            raise CodecError(f"a {self.register_type} holds 0 or 1, not {raw}")
        if self.mask and rng and not rng[0] <= raw <= rng[1]:
            width = codec.mask_shift(self.mask)[1]
            raise CodecError(
                f"raw value {raw} does not fit in the field's "
                f"{width} bit{'s' if width != 1 else ''} ({rng[0]}..{rng[1]})"
            )
        return raw

    def encode(self, raw: codec.Raw) -> tuple[int, ...]:
        """Raw -> registers; a field's register carries only its own bits (the planner merges)."""
        if self.is_bit:
            if raw not in (0, 1) or not isinstance(raw, int):
                raise CodecError(f"a {self.register_type} holds 0 or 1, not {raw!r}")
            return (raw,)
        if self.mask:
            if not isinstance(raw, int):
                raise CodecError(f"a bit field needs an integer raw value, not {raw!r}")
            return (codec.insert_field(raw, self.mask, self.type == "int16"),)
        return codec.encode(raw, self.type, self.word_order, self.byte_swap)

    def decode(self, registers: tuple[int, ...] | list[int]) -> codec.Raw:
        """Registers -> raw value; a field's value is its bits of the register."""
        if self.is_bit:
            return 1 if registers[0] else 0
        if self.mask:
            return codec.extract_field(int(registers[0]), self.mask, self.type == "int16")
        if self.is_string:
            raise CodecError(f"{self.name} is a string: use text_of")
        return codec.decode(registers, self.type, self.word_order, self.byte_swap)

    def encode_text(self, text: str) -> tuple[int, ...]:
        return codec.encode_string(text, self.size, self.encoding, self.padding, self.byte_swap)

    def text_of(self, registers: tuple[int, ...] | list[int]) -> str:
        return codec.decode_string(registers, self.encoding, self.byte_swap)

    def default_registers(self) -> tuple[int, ...] | None:
        """The factory default as registers (a field: its bits in place), or None when the profile gives none."""
        if self.default is None:
            return None
        if isinstance(self.default, str):
            return self.encode_text(self.default)
        return self.encode(self.to_raw(self.default, "nearest"))

    def same_value(self, a: tuple[int, ...] | list[int] | None, b: tuple[int, ...] | list[int] | None) -> bool:
        """Do two register readings hold the same value of this parameter (a field compares its bits)?"""
        if a is None or b is None:
            return a is b
        if self.mask:
            return len(a) == len(b) == 1 and not (a[0] ^ b[0]) & self.mask
        return tuple(a) == tuple(b)

    def to_engineering(self, registers: tuple[int, ...] | list[int]) -> Decimal:
        if self.mask or self.is_bit:
            return codec.from_raw(self.decode(registers), self.scale, self.offset)
        return codec.registers_to_engineering(
            registers, self.type, self.scale, self.offset, self.word_order, self.byte_swap
        )

    def format_registers(self, registers: tuple[int, ...] | list[int]) -> str:
        """Human text for a register value: '10 s', 'coast', '1000', a string's text ..."""
        if self.is_string:
            return self.text_of(registers)
        raw = self.decode(registers)
        label = self.label_for(raw)
        if label is not None:
            return label
        if self.type == codec.BOOL:
            return "true" if raw else "false"
        text = codec.format_decimal(self.to_engineering(registers))
        return f"{text} {self.unit}" if self.unit else text

    def show_registers(self, registers: tuple[int, ...] | list[int]) -> str:
        """``format_registers``, or the raw words where the codec cannot show the value (e.g. NaN)."""
        try:
            return self.format_registers(registers)
        except Exception:
            return " ".join(f"{w:04X}h" for w in registers)


@dataclass(frozen=True)
class IdentityCheck:
    """A register read before any write; a different value means the wrong device."""

    address: int
    raw: int
    description: str = ""
    register_type: RegisterType = "holding"  # or "input": where many devices report model and firmware


# Function 43 / 14 objects by name (Modbus Application Protocol v1.1b3, 6.21)
IDENTITY_OBJECTS = {
    "vendor": 0,
    "product_code": 1,
    "revision": 2,
    "vendor_url": 3,
    "product_name": 4,
    "model_name": 5,
    "application_name": 6,
}


def object_name(object_id: int) -> str:
    """'vendor', 'product_code' ... for the basic and regular objects, else '0x80'."""
    for name, i in IDENTITY_OBJECTS.items():
        if i == object_id:
            return name
    return f"0x{object_id:02X}"


@dataclass(frozen=True)
class IdentityObject:
    """A Device Identification object (Function 43 / 14) that must hold a text, read before any write."""

    object_id: int
    equals: str
    description: str = ""


@dataclass(frozen=True)
class Precondition:
    """Bits of a register read before any write; another value refuses the device ("drive running")."""

    address: int
    mask: int  # 0xFFFF for the whole register
    equals: int  # the expected value of the masked bits, shifted down
    description: str = ""

    def holds(self, word: int) -> bool:
        return codec.extract_field(word, self.mask) == self.equals

    def what(self) -> str:
        shift, width = codec.mask_shift(self.mask)
        bits = "" if self.mask == 0xFFFF else (f" bit {shift}" if width == 1 else f" bits {shift}..{shift + width - 1}")
        return f"register 0x{self.address:04X}{bits}" + (f" ({self.description})" if self.description else "")


@dataclass(frozen=True)
class HealthCheck:
    """A value watched after a verified write (``apply --soak``, ``--confirm-within``): another value means
    the change hurt the device ("drive fault code is zero"), and it is rolled back.

    Either raw bits of a holding or input register (``mask``, ``equals``/``min``/``max`` raw), or a
    declared ``parameter`` in any table (``equals`` its raw value, e.g. a label's; ``low``/``high``
    engineering bounds in its unit).
    """

    address: int
    mask: int = 0xFFFF  # 0xFFFF for the whole register
    equals: codec.Raw | None = None  # the healthy value of the masked bits, shifted down (a parameter's raw) ...
    min: int | None = None  # ... or a healthy raw range
    max: int | None = None
    register_type: RegisterType = "holding"  # read with Function 03, 04 (or 01, 02 for a parameter's bit)
    description: str = ""
    parameter: Parameter | None = None
    low: Decimal | None = None  # a parameter's healthy range, engineering units
    high: Decimal | None = None

    @property
    def function(self) -> int:
        return READ_FUNCTION[self.register_type]

    @property
    def count(self) -> int:
        """Registers (or bits) read for the check."""
        return self.parameter.count if self.parameter is not None else 1

    @property
    def key(self) -> int:
        """Where the register is in a register map of all four tables (see SPACE)."""
        return SPACE[self.register_type] << 16 | self.address

    def value(self, word: int) -> int:
        return codec.extract_field(word, self.mask)

    def holds(self, words: int | Sequence[int]) -> bool:
        regs = (words,) if isinstance(words, int) else tuple(words)
        p = self.parameter
        if p is None:
            v: codec.Raw | Decimal = self.value(regs[0])
            lo, hi, eq = self.min, self.max, self.equals
        else:
            try:
                if self.equals is not None:
                    return p.decode(regs) == self.equals
                v = p.to_engineering(regs)
            except (CodecError, ArithmeticError, ValueError):  # NaN, infinity: not a healthy value
                return False
            lo, hi, eq = self.low, self.high, None  # type: ignore[assignment]
        if eq is not None and v != eq:
            return False
        return (lo is None or v >= lo) and (hi is None or v <= hi)

    def expected(self) -> str:
        p = self.parameter
        if p is not None:
            return self._expected_value(p)
        if self.equals is not None:
            return f"expected {self.equals}"
        if self.min is not None and self.max is not None:
            return f"expected {self.min}..{self.max}"
        return f"expected at least {self.min}" if self.min is not None else f"expected at most {self.max}"

    def _expected_value(self, p: Parameter) -> str:
        unit = f" {p.unit}" if p.unit else ""
        if self.equals is not None:
            label = p.label_for(self.equals)
            if label is not None:
                return f"expected {label}"
            if p.type == codec.BOOL:
                return f"expected {'true' if self.equals else 'false'}"
            return f"expected {codec.format_decimal(codec.from_raw(self.equals, p.scale, p.offset))}{unit}"
        lo = None if self.low is None else codec.format_decimal(self.low)
        hi = None if self.high is None else codec.format_decimal(self.high)
        if lo is not None and hi is not None:
            return f"expected {lo}..{hi}{unit}"
        return f"expected at least {lo}{unit}" if lo is not None else f"expected at most {hi}{unit}"

    def what(self) -> str:
        if self.parameter is not None:
            return self.parameter.name + (f" ({self.description})" if self.description else "")
        shift, width = codec.mask_shift(self.mask)
        bits = "" if self.mask == 0xFFFF else (f" bit {shift}" if width == 1 else f" bits {shift}..{shift + width - 1}")
        kind = {"input": "input register", "coil": "coil", "discrete": "discrete input"}.get(
            self.register_type, "register"
        )
        return f"{kind} 0x{self.address:04X}{bits}" + (f" ({self.description})" if self.description else "")

    def failure(self, words: int | Sequence[int]) -> str:
        """'register 0x0030 (drive fault code is zero) is 7, expected 0'; 'dc_bus_voltage is 850 V, expected
        450..800 V'."""
        regs = (words,) if isinstance(words, int) else tuple(words)
        shown = self.parameter.show_registers(regs) if self.parameter is not None else str(self.value(regs[0]))
        return f"{self.what()} is {shown}, {self.expected()}"


@dataclass(frozen=True)
class CommitAction:
    """A write the profile declares: commit (after a verified apply), unlock (before), lock (after).

    Holding registers (Function 16, or 06), or one coil (Function 05: ``registers`` is its 0 or 1), as a
    Danfoss FC 102 stores its parameters to EEPROM with coil 65."""

    address: int
    registers: tuple[int, ...]
    description: str = ""
    wait_ms: int = 0  # the device needs this long before it accepts the next request
    secret: str = ""  # where a secret value came from ('environment variable DRIVE_PASSWORD'): never shown
    register_type: Literal["holding", "coil"] = "holding"

    @property
    def key(self) -> int:
        """Where it writes in a register map of all four tables (see SPACE)."""
        return SPACE[self.register_type] << 16 | self.address

    @property
    def is_coil(self) -> bool:
        return self.register_type == "coil"

    def __repr__(self) -> str:
        regs = f"<secret from {self.secret}>" if self.secret else repr(self.registers)
        table = "" if self.register_type == "holding" else f", register_type={self.register_type!r}"
        return (
            f"CommitAction(address={self.address}, registers={regs}, description={self.description!r}, "
            f"wait_ms={self.wait_ms}{table})"
        )


WriteAction = CommitAction


@dataclass(frozen=True)
class Profile:
    id: str
    description: str = ""
    addressing: Addressing = "address"
    word_order: str = "big"  # the profile's default layout: word order ...
    byte_swap: bool = False  # ... and byte swap (codec.layout_name gives ABCD/CDAB/BADC/DCBA)
    limits: Limits = field(default_factory=Limits)
    identity: tuple[IdentityCheck, ...] = ()
    identity_objects: tuple[IdentityObject, ...] = ()
    # sorted by address; table entries expanded to "table[i].field"
    parameters: tuple[Parameter, ...] = ()
    commit: tuple[CommitAction, ...] = ()
    source: str | None = None  # file the profile came from (None for built-ins and profiles built in code)
    digest: str | None = None  # sha256 of the profile file's text: snapshots record it, rollback compares it
    preconditions: tuple[Precondition, ...] = ()
    unlock: tuple[WriteAction, ...] = ()
    lock: tuple[WriteAction, ...] = ()
    stage_waits: tuple[tuple[int, int], ...] = ()  # (stage, ms to wait after it)
    health: tuple[HealthCheck, ...] = ()  # read while a written change soaks (apply --soak)
    firmware: FirmwareSource | None = None  # where the device says its revision, and what the profile wants
    endurance: int | None = None  # commits (and writes of a parameter without its own) the memory survives

    def __post_init__(self) -> None:
        object.__setattr__(self, "_by_name", {p.name: p for p in self.parameters})
        object.__setattr__(self, "_fields", frozenset(p.name for p in self.parameters if p.mask and p.readable))

    def readable_fields(self) -> frozenset[str]:
        """The names of the bit fields that can be read: an apply merges each one's register anew before a write."""
        fields: frozenset[str] = self._fields  # type: ignore[attr-defined]
        return fields

    def parameter(self, name: str) -> Parameter:
        by_name: dict[str, Parameter] = self._by_name  # type: ignore[attr-defined]
        return by_name[name]

    def get(self, name: str) -> Parameter | None:
        by_name: dict[str, Parameter] = self._by_name  # type: ignore[attr-defined]
        return by_name.get(name)

    def names(self) -> list[str]:
        return [p.name for p in self.parameters]

    def wait_after(self, stage: int) -> int:
        return dict(self.stage_waits).get(stage, 0)
