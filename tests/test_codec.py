"""Codec: exact engineering <-> raw <-> registers, the seeds' values, and round trips."""

from __future__ import annotations

from decimal import Decimal

import pytest
from hypothesis import given
from hypothesis import strategies as st

from deployer import codec


def test_omron_f07_ten_seconds_is_0000_03e8() -> None:
    # ../shared/seeds/omron-m1-p668.txt: 10 s at 0.01 s -> 1000 -> 0000 03E8 hex
    assert codec.engineering_to_registers(Decimal("10"), "uint32", Decimal("0.01")) == (0x0000, 0x03E8)


@pytest.mark.parametrize(
    ("value", "regs"), [(10000, (0x0000, 0x2710)), (20000, (0x0000, 0x4E20)), (500, (0x0000, 0x01F4))]
)
def test_oriental_operation_data_no3(value: int, regs: tuple[int, int]) -> None:
    # ../shared/seeds/oriental-az-HM-60252J-p267.txt, 32-bit, upper word first
    assert codec.engineering_to_registers(Decimal(value), "int32") == regs


def test_not_a_multiple_of_resolution() -> None:
    with pytest.raises(codec.CodecError, match="not a multiple of the resolution 0.01"):
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
    with pytest.raises(codec.CodecError, match="does not fit in uint16"):
        codec.encode(65536, "uint16")
    with pytest.raises(codec.CodecError, match="does not fit in int16"):
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
