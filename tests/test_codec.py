"""Codec: exact engineering <-> raw <-> registers, the seeds' values, and round trips."""

from __future__ import annotations

from decimal import Decimal

import pytest
from hypothesis import given
from hypothesis import strategies as st

from deployer.errors import CodecError
from deployer.profile import codec


def test_omron_f07_ten_seconds_is_0000_03e8() -> None:
    # the OMRON M1 manual, p. 668: 10 s at 0.01 s -> 1000 -> 0000 03E8 hex
    assert codec.engineering_to_registers(Decimal("10"), "uint32", Decimal("0.01")) == (0x0000, 0x03E8)


@pytest.mark.parametrize(
    ("value", "regs"), [(10000, (0x0000, 0x2710)), (20000, (0x0000, 0x4E20)), (500, (0x0000, 0x01F4))]
)
def test_oriental_operation_data_no3(value: int, regs: tuple[int, int]) -> None:
    # the Oriental Motor AZ manual HM-60252J, p. 267: 32-bit, upper word first
    assert codec.engineering_to_registers(Decimal(value), "int32") == regs


def test_not_a_multiple_of_resolution() -> None:
    with pytest.raises(CodecError, match="not a multiple of the resolution 0.01"):
        codec.to_raw(Decimal("10.005"), "uint32", Decimal("0.01"))
    assert codec.to_raw(Decimal("10.005"), "uint32", Decimal("0.01"), rounding="nearest") == 1000


def test_signed_twos_complement_and_word_order() -> None:
    assert codec.encode(-1, "int16") == (0xFFFF,)
    assert codec.encode(-2, "int32", "big") == (0xFFFF, 0xFFFE)
    assert codec.encode(-2, "int32", "little") == (0xFFFE, 0xFFFF)
    assert codec.encode(0x0102030405060708, "uint64") == (0x0102, 0x0304, 0x0506, 0x0708)


def test_float32_reads_back_as_written() -> None:
    regs = codec.engineering_to_registers(Decimal("0.1"), "float32")
    assert codec.registers_to_engineering(regs, "float32") == Decimal("0.1")


def test_out_of_type_range() -> None:
    with pytest.raises(CodecError, match="does not fit in uint16"):
        codec.encode(65536, "uint16")
    with pytest.raises(CodecError, match="does not fit in int16"):
        codec.to_raw(Decimal("-32769"), "int16")


_INT_TYPES = [t for t in codec.TYPE_NAMES if not codec.is_float(t)]


@st.composite
def _int_case(draw: st.DrawFn) -> tuple[str, int]:
    type_ = draw(st.sampled_from(_INT_TYPES))
    lo, hi = codec.raw_range(type_) or (0, 0)
    return type_, draw(st.integers(lo, hi))


@given(_int_case(), st.sampled_from(["big", "little"]))
def test_integer_round_trip(case: tuple[str, int], order: str) -> None:
    type_, raw = case
    regs = codec.encode(raw, type_, order)
    assert len(regs) == codec.register_count(type_)
    assert all(0 <= r <= 0xFFFF for r in regs)
    assert codec.decode(regs, type_, order) == raw


@given(st.floats(allow_nan=False, width=32), st.sampled_from(["big", "little"]))
def test_float32_round_trip(x: float, order: str) -> None:
    assert codec.decode(codec.encode(x, "float32", order), "float32", order) == x


@given(st.floats(allow_nan=False), st.sampled_from(["big", "little"]))
def test_float64_round_trip(x: float, order: str) -> None:
    assert codec.decode(codec.encode(x, "float64", order), "float64", order) == x


@given(
    _int_case(),
    st.sampled_from([Decimal("1"), Decimal("0.01"), Decimal("0.1"), Decimal("5"), Decimal("-0.5")]),
    st.sampled_from([Decimal("0"), Decimal("-40"), Decimal("0.25")]),
    st.sampled_from(["big", "little"]),
)
def test_engineering_round_trip(case: tuple[str, int], scale: Decimal, offset: Decimal, order: str) -> None:
    type_, raw = case
    eng = codec.from_raw(raw, scale, offset)
    regs = codec.engineering_to_registers(eng, type_, scale, offset, order)
    assert codec.decode(regs, type_, order) == raw
    assert codec.registers_to_engineering(regs, type_, scale, offset, order) == eng


