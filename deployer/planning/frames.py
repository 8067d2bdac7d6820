"""Exact bytes of each request and its normal answer, rendered by pymodbus's own framers.

Used by ``plan --show-frames`` and the golden tests against the manuals' example frames.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

from pymodbus.framer import FramerAscii, FramerRTU, FramerSocket
from pymodbus.pdu import DecodePDU, ModbusPDU
from pymodbus.pdu.bit_message import (
    ReadCoilsRequest,
    ReadCoilsResponse,
    ReadDiscreteInputsRequest,
    ReadDiscreteInputsResponse,
    WriteMultipleCoilsRequest,
    WriteMultipleCoilsResponse,
    WriteSingleCoilRequest,
    WriteSingleCoilResponse,
)
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadHoldingRegistersResponse,
    ReadInputRegistersRequest,
    ReadInputRegistersResponse,
    WriteMultipleRegistersRequest,
    WriteMultipleRegistersResponse,
    WriteSingleRegisterRequest,
    WriteSingleRegisterResponse,
)

from ..errors import UsageError
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
    if req.function not in _TOP:
        raise UsageError(f"function {req.function} is none of {', '.join(map(str, sorted(_TOP)))}")
    top = _TOP[req.function]
    what = "coils" if req.function in (1, 2, 5, 15) else "registers"
    if not 1 <= req.count <= top:
        raise UsageError(f"a function {req.function} request carries 1..{top} {what}, not {req.count}")
    if not 0 <= req.address <= 0xFFFF - req.count + 1:
        raise UsageError(f"{what} {req.address}..{req.address + req.count - 1} are outside 0..65535")
    if isinstance(req, WriteRequest):
        if req.function in (5, 15) and any(v not in (0, 1) for v in req.registers):
            raise UsageError(f"a coil value at {req.address} is not 0 or 1")
        if any(not 0 <= v <= 0xFFFF for v in req.registers):
            raise UsageError(f"a register value at {req.address} is outside 0..65535")


# the most one request of each function carries (Modbus Application Protocol v1.1b3, 6.1-6.12)
_TOP = {1: 2000, 2: 2000, 3: 125, 4: 125, 5: 1, 6: 1, 15: 1968, 16: 123}
_READS = {1: ReadCoilsRequest, 2: ReadDiscreteInputsRequest, 3: ReadHoldingRegistersRequest,
          4: ReadInputRegistersRequest}
_READ_ANSWERS = {1: ReadCoilsResponse, 2: ReadDiscreteInputsResponse, 3: ReadHoldingRegistersResponse,
                 4: ReadInputRegistersResponse}


def request_pdu(req: WriteRequest | ReadRequest, unit: int, transaction_id: int = 0) -> ModbusPDU:
    _check(req, unit, transaction_id)
    if isinstance(req, ReadRequest):
        return _READS[req.function](address=req.address, count=req.count, dev_id=unit,
                                    transaction_id=transaction_id)
    if req.function == 5:
        return WriteSingleCoilRequest(address=req.address, bits=[bool(req.registers[0])], dev_id=unit,
                                      transaction_id=transaction_id)
    if req.function == 15:
        return WriteMultipleCoilsRequest(address=req.address, bits=[bool(b) for b in req.registers], dev_id=unit,
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
    """The normal answer of a device to ``req`` (for reads, carrying ``registers`` or bits 0/1, default zeros)."""
    tid = transaction_id if framing == "tcp" else 0
    _check(req, unit, tid)
    pdu: ModbusPDU
    if isinstance(req, ReadRequest):
        regs = list(registers) if registers is not None else [0] * req.count
        top = 1 if req.function in (1, 2) else 0xFFFF
        if len(regs) != req.count or any(not 0 <= v <= top for v in regs):
            raise UsageError(f"a read of {req.count} answers {req.count} values in 0..{top}")
        if req.function in (1, 2):  # the bits, padded with zeros to whole bytes
            bits = [bool(v) for v in regs] + [False] * (-req.count % 8)
            pdu = _READ_ANSWERS[req.function](bits=bits, dev_id=unit, transaction_id=tid)
        else:
            pdu = _READ_ANSWERS[req.function](registers=regs, dev_id=unit, transaction_id=tid)
    elif req.function == 5:
        pdu = WriteSingleCoilResponse(address=req.address, bits=[bool(req.registers[0])], dev_id=unit,
                                      transaction_id=tid)
    elif req.function == 15:
        pdu = WriteMultipleCoilsResponse(address=req.address, count=req.count, dev_id=unit, transaction_id=tid)
    elif req.function == 6:
        pdu = WriteSingleRegisterResponse(address=req.address, registers=list(req.registers), dev_id=unit,
                                          transaction_id=tid)
    else:
        pdu = WriteMultipleRegistersResponse(address=req.address, count=req.count, dev_id=unit, transaction_id=tid)
    return _frame(pdu, framing)
