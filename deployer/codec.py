"""Engineering values <-> raw values <-> 16-bit registers.

Pure functions. Arithmetic on engineering values uses ``decimal.Decimal`` so that
``10.00 s`` at 0.01 s resolution is exactly raw 1000, never 999.9999.

Terms:
  engineering = raw * scale + offset        (what the user writes, in the profile's unit)
  raw         = the integer (or IEEE float) the device stores
  registers   = raw encoded as 16-bit words in the parameter's word order
"""

from __future__ import annotations

import struct
from decimal import ROUND_HALF_EVEN, Decimal
from typing import Literal

TypeName = Literal["uint16", "int16", "uint32", "int32", "uint64", "int64", "float32", "float64"]
WordOrder = Literal["big", "little"]
Raw = int | float

# type -> (registers, signed, is_float)
_TYPES: dict[str, tuple[int, bool, bool]] = {
    "uint16": (1, False, False),
    "int16": (1, True, False),
    "uint32": (2, False, False),
    "int32": (2, True, False),
    "uint64": (4, False, False),
    "int64": (4, True, False),
    "float32": (2, True, True),
    "float64": (4, True, True),
}
TYPE_NAMES: tuple[str, ...] = tuple(_TYPES)


class CodecError(ValueError):
    """A value that cannot be represented; the message is meant for the user."""


def register_count(type_: str) -> int:
    return _TYPES[type_][0]


def is_float(type_: str) -> bool:
    return _TYPES[type_][2]


def raw_range(type_: str) -> tuple[int, int] | None:
    """Inclusive integer range of an integer type; None for floats."""
    count, signed, flt = _TYPES[type_]
    if flt:
        return None
    bits = 16 * count
    if signed:
        return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    return 0, (1 << bits) - 1


def to_raw(
    value: Decimal,
    type_: str,
    scale: Decimal = Decimal(1),
    offset: Decimal = Decimal(0),
    rounding: Literal["exact", "nearest"] = "exact",
) -> Raw:
    """Engineering value -> raw value. Raises CodecError if not exactly representable."""
    if scale == 0:
        raise CodecError("scale must not be 0")
    try:
        exact = (value - offset) / scale
    except ArithmeticError:  # 1e999999999 overflows Decimal's context: far outside any type
        raise CodecError(f"{value:g} is far outside the range of {type_}") from None
    if is_float(type_):
        raw_f = float(exact)
        if type_ == "float32":
            try:
                struct.pack(">f", raw_f)
            except OverflowError:
                raise CodecError(f"{value} does not fit in float32") from None
        return raw_f
    lo, hi = raw_range(type_) or (0, 0)
    if exact.adjusted() > 40:  # far outside any type: do not print a 400-digit number
        raise CodecError(f"{value:g} is far outside the range of {type_}")
    integral = exact.to_integral_value(rounding=ROUND_HALF_EVEN)
    if integral != exact and rounding == "exact":
        raise CodecError(
            f"{_plain(value)} is not a multiple of the resolution {_plain(scale)}"
            + (f" (offset {_plain(offset)})" if offset else "")
            + "; set 'rounding: nearest' to round"
        )
    raw = int(integral)
    if not lo <= raw <= hi:
        raise CodecError(f"raw value {raw} does not fit in {type_} ({lo}..{hi})")
    return raw


def from_raw(raw: Raw, scale: Decimal = Decimal(1), offset: Decimal = Decimal(0)) -> Decimal:
    """Raw value -> engineering value (exact for integers)."""
    base = Decimal(raw) if isinstance(raw, int) else Decimal(shortest_float_repr(raw))
    return base * scale + offset


def encode(raw: Raw, type_: str, word_order: str = "big") -> tuple[int, ...]:
    """Raw value -> registers. Words are big-endian bytes; word_order orders the words."""
    count, signed, flt = _TYPES[type_]
    if flt:
        data = struct.pack(">f" if count == 2 else ">d", float(raw))
    else:
        if not isinstance(raw, int):
            raise CodecError(f"{type_} needs an integer raw value, not {raw!r}")
        lo, hi = raw_range(type_) or (0, 0)
        if not lo <= raw <= hi:
            raise CodecError(f"raw value {raw} does not fit in {type_} ({lo}..{hi})")
        data = raw.to_bytes(2 * count, "big", signed=signed)
    words = [int.from_bytes(data[i : i + 2], "big") for i in range(0, len(data), 2)]
    if word_order == "little":
        words.reverse()
    return tuple(words)


def decode(registers: tuple[int, ...] | list[int], type_: str, word_order: str = "big") -> Raw:
    """Registers -> raw value (inverse of encode)."""
    count, signed, flt = _TYPES[type_]
    if len(registers) != count:
        raise CodecError(f"{type_} needs {count} registers, got {len(registers)}")
    words = list(registers)
    if word_order == "little":
        words.reverse()
    data = b"".join(int(w).to_bytes(2, "big") for w in words)
    if flt:
        return float(struct.unpack(">f" if count == 2 else ">d", data)[0])
    return int.from_bytes(data, "big", signed=signed)


def shortest_float_repr(x: float, type_: str = "float64") -> str:
    """Shortest decimal text that reads back as the same float32/float64 (0.1f -> '0.1')."""
    if type_ == "float32":
        target = struct.pack(">f", x)
        for digits in range(1, 10):
            s = f"{x:.{digits}g}"
            if struct.pack(">f", float(s)) == target:
                return s
    return repr(x)


def engineering_to_registers(
    value: Decimal,
    type_: str,
    scale: Decimal = Decimal(1),
    offset: Decimal = Decimal(0),
    word_order: str = "big",
    rounding: Literal["exact", "nearest"] = "exact",
) -> tuple[int, ...]:
    return encode(to_raw(value, type_, scale, offset, rounding), type_, word_order)


def registers_to_engineering(
    registers: tuple[int, ...] | list[int],
    type_: str,
    scale: Decimal = Decimal(1),
    offset: Decimal = Decimal(0),
    word_order: str = "big",
) -> Decimal:
    raw = decode(registers, type_, word_order)
    if isinstance(raw, float) and type_ == "float32":
        raw = float(shortest_float_repr(raw, "float32"))
    return from_raw(raw, scale, offset)


def _plain(d: Decimal) -> str:
    """Decimal without exponent notation or trailing zeros: 0.01, 10, 1E+2 -> 100."""
    s = format(d.normalize(), "f")
    return s


def format_decimal(d: Decimal) -> str:
    return _plain(d)