# ---- layouts: ABCD, CDAB, BADC, DCBA and their 64-bit forms ---------------------------------

# Honeywell HC900 Communications User Guide, "Modbus Double Register Format" (Table 3-1 and 3.2):
# the value 12345678h in its four selectable formats, register N then register N+1.
#   FP B  (byte order 4,3,2,1) = ABCD: 1234 5678     FP BB (3,4,1,2) = BADC: 3412 7856
#   FP L  (1,2,3,4)            = DCBA: 7856 3412     FP LB (2,1,4,3) = CDAB: 5678 1234 (Modicon standard)
HC900 = {"ABCD": (0x1234, 0x5678), "BADC": (0x3412, 0x7856), "DCBA": (0x7856, 0x3412), "CDAB": (0x5678, 0x1234)}


@pytest.mark.parametrize("layout", sorted(HC900))
def test_hc900_manual_example_per_layout(layout: str) -> None:
    order, swap = codec.LAYOUTS[layout]
    assert codec.encode(0x12345678, "uint32", order, swap) == HC900[layout]
    assert codec.decode(HC900[layout], "uint32", order, swap) == 0x12345678
    assert codec.layout_name(order, swap, "uint32") == layout


@pytest.mark.parametrize(
    ("swap", "layout"), [("none", "ABCD"), ("byte", "BADC"), ("word", "CDAB"), ("word_byte", "DCBA")]
)
def test_home_assistant_swap_names(swap: str, layout: str) -> None:
    # Home Assistant modbus integration: swap none|byte|word|word_byte
    assert codec.SWAPS[swap] == codec.LAYOUTS[layout]


def test_float32_layouts_of_one_value() -> None:
    # IEEE 754: 123.456f = 42F6E979h (bytes A=42 B=F6 C=E9 D=79)
    expected = {"ABCD": (0x42F6, 0xE979), "CDAB": (0xE979, 0x42F6), "BADC": (0xF642, 0x79E9), "DCBA": (0x79E9, 0xF642)}
    for layout, regs in expected.items():
        assert codec.encode(123.456, "float32", *codec.LAYOUTS[layout]) == regs


@pytest.mark.parametrize(
    ("layout", "regs"),
    [
        ("ABCDEFGH", (0x0102, 0x0304, 0x0506, 0x0708)),
        ("GHEFCDAB", (0x0708, 0x0506, 0x0304, 0x0102)),
        ("BADCFEHG", (0x0201, 0x0403, 0x0605, 0x0807)),
        ("HGFEDCBA", (0x0807, 0x0605, 0x0403, 0x0201)),
    ],
)
def test_64_bit_layouts(layout: str, regs: tuple[int, ...]) -> None:
    # bytes A..H = 01..08: each name spells which byte lands where
    order, swap = codec.LAYOUTS[layout]
    assert codec.encode(0x0102030405060708, "uint64", order, swap) == regs
    assert codec.layout_name(order, swap, "uint64") == layout


_LAYOUT_PAIRS = sorted(set(codec.LAYOUTS.values()))


@given(_int_case(), st.sampled_from(_LAYOUT_PAIRS))
def test_integer_round_trip_every_layout(case: tuple[str, int], layout: tuple[str, bool]) -> None:
    type_, raw = case
    regs = codec.encode(raw, type_, *layout)
    assert codec.decode(regs, type_, *layout) == raw
    # a layout is a permutation of the bytes of the big-endian form
    big = b"".join(w.to_bytes(2, "big") for w in codec.encode(raw, type_))
    assert sorted(b"".join(w.to_bytes(2, "big") for w in regs)) == sorted(big)


@given(st.floats(allow_nan=False), st.sampled_from(_LAYOUT_PAIRS), st.sampled_from(["float32", "float64"]))
def test_float_round_trip_every_layout(x: float, layout: tuple[str, bool], type_: str) -> None:
    if type_ == "float32":
        x = codec.decode(codec.encode(x if abs(x) < 3e38 else 0.0, "float32"), "float32")
    assert codec.decode(codec.encode(x, type_, *layout), type_, *layout) == x


# ---- strings ----------------------------------------------------------------------------------


