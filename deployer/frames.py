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

from .planner import ReadRequest, WriteRequest

Framing = Literal["rtu", "ascii", "tcp"]
_FRAMERS = {"rtu": FramerRTU, "ascii": FramerAscii, "tcp": FramerSocket}


def _frame(pdu: ModbusPDU, framing: Framing) -> bytes:
    framer = _FRAMERS[framing](DecodePDU(is_server=False))
    return bytes(framer.buildFrame(pdu))


def request_pdu(req: WriteRequest | ReadRequest, unit: int, transaction_id: int = 0) -> ModbusPDU:
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
    pdu: ModbusPDU
    if isinstance(req, ReadRequest):
        regs = list(registers) if registers is not None else [0] * req.count
        pdu = ReadHoldingRegistersResponse(registers=regs, dev_id=unit, transaction_id=tid)
    elif req.function == 6:
        pdu = WriteSingleRegisterResponse(address=req.address, registers=list(req.registers), dev_id=unit,
                                          transaction_id=tid)
    else:
        pdu = WriteMultipleRegistersResponse(address=req.address, count=req.count, dev_id=unit, transaction_id=tid)
    return _frame(pdu, framing)
