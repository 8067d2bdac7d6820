"""Device profiles: the object dictionary of one device type (where each parameter lives).

The data model below is shared by every module. Loading from YAML (schema + semantic
checks with FILE:LINE:COL diagnostics) lives in this module too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from decimal import Decimal
from typing import Literal

from . import codec

Access = Literal["read-write", "read-only", "write-only"]
Addressing = Literal["address", "register-number", "modicon"]

PROTOCOL_MAX_WRITE = 123  # FC16: 0x7B registers (Modbus Application Protocol v1.1b3, 6.12)
PROTOCOL_MAX_READ = 125  # FC03: 0x7D registers (6.3)


@dataclass(frozen=True)
class Limits:
    max_write_registers: int = PROTOCOL_MAX_WRITE
    max_read_registers: int = PROTOCOL_MAX_READ
    max_frame_bytes: int = 256  # whole RTU frame: unit id + PDU + CRC
    write_function: Literal[6, 16] = 16

    @property
    def write_registers(self) -> int:
        """Registers one write request may carry (DESIGN.md, planning rule 2)."""
        if self.write_function == 6:
            return 1
        # FC16 RTU frame: unit(1) fc(1) addr(2) qty(2) bytecount(1) data(2n) crc(2) = 9 + 2n
        return max(0, min(PROTOCOL_MAX_WRITE, self.max_write_registers, (self.max_frame_bytes - 9) // 2))

    @property
    def read_registers(self) -> int:
        """Registers one FC03 request may ask for; the answer frame is 5 + 2n bytes."""
        return max(0, min(PROTOCOL_MAX_READ, self.max_read_registers, (self.max_frame_bytes - 5) // 2))


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
    source: str | None = None  # file the profile came from (None for profiles built in code)

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