def test_string_golden_bytes() -> None:
    # two characters per register, the first in the high byte (e.g. Vaisala's Modbus API, SunSpec);
    # NUL padding; byte swap puts the first character in the low byte
    assert codec.encode_string("ABC", 2) == (0x4142, 0x4300)
    assert codec.encode_string("ABC", 2, padding="space") == (0x4142, 0x4320)
    assert codec.encode_string("ABC", 2, byte_swap=True) == (0x4241, 0x0043)
    assert codec.encode_string("Müller", 3, "latin-1") == (0x4DFC, 0x6C6C, 0x6572)


def test_string_errors() -> None:
    with pytest.raises(CodecError, match="5 characters; 2 registers hold at most 4"):
        codec.encode_string("ABCDE", 2)
    with pytest.raises(CodecError, match="'ü' at character 2 is not ascii"):
        codec.encode_string("Mü", 2)
    with pytest.raises(CodecError, match="not ascii text"):
        codec.decode_string((0x41FC,))


@given(
    st.text(alphabet=st.characters(min_codepoint=0x21, max_codepoint=0xFF), max_size=16),
    st.sampled_from(["nul", "space"]),
    st.booleans(),
)
def test_string_round_trip(text: str, padding: str, swap: bool) -> None:
    regs = codec.encode_string(text, 8, "latin-1", padding, swap)
    assert len(regs) == 8
    assert codec.decode_string(regs, "latin-1", swap) == text


# ---- bit fields -------------------------------------------------------------------------------


def test_bits_and_masks() -> None:
    assert codec.parse_bits(3) == 0x0008
    assert codec.parse_bits("3..5") == 0x0038
    assert codec.mask_shift(0x0038) == (3, 3)
    with pytest.raises(ValueError, match="contiguous"):
        codec.mask_shift(0x0101)
    with pytest.raises(ValueError, match="outside 0..15"):
        codec.parse_bits("14..16")
    assert codec.insert_field(5, 0x0038, word=0xFFFF) == 0xFFEF
    assert codec.extract_field(0xFFEF, 0x0038) == 5
    assert codec.extract_field(0x0030, 0x0038, signed=True) == -2
    with pytest.raises(CodecError, match="does not fit in 3 bits"):
        codec.insert_field(8, 0x0038)


@given(st.integers(0, 15), st.integers(1, 16), st.integers(0, 0xFFFF), st.data())
def test_field_round_trip_keeps_other_bits(lo: int, width: int, word: int, data: st.DataObject) -> None:
    width = min(width, 16 - lo)
    mask = ((1 << width) - 1) << lo
    raw = data.draw(st.integers(0, (1 << width) - 1))
    new = codec.insert_field(raw, mask, word=word)
    assert codec.extract_field(new, mask) == raw
    assert new & ~mask == word & ~mask


@pytest.mark.parametrize(
    ("name", "layout"),
    [
        ("big-endian", "ABCD"),
        ("little-endian", "DCBA"),
        ("big-endian-byte-swap", "BADC"),
        ("big-endian-word-swap", "CDAB"),
        ("little-endian-byte-swap", "CDAB"),
        ("little-endian-word-swap", "BADC"),  # DCBA with bytes / words swapped
    ],
)
def test_layout_names_from_tools(name: str, layout: str) -> None:
    assert codec.LAYOUTS[name] == codec.LAYOUTS[layout]


def test_pint_that_cannot_load_is_never_kept_as_an_unknown_unit(monkeypatch: pytest.MonkeyPatch) -> None:
    """A unit check while pint cannot be imported (a broken install, a platform module missing) raises;
    it is not answered, nor saved in the units cache, as "unknown unit" (that poisoned every later run)."""
    import sys

    from deployer.profile import units

    fresh = units._DiskCache.__new__(units._DiskCache)
    fresh.checks, fresh.factors, fresh.dirty, fresh.writable, fresh.path = {}, {}, False, False, None
    monkeypatch.setattr(units, "_disk", lambda: fresh)
    units.check.cache_clear()
    units.registry.cache_clear()
    monkeypatch.setitem(sys.modules, "pint", None)
    try:
        with pytest.raises(ImportError):
            units.check("Hz")
        assert fresh.checks == {} and not fresh.dirty
    finally:
        monkeypatch.undo()
        units.check.cache_clear()
        units.registry.cache_clear()
    assert units.check("Hz") is None and units.check("zorks per Hz") is not None
