"""What a plan costs on the wire: RTU bytes and seconds at a line speed."""

from __future__ import annotations

from collections.abc import Iterable

from .model import Plan

# ---- cost on the wire --------------------------------------------------------------------------

BAUD = 19200
CHAR_BITS = 11  # 8E1: start + 8 data + parity + stop


def _rtu_request_bytes(function: int, count: int) -> int:
    # unit(1) + PDU + CRC(2); PDU: FC16 fc addr qty bytecount data = 6 + 2n, FC15 6 + ceil(n / 8),
    # FC06, FC05 and the reads = 5
    if function == 16:
        return 9 + 2 * count
    if function == 15:
        return 9 + (count + 7) // 8
    return 8


def _rtu_response_bytes(function: int, count: int) -> int:
    # FC16/FC15 echo address and quantity, FC06/FC05 echo the request, reads carry bytecount + data
    if function in (3, 4):
        return 5 + 2 * count
    if function in (1, 2):
        return 5 + (count + 7) // 8
    return 8


def line_cost(plan: Plan, *, framing: str = "rtu", baud: int = BAUD, char_bits: int = CHAR_BITS) -> tuple[int, float]:
    """Characters on a serial line and seconds for the plan's write requests and their answers.

    RTU: binary frames plus the 3.5-character silence that ends each; ASCII: every byte but the CRC
    becomes two hex characters, plus ':', the LRC (two characters) and CR LF (2n + 1 characters for an
    n-byte RTU frame), and no silence. ``char_bits``: start + data + parity + stop bits.
    """
    answers = plan.device.unit != 0
    chars = 0.0
    frames = 0
    for w in plan.writes:
        sizes = [_rtu_request_bytes(w.function, w.count)]
        if answers:
            sizes.append(_rtu_response_bytes(w.function, w.count))
        for n in sizes:
            frames += 1
            chars += 2 * n + 1 if framing == "ascii" else n
    silence = 0.0 if framing == "ascii" else 3.5 * frames
    return int(chars), (chars + silence) * char_bits / baud


def wire_stats(plan: Plan) -> dict[str, float | int]:
    """Bytes and line time of the plan's write requests and their answers on an RTU line.

    ``rtu_bytes`` counts requests plus the answers the device gives (none for unit 0, broadcast);
    ``seconds_19200`` is that at 19200 baud, 8E1 (11 bits a character), plus the 3.5-character
    silent interval that ends every frame. ``read_*`` is the same for the plan's FC03 blocks
    (one pass: snapshot or read-back).
    """
    char = CHAR_BITS / BAUD
    answers = plan.device.unit != 0

    def cost(reqs: Iterable[tuple[int, int]]) -> tuple[int, int]:
        total = frames = 0
        for function, count in reqs:
            total += _rtu_request_bytes(function, count)
            frames += 1
            if answers:
                total += _rtu_response_bytes(function, count)
                frames += 1
        return total, frames

    w_bytes, w_frames = cost((w.function, w.count) for w in plan.writes)
    r_bytes, r_frames = cost((r.function, r.count) for r in plan.reads)
    return {"requests": len(plan.writes), "registers": sum(w.count for w in plan.writes), "rtu_bytes": w_bytes,
            "seconds_19200": round((w_bytes + 3.5 * w_frames) * char, 6),
            "read_requests": len(plan.reads), "read_registers": sum(r.count for r in plan.reads),
            "read_rtu_bytes": r_bytes, "read_seconds_19200": round((r_bytes + 3.5 * r_frames) * char, 6)}
