"""Engineering values <-> raw values <-> 16-bit registers.

Pure functions. Arithmetic on engineering values uses ``decimal.Decimal`` so that
``10.00 s`` at 0.01 s resolution is exactly raw 1000, never 999.9999.

Terms:
  engineering = raw * scale + offset        (what the user writes, in the profile's unit)
  raw         = the integer (or IEEE float) the device stores
  registers   = raw encoded as 16-bit words in the parameter's word order

Layouts: a value's bytes A B C D (most significant first) go into registers as ABCD
(big-endian, the Modbus default), CDAB (word swap), BADC (byte swap) or DCBA (both);
64-bit values alike (ABCDEFGH, GHEFCDAB, BADCFEHG, HGFEDCBA). Internally a layout is
``word_order`` ("big"/"little": which word comes first) plus ``byte_swap`` (low byte first
inside each word). Strings are bytes in address order, two per register; bit fields are
bits of one register under a contiguous mask.
"""

from __future__ import annotations

import struct
from decimal import ROUND_HALF_EVEN, Decimal
from functools import cache
from typing import Literal

from ..errors import CodecError

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
STRING = "string"  # registers holding text; its register count comes from the parameter
BOOL = "bool"  # a one-bit field: false/true

# Layout names users find in manuals (and Home Assistant's ``swap``) -> (word_order, byte_swap)
LAYOUTS: dict[str, tuple[str, bool]] = {
    "ABCD": ("big", False),
    "ABCDEFGH": ("big", False),
    "big-endian": ("big", False),
    "CDAB": ("little", False),
    "GHEFCDAB": ("little", False),
    "big-endian-word-swap": ("little", False),
    "little-endian-byte-swap": ("little", False),  # Modbus Poll's name for CDAB
    "BADC": ("big", True),
    "BADCFEHG": ("big", True),
    "big-endian-byte-swap": ("big", True),
    "little-endian-word-swap": ("big", True),
    "DCBA": ("little", True),
    "HGFEDCBA": ("little", True),
    "little-endian": ("little", True),
}
# Home Assistant modbus: swap: none | byte | word | word_byte
SWAPS: dict[str, tuple[str, bool]] = {
    "none": ("big", False),
    "byte": ("big", True),
    "word": ("little", False),
    "word_byte": ("little", True),
}
ENCODINGS: dict[str, str] = {"ascii": "ascii", "latin-1": "latin-1"}  # profile name -> Python codec
PADDING: dict[str, bytes] = {"nul": b"\0", "space": b" "}


def layout_name(word_order: str, byte_swap: bool, type_: str = "uint32") -> str:
    """The manual's name for a layout of ``type_``: 'CDAB', 'BADCFEHG', 'BA' ..."""
    size = 2 * _TYPES[type_][0] if type_ in _TYPES else 4
    letters = list("ABCDEFGH"[:size])
    words = [letters[i : i + 2] for i in range(0, size, 2)]
    if byte_swap:
        words = [w[::-1] for w in words]
    if word_order == "little":
        words.reverse()
    return "".join("".join(w) for w in words)


def register_count(type_: str) -> int:
    return _TYPES[type_][0]


def is_float(type_: str) -> bool:
    return _TYPES[type_][2]


@cache  # called for every bound of every parameter: a lookup, not arithmetic on big ints
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
    if value and value.adjusted() < -60:  # the arithmetic below would round it to 0 without a word
        raise CodecError(f"{value:g} is too close to 0 to be meant (at most 60 decimal places)")
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
            + "; set 'rounding: nearest' to round",
            kind="resolution",
        )
    raw = int(integral)
    if not lo <= raw <= hi:
        raise CodecError(f"raw value {raw} does not fit in {type_} ({lo}..{hi})")
    return raw


def from_raw(raw: Raw, scale: Decimal = Decimal(1), offset: Decimal = Decimal(0)) -> Decimal:
    """Raw value -> engineering value (exact for integers)."""
    base = Decimal(raw) if isinstance(raw, int) else Decimal(shortest_float_repr(raw))
    return base * scale + offset


def encode(raw: Raw, type_: str, word_order: str = "big", byte_swap: bool = False) -> tuple[int, ...]:
    """Raw value -> registers. word_order orders the words; byte_swap puts each word's low byte first."""
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
    words = [int.from_bytes(data[i : i + 2], "little" if byte_swap else "big") for i in range(0, len(data), 2)]
    if word_order == "little":
        words.reverse()
    return tuple(words)


def decode(registers: tuple[int, ...] | list[int], type_: str, word_order: str = "big", byte_swap: bool = False) -> Raw:
    """Registers -> raw value (inverse of encode)."""
    count, signed, flt = _TYPES[type_]
    if len(registers) != count:
        raise CodecError(f"{type_} needs {count} registers, got {len(registers)}")
    words = list(registers)
    if word_order == "little":
        words.reverse()
    data = b"".join(int(w).to_bytes(2, "little" if byte_swap else "big") for w in words)
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
    byte_swap: bool = False,
) -> tuple[int, ...]:
    return encode(to_raw(value, type_, scale, offset, rounding), type_, word_order, byte_swap)


