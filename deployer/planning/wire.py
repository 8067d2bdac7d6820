"""What a plan costs one device: requests, bytes and time on the line, waits, and writes that wear memory."""

from __future__ import annotations

from typing import TYPE_CHECKING

from .model import DEVICE_ID, Cost, Plan, Step

if TYPE_CHECKING:
    from ..profile import Profile
    from ..transport.urls import DeviceURL

BAUD = 19200
CHAR_BITS = 11  # 8E1: start + 8 data + parity + stop
# a Function 43 answer's fixed part (MEI type, read code, conformity, more, next id, number of objects) and the
# three basic objects' id and length bytes: their texts are the device's, unknown until it answers
_DEVICE_ID_ANSWER = 7 + 3 * 2


def _pdu_sizes(function: int, count: int) -> tuple[int, int]:
    """(request, answer) PDU bytes of one request of ``function`` over ``count`` registers or bits."""
    if function == 16:
        return 6 + 2 * count, 5
    if function == 15:
        return 6 + (count + 7) // 8, 5
    if function in (3, 4):
        return 5, 2 + 2 * count
    if function in (1, 2):
        return 5, 2 + (count + 7) // 8
    if function == DEVICE_ID:
        return 4, _DEVICE_ID_ANSWER
    return 5, 5  # 05 and 06 echo the request


def _frame(pdu: int, framing: str) -> int:
    """Bytes (characters on ASCII) of a frame carrying ``pdu`` bytes: unit + PDU + CRC on RTU; ':', the unit
    and PDU as hex pairs, the LRC (two characters) and CR LF on ASCII; the 7-byte MBAP header and the PDU on
    Modbus/TCP."""
    if framing == "ascii":
        return 1 + 2 * (1 + pdu) + 2 + 2
    if framing == "tcp":
        return 7 + pdu
    return 1 + pdu + 2


def line_of(device: DeviceURL | None) -> tuple[str, int, int, str]:
    """(framing, baud, bits a character, the line's text) for a device URL: its serial settings; RTU frames at
    Modbus's default 19200 8E1 for a gateway (rtu+tcp) or no device; Modbus/TCP frames (no line) on TCP."""
    if device is not None and device.scheme in ("rtu", "ascii"):
        ln = device.line
        bits = 1 + ln.bytesize + (ln.parity != "N") + ln.stopbits
        return device.scheme, ln.baudrate, bits, f"{ln.baudrate} baud {ln.bytesize}{ln.parity}{ln.stopbits}"
    if device is not None and device.scheme in ("tcp", "tls"):
        return "tcp", 0, 0, "Modbus/TCP"
    return "rtu", BAUD, CHAR_BITS, f"{BAUD} baud 8E1"


def step_bytes(step: Step, framing: str, answers: bool = True) -> int:
    request, answer = _pdu_sizes(step.function, step.count)
    return _frame(request, framing) + (_frame(answer, framing) if answers else 0)


def plan_cost(plan: Plan, profile: Profile | None = None, device: DeviceURL | None = None) -> Cost:
    """The plan's cost on ``device``'s line (see ``Cost``), every step sent once, in the order planned."""
    framing, baud, bits, line = line_of(device)
    answers = plan.device.unit != 0
    total = frames = 0
    for s in plan.steps:
        total += step_bytes(s, framing, answers)
        frames += 2 if answers else 1
    seconds = 0.0
    if baud:  # the 3.5-character silence ends every RTU frame; ASCII frames end with CR LF
        silence = 3.5 * frames if framing == "rtu" else 0.0
        seconds = (total + silence) * bits / baud
    n = len(plan.steps)
    p = plan.pacing
    waits = sum(s.wait for s in plan.steps) + ((p.after_connect + p.between_requests * (n - 1)) if n else 0.0)
    writes = [s for s in plan.steps if s.writes]
    commits = [s for s in writes if s.kind == "commit"]
    stored = [s for s in writes if s.kind == "write"]
    if commits:  # a commit stores what is in RAM: every parameter the plan writes
        nv, stores = len(commits), tuple(n for s in stored for n in s.parameters)
    elif profile is not None:  # no commit: writes go where they go; a stated endurance says that memory wears
        lasting = {q.name for q in profile.parameters if q.endurance or profile.endurance}
        worn = [s for s in stored if lasting.intersection(s.parameters)]
        nv, stores = len(worn), tuple(n for s in worn for n in s.parameters if n in lasting)
    else:
        nv, stores = 0, ()
    return Cost(
        requests=n,
        reads=n - len(writes),
        writes=len(writes),
        bytes=total,
        framing=framing,
        line=line,
        seconds=round(seconds + waits, 6),
        waits=round(waits, 6),
        non_volatile_writes=nv,
        stores=stores,
    )
