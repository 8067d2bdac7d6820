"""Exact bytes of each request and its normal answer, rendered by pymodbus's own framers.

Used by ``plan --show-frames`` and the golden tests against the manuals' example frames.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

from pymodbus.framer import FramerAscii, FramerRTU, FramerSocket
from pymodbus.pdu import DecodePDU, ModbusPDU
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadHoldingRegistersResponse,
    WriteMultipleRegistersRequest,
    WriteMultipleRegistersResponse,
    WriteSingleRegisterRequest,
    WriteSingleRegisterResponse,
)

from ..load.diagnostics import UsageError
from .model import ReadRequest, WriteRequest

Framing = Literal["rtu", "ascii", "tcp"]
_FRAMERS = {"rtu": FramerRTU, "ascii": FramerAscii, "tcp": FramerSocket}


def _frame(pdu: ModbusPDU, framing: Framing) -> bytes:
    framer = _FRAMERS[framing](DecodePDU(is_server=False))
    return bytes(framer.buildFrame(pdu))


def _check(req: WriteRequest | ReadRequest, unit: int, transaction_id: int) -> None:
    """pymodbus encodes out-of-range values with struct (a traceback) or not at all: refuse them first."""
    if not 0 <= unit <= 255:
        raise UsageError(f"unit {unit} is outside 0..255")
    if not 0 <= transaction_id <= 0xFFFF:
        raise UsageError(f"transaction id {transaction_id} is outside 0..65535")
    top = 125 if isinstance(req, ReadRequest) else (1 if req.function == 6 else 123)
    if not 1 <= req.count <= top:
        raise UsageError(f"a function {req.function} request carries 1..{top} registers, not {req.count}")
    if not 0 <= req.address <= 0xFFFF - req.count + 1:
        raise UsageError(f"registers {req.address}..{req.address + req.count - 1} are outside 0..65535")
    if isinstance(req, WriteRequest) and any(not 0 <= v <= 0xFFFF for v in req.registers):
        raise UsageError(f"a register value at {req.address} is outside 0..65535")


def request_pdu(req: WriteRequest | ReadRequest, unit: int, transaction_id: int = 0) -> ModbusPDU:
    _check(req, unit, transaction_id)
    if isinstance(req, ReadRequest):
        return ReadHoldingRegistersRequest(address=req.address, count=req.count, dev_id=unit,
                                           transaction_id=transaction_id)
    if req.function == 6:
        return WriteSingleRegisterRequest(address=req.address, registers=list(req.registers), dev_id=unit,
                                          transaction_id=transaction_id)
    return WriteMultipleRegistersRequest(address=req.address, registers=list(req.registers), dev_id=unit,
                                         transaction_id=transaction_id)


def request_frame(req: WriteRequest | ReadRequest, unit: int, framing: Framing, transaction_id: int = 1) -> bytes:
    """The request as sent on the wire: RTU (CRC low byte first), ASCII (LRC) or a Modbus/TCP ADU."""
    return _frame(request_pdu(req, unit, transaction_id if framing == "tcp" else 0), framing)


def response_frame(req: WriteRequest | ReadRequest, unit: int, framing: Framing,
                   registers: Sequence[int] | None = None, transaction_id: int = 1) -> bytes:
    """The normal answer of a device to ``req`` (for reads, carrying ``registers``, default zeros)."""
    tid = transaction_id if framing == "tcp" else 0
    _check(req, unit, tid)
    pdu: ModbusPDU
    if isinstance(req, ReadRequest):
        regs = list(registers) if registers is not None else [0] * req.count
        if len(regs) != req.count or any(not 0 <= v <= 0xFFFF for v in regs):
            raise UsageError(f"a read of {req.count} registers answers {req.count} values in 0..65535")
        pdu = ReadHoldingRegistersResponse(registers=regs, dev_id=unit, transaction_id=tid)
    elif req.function == 6:
        pdu = WriteSingleRegisterResponse(address=req.address, registers=list(req.registers), dev_id=unit,
                                          transaction_id=tid)
    else:
        pdu = WriteMultipleRegistersResponse(address=req.address, count=req.count, dev_id=unit, transaction_id=tid)
    return _frame(pdu, framing)
