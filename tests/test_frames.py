"""Golden tests: the manuals' example frames, byte for byte, from recipes in engineering units."""

from __future__ import annotations

from pathlib import Path

from deployer.frames import request_frame, response_frame
from deployer.planner import ReadRequest, Target, make_plan
from deployer.recipe import load_recipe

EXAMPLES = Path(__file__).parent.parent / "recipes" / "examples"


def hexbytes(text: str) -> bytes:
    return bytes.fromhex(text.replace(" ", ""))


def plan_of(path: Path, unit: int):  # type: ignore[no-untyped-def]
    rec = load_recipe(str(path))
    return make_plan(rec, Target(None, unit, rec.profile.id))


def test_omron_m1_f07_ten_seconds() -> None:
    """M1 manual I669 8-5-7: slave 1, F07 (1103h) = 10 s at 0.01 s."""
    plan = plan_of(EXAMPLES / "omron-m1-accel.yaml", 1)
    (w,) = plan.writes
    assert request_frame(w, 1, "rtu") == hexbytes("01 10 11 02 00 02 04 00 00 03 E8 B2 98")
    assert response_frame(w, 1, "rtu") == hexbytes("01 10 11 02 00 02 E5 34")


def test_oriental_az_operation_data_no3() -> None:
    """AZ manual HM-60252J p.267: server 4, operation data No.3 rates and current in one request."""
    plan = plan_of(EXAMPLES / "oriental-az-op3.yaml", 4)
    (w,) = plan.writes
    assert (w.address, w.count) == (0x18C6, 6)
    assert request_frame(w, 4, "rtu") == hexbytes(
        "04 10 18 C6 00 06 0C 00 00 27 10 00 00 4E 20 00 00 01 F4 6C A0")
    assert response_frame(w, 4, "rtu") == hexbytes("04 10 18 C6 00 06 A6 C3")


def test_from_a_recipe_in_other_units(tmp_path: Path) -> None:
    p = tmp_path / "r.yaml"
    p.write_text("recipe: t\nprofile: omron-m1\nparameters: {F07: 10000 ms}\n")
    (w,) = plan_of(p, 1).writes
    assert request_frame(w, 1, "rtu").hex() == "01101102000204000003e8b298"


def test_ascii_frame_has_lrc() -> None:
    (w,) = plan_of(EXAMPLES / "omron-m1-accel.yaml", 1).writes
    frame = request_frame(w, 1, "ascii")
    assert frame.startswith(b":") and frame.endswith(b"\r\n")
    body = bytes.fromhex(frame[1:-2].decode())
    assert body[:-1] == hexbytes("01 10 11 02 00 02 04 00 00 03 E8")
    assert (sum(body[:-1]) + body[-1]) & 0xFF == 0  # LRC: two's complement of the byte sum
    # by hand: 01+10+11+02+00+02+04+00+00+03+E8 = 0x115; -0x15 & 0xFF = 0xEB
    assert frame == b":01101102000204000003E8EB\r\n"


def test_tcp_adu() -> None:
    (w,) = plan_of(EXAMPLES / "omron-m1-accel.yaml", 1).writes
    adu = request_frame(w, 1, "tcp", transaction_id=7)
    # MBAP: transaction 7, protocol 0, length 11 (unit + PDU), then the PDU without CRC
    assert adu == hexbytes("00 07 00 00 00 0B 01 10 11 02 00 02 04 00 00 03 E8")


def test_read_frames() -> None:
    req = ReadRequest(0x1102, 2)
    assert request_frame(req, 1, "rtu")[:6] == hexbytes("01 03 11 02 00 02")
    assert response_frame(req, 1, "rtu", [0, 1000])[:7] == hexbytes("01 03 04 00 00 03 E8")
