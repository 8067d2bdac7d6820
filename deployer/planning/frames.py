"""Exact bytes of each request and its normal answer, rendered by pymodbus's own framers.

Used by ``plan --show-frames`` (every step of a plan: ``step_frames``, ``shown``) and the golden tests against
the manuals' example frames.
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
from pymodbus.pdu.mei_message import ReadDeviceInformationRequest
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
from .model import DEVICE_ID, MOST_PER_REQUEST, ReadRequest, Step, WriteRequest

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
    if req.function not in MOST_PER_REQUEST:
        raise UsageError(f"function {req.function} is none of {', '.join(map(str, sorted(MOST_PER_REQUEST)))}")
    top = MOST_PER_REQUEST[req.function]
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


_READS = {
    1: ReadCoilsRequest,
    2: ReadDiscreteInputsRequest,
    3: ReadHoldingRegistersRequest,
    4: ReadInputRegistersRequest,
}
_READ_ANSWERS = {
    1: ReadCoilsResponse,
    2: ReadDiscreteInputsResponse,
    3: ReadHoldingRegistersResponse,
    4: ReadInputRegistersResponse,
}


def request_pdu(req: WriteRequest | ReadRequest, unit: int, transaction_id: int = 0) -> ModbusPDU:
    _check(req, unit, transaction_id)
    if isinstance(req, ReadRequest):
        return _READS[req.function](address=req.address, count=req.count, dev_id=unit, transaction_id=transaction_id)
    if req.function == 5:
        return WriteSingleCoilRequest(
            address=req.address, bits=[bool(req.registers[0])], dev_id=unit, transaction_id=transaction_id
        )
    if req.function == 15:
        return WriteMultipleCoilsRequest(
            address=req.address, bits=[bool(b) for b in req.registers], dev_id=unit, transaction_id=transaction_id
        )
    if req.function == 6:
        return WriteSingleRegisterRequest(
            address=req.address, registers=list(req.registers), dev_id=unit, transaction_id=transaction_id
        )
    return WriteMultipleRegistersRequest(
        address=req.address, registers=list(req.registers), dev_id=unit, transaction_id=transaction_id
    )


def request_frame(req: WriteRequest | ReadRequest, unit: int, framing: Framing, transaction_id: int = 1) -> bytes:
    """The request as sent on the wire: RTU (CRC low byte first), ASCII (LRC) or a Modbus/TCP ADU."""
    return _frame(request_pdu(req, unit, transaction_id if framing == "tcp" else 0), framing)


def response_frame(
    req: WriteRequest | ReadRequest,
    unit: int,
    framing: Framing,
    registers: Sequence[int] | None = None,
    transaction_id: int = 1,
) -> bytes:
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
        pdu = WriteSingleCoilResponse(
            address=req.address, bits=[bool(req.registers[0])], dev_id=unit, transaction_id=tid
        )
    elif req.function == 15:
        pdu = WriteMultipleCoilsResponse(address=req.address, count=req.count, dev_id=unit, transaction_id=tid)
    elif req.function == 6:
        pdu = WriteSingleRegisterResponse(
            address=req.address, registers=list(req.registers), dev_id=unit, transaction_id=tid
        )
    else:
        pdu = WriteMultipleRegistersResponse(address=req.address, count=req.count, dev_id=unit, transaction_id=tid)
    return _frame(pdu, framing)


# ---- plan steps -----------------------------------------------------------------------------------


def _as_request(step: Step, values: tuple[int, ...] | None = None) -> WriteRequest | ReadRequest:
    if step.writes:
        words = values if values is not None else (step.values if step.values is not None else (0,) * step.count)
        return step.write(words)
    return step.read()


def step_frames(step: Step, unit: int, framing: Framing, transaction_id: int = 1) -> tuple[bytes, bytes | None]:
    """A plan step as (the query, the device's normal answer) on the wire; the answer is None for a broadcast
    and for Function 43 (its texts are the device's). A secret step's words go as zeros: ``shown`` masks them."""
    tid = transaction_id if framing == "tcp" else 0
    if step.function == DEVICE_ID:
        if not 0 <= unit <= 255:
            raise UsageError(f"unit {unit} is outside 0..255")
        pdu = ReadDeviceInformationRequest(read_code=1, object_id=step.address, dev_id=unit, transaction_id=tid)
        return _frame(pdu, framing), None
    req = _as_request(step)
    query = request_frame(req, unit, framing, transaction_id)
    return query, None if unit == 0 else response_frame(req, unit, framing, transaction_id=transaction_id)


def shown(
    step: Step, frame: bytes, unit: int, framing: Framing, transaction_id: int = 1, *, answer: bool = False
) -> str:
    """A frame as text (hex bytes; ASCII as its characters) with a secret step's words and the checksum that
    depends on them masked (``**``): the bytes that change when the words do."""
    text = frame.decode("ascii").strip() if framing == "ascii" else frame.hex(" ").upper()
    if not step.secret or (answer and step.function == 16):
        return text
    variants = []
    for word in (0x0000, 0xFFFF, 0x5A5A):
        req = _as_request(step, (word,) * step.count)
        f = (
            response_frame(req, unit, framing, transaction_id=transaction_id)
            if answer
            else request_frame(req, unit, framing, transaction_id)
        )
        variants.append(f.decode("ascii").strip() if framing == "ascii" else f.hex(" ").upper())
    if framing == "ascii":
        return "".join(
            "*" if len({v[i] for v in variants}) > 1 or i >= len(text) - 2 else c for i, c in enumerate(text)
        )
    parts = [v.split(" ") for v in variants]
    own = text.split(" ")
    check = 2 if framing == "rtu" else 0  # the CRC depends on the words whatever their value
    return " ".join("**" if len({p[i] for p in parts}) > 1 or i >= len(own) - check else b for i, b in enumerate(own))