def registers_to_engineering(
    registers: tuple[int, ...] | list[int],
    type_: str,
    scale: Decimal = Decimal(1),
    offset: Decimal = Decimal(0),
    word_order: str = "big",
    byte_swap: bool = False,
) -> Decimal:
    raw = decode(registers, type_, word_order, byte_swap)
    if isinstance(raw, float) and type_ == "float32":
        raw = float(shortest_float_repr(raw, "float32"))
    return from_raw(raw, scale, offset)


# ---- strings ---------------------------------------------------------------------------------


def encode_string(
    text: str, count: int, encoding: str = "ascii", padding: str = "nul", byte_swap: bool = False
) -> tuple[int, ...]:
    """Text -> ``count`` registers, two characters each, padded. CodecError if it does not fit."""
    try:
        data = text.encode(ENCODINGS[encoding])
    except UnicodeEncodeError as e:
        raise CodecError(f"{text[e.start : e.end]!r} at character {e.start + 1} is not {encoding}") from None
    if len(data) > 2 * count:
        held = "1 register holds" if count == 1 else f"{count} registers hold"
        raise CodecError(f"'{text}' is {len(data)} characters; {held} at most {2 * count}")
    data = data.ljust(2 * count, PADDING[padding])
    return tuple(int.from_bytes(data[i : i + 2], "little" if byte_swap else "big") for i in range(0, len(data), 2))


def decode_string(registers: tuple[int, ...] | list[int], encoding: str = "ascii", byte_swap: bool = False) -> str:
    """Registers -> text without trailing NUL/space padding. CodecError for bytes outside the encoding."""
    data = b"".join(int(w).to_bytes(2, "little" if byte_swap else "big") for w in registers)
    try:
        return data.decode(ENCODINGS[encoding]).rstrip("\0 ")
    except UnicodeDecodeError as e:
        raise CodecError(f"byte {data[e.start]:02X}h at offset {e.start} is not {encoding} text") from None


# ---- bit fields --------------------------------------------------------------------------------


def parse_bits(spec: object) -> int:
    """``3`` / ``"3..5"`` / ``"3-5"`` -> a mask over those bits (0..15). ValueError for a user message."""
    text = str(spec).strip()
    for sep in ("..", "-", ":"):
        if sep in text:
            lo_s, hi_s = text.split(sep, 1)
            break
    else:
        lo_s = hi_s = text
    try:
        lo, hi = sorted((int(lo_s), int(hi_s)))
    except ValueError:
        raise ValueError(f"bits: {spec!r} is not a bit number or a range like 3..5") from None
    if not 0 <= lo <= hi <= 15:
        raise ValueError(f"bits: {spec!r} is outside 0..15 (a register has 16 bits)")
    return ((1 << (hi - lo + 1)) - 1) << lo


def mask_shift(mask: int) -> tuple[int, int]:
    """(lowest bit, width) of a contiguous mask; ValueError otherwise."""
    if not 0 < mask <= 0xFFFF:
        raise ValueError(f"mask 0x{mask:04X} selects no bit of a 16-bit register")
    shift = (mask & -mask).bit_length() - 1
    width = (mask >> shift).bit_length()
    if (mask >> shift) != (1 << width) - 1:
        raise ValueError(f"mask 0x{mask:04X} is not one contiguous group of bits")
    return shift, width


def field_range(mask: int, signed: bool = False) -> tuple[int, int]:
    width = mask_shift(mask)[1]
    if signed:
        return -(1 << (width - 1)), (1 << (width - 1)) - 1
    return 0, (1 << width) - 1


def extract_field(word: int, mask: int, signed: bool = False) -> int:
    shift, width = mask_shift(mask)
    raw = (word & mask) >> shift
    if signed and raw >> (width - 1):
        raw -= 1 << width
    return raw


def insert_field(raw: int, mask: int, signed: bool = False, word: int = 0) -> int:
    """``word`` with the field's bits replaced by ``raw``. CodecError if it does not fit."""
    lo, hi = field_range(mask, signed)
    if not lo <= raw <= hi:
        width = mask_shift(mask)[1]
        raise CodecError(f"raw value {raw} does not fit in {width} bit{'s' if width != 1 else ''} ({lo}..{hi})")
    shift = mask_shift(mask)[0]
    return (word & ~mask & 0xFFFF) | ((raw << shift) & mask)


def _plain(d: Decimal) -> str:
    """Decimal without exponent notation or trailing zeros: 0.01, 10, 1E+2 -> 100."""
    s = format(d.normalize(), "f")
    return s


def format_decimal(d: Decimal) -> str:
    return _plain(d)
