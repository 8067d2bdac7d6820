"""Golden tests: the manuals' example frames, byte for byte, from recipes in engineering units."""

from __future__ import annotations

import socket
from decimal import Decimal
from pathlib import Path

import pytest

from deployer.errors import UsageError
from deployer.planning.frames import Framing, request_frame, response_frame
from deployer.planning.model import ReadRequest, Target, WriteRequest
from deployer.planning.steps import make_plan
from deployer.profile import builtin_profile, codec
from deployer.recipe.loader import Desired, Recipe, load_recipe
from deployer.testing.simulator import SimulatorThread

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
    assert request_frame(w, 4, "rtu") == hexbytes("04 10 18 C6 00 06 0C 00 00 27 10 00 00 4E 20 00 00 01 F4 6C A0")
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


# ---- independent of the recipe loader: Desired built by hand from the built-in profiles ---------


def crc16_modbus(data: bytes) -> bytes:
    """The Modbus CRC written out here, to check pymodbus's framer independently."""
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return bytes([crc & 0xFF, crc >> 8])  # low byte first on the wire


def by_hand(profile_id: str, values: dict[str, Decimal]) -> Recipe:
    prof = builtin_profile(profile_id)
    ds = []
    for name, v in values.items():
        p = prof.parameter(name)
        regs = codec.engineering_to_registers(v, p.type, p.scale, p.offset, p.word_order)
        ds.append(Desired(parameter=p, text=str(v), registers=regs))
    return Recipe("by-hand", None, prof, tuple(ds))


def test_omron_by_hand() -> None:
    plan = make_plan(by_hand("omron-m1", {"F07": Decimal(10)}), Target(None, 1, "omron-m1"))
    (w,) = plan.writes
    q = request_frame(w, 1, "rtu")
    assert q == hexbytes("01 10 11 02 00 02 04 00 00 03 E8 B2 98")
    assert q[-2:] == crc16_modbus(q[:-2])
    assert response_frame(w, 1, "rtu") == hexbytes("01 10 11 02 00 02 E5 34")


def test_oriental_by_hand() -> None:
    rec = by_hand(
        "oriental-az",
        {
            "operation_data[3].starting_rate": Decimal(10000),
            "operation_data[3].stopping_rate": Decimal(20000),
            "operation_data[3].operating_current": Decimal(500),
        },
    )
    plan = make_plan(rec, Target(None, 4, "oriental-az"))
    (w,) = plan.writes
    assert w.parameters == (
        "operation_data[3].starting_rate",
        "operation_data[3].stopping_rate",
        "operation_data[3].operating_current",
    )
    assert request_frame(w, 4, "rtu") == hexbytes("04 10 18 C6 00 06 0C 00 00 27 10 00 00 4E 20 00 00 01 F4 6C A0")
    assert response_frame(w, 4, "rtu") == hexbytes("04 10 18 C6 00 06 A6 C3")
    # TCP: the same PDU behind an MBAP header whose length counts unit + PDU (1 + 18 = 0x13)
    adu = request_frame(w, 4, "tcp", transaction_id=0x1234)
    assert adu[:7] == hexbytes("12 34 00 00 00 13 04")
    assert adu[7:] == hexbytes("10 18 C6 00 06 0C 00 00 27 10 00 00 4E 20 00 00 01 F4")
    assert response_frame(w, 4, "tcp", transaction_id=0x1234) == hexbytes("12 34 00 00 00 06 04 10 18 C6 00 06")


# ---- the protocol specification's examples (Modbus over serial line / application protocol) ------


def test_spec_examples_fc03_fc06() -> None:
    read = ReadRequest(0x006B, 3)
    assert request_frame(read, 0x11, "rtu") == hexbytes("11 03 00 6B 00 03 76 87")
    answer = response_frame(read, 0x11, "rtu", [0xAE41, 0x5652, 0x4340])
    assert answer == hexbytes("11 03 06 AE 41 56 52 43 40 49 AD")
    assert answer[-2:] == crc16_modbus(answer[:-2])
    single = WriteRequest(6, 0x0001, (0x0003,), ("x",))
    assert request_frame(single, 0x11, "rtu") == hexbytes("11 06 00 01 00 03 9A 9B")
    assert response_frame(single, 0x11, "rtu") == hexbytes("11 06 00 01 00 03 9A 9B")  # FC06 echoes


def test_ascii_response_and_read() -> None:
    (w,) = plan_of(EXAMPLES / "omron-m1-accel.yaml", 1).writes
    a = response_frame(w, 1, "ascii")
    body = bytes.fromhex(a[1:-2].decode())
    assert a[:1] == b":" and a[-2:] == b"\r\n" and body[:-1] == hexbytes("01 10 11 02 00 02")
    assert (sum(body) & 0xFF) == 0
    q = request_frame(ReadRequest(0x1102, 2), 1, "ascii")
    assert q == b":010311020002" + f"{-(1 + 3 + 0x11 + 2 + 2) & 0xFF:02X}".encode() + b"\r\n"


def test_frames_refuse_what_no_device_could_take() -> None:
    with pytest.raises(UsageError, match="unit 300"):
        request_frame(ReadRequest(0, 1), 300, "rtu")
    with pytest.raises(UsageError, match="1..123 registers, not 124"):
        request_frame(WriteRequest(16, 0, tuple(range(124)), ("x",)), 1, "rtu")
    with pytest.raises(UsageError, match="outside 0..65535"):
        request_frame(WriteRequest(16, 0, (70000,), ("x",)), 1, "rtu")
    with pytest.raises(UsageError, match="outside 0..65535"):
        request_frame(ReadRequest(65535, 2), 1, "rtu")
    with pytest.raises(UsageError, match="answers 2 values"):
        response_frame(ReadRequest(0, 2), 1, "rtu", [1])


def test_every_planned_frame_has_a_valid_crc(tmp_path: Path) -> None:
    """A whole table of operation data: requests of at most 27 registers at 64-byte frames."""
    p = tmp_path / "r.yaml"
    entries = "\n".join(
        f"  operation_data[{i}]: {{starting_rate: {1000 + i}, stopping_rate: {2000 + i}}}" for i in range(8)
    )
    p.write_text(f"recipe: t\nprofile: oriental-az\nparameters:\n{entries}\n")
    plan = plan_of(p, 4)
    assert len(plan.writes) == 8  # entries are 0x40 apart: nothing contiguous between them
    for w in plan.writes:
        q = request_frame(w, 4, "rtu")
        assert q[-2:] == crc16_modbus(q[:-2]) and len(q) == 9 + 2 * w.count


# ---- on a real socket: a pymodbus server (the project's simulator) takes these bytes and answers
# exactly what response_frame predicts ------------------------------------------------------------


def _exchange(url: str, frame: bytes, expect_len: int) -> bytes:
    host, port = url.split("://", 1)[1].rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=5) as s:
        s.sendall(frame)
        got = b""
        while len(got) < expect_len:
            chunk = s.recv(expect_len - len(got))
            if not chunk:
                break
            got += chunk
        return got


@pytest.mark.timeout(30)
@pytest.mark.parametrize("scheme, framing", [("tcp", "tcp"), ("rtu+tcp", "rtu")])
def test_frames_on_the_wire(scheme: str, framing: Framing) -> None:
    rec = by_hand("omron-m1", {"F07": Decimal(10)})
    plan = make_plan(rec, Target(None, 1, "omron-m1"))
    (w,) = plan.writes
    (r,) = plan.reads
    with SimulatorThread(rec.profile, listen=f"{scheme}://127.0.0.1:0") as sim:
        assert sim.read("F07") != (0, 1000)
        q = request_frame(w, 1, framing, transaction_id=5)
        want = response_frame(w, 1, framing, transaction_id=5)
        assert _exchange(sim.url, q, len(want)) == want
        assert sim.read("F07") == (0, 1000)  # the device took the value the frame carried
        q = request_frame(r, 1, framing, transaction_id=6)
        want = response_frame(r, 1, framing, [0, 1000], transaction_id=6)
        assert _exchange(sim.url, q, len(want)) == want


@pytest.mark.timeout(30)
@pytest.mark.parametrize("framing", ["rtu", "ascii"])
def test_serial_frames_over_a_pty_pair(framing: Framing, socat_pair: tuple[str, str]) -> None:
    """The RTU and ASCII bytes, written to one end of a socat pty pair, answered from the other."""
    import serial  # pyserial, which pymodbus's serial transport uses

    ours, device = socat_pair
    rec = by_hand(
        "oriental-az",
        {
            "operation_data[3].starting_rate": Decimal(10000),
            "operation_data[3].stopping_rate": Decimal(20000),
            "operation_data[3].operating_current": Decimal(500),
        },
    )
    (w,) = make_plan(rec, Target(None, 4, "oriental-az")).writes
    with (
        SimulatorThread(rec.profile, listen=f"{framing}://{device}", units=(4,)) as sim,
        serial.Serial(ours, 19200, timeout=5) as port,
    ):
        assert sim.read("operation_data[3].stopping_rate", unit=4) != (0, 20000)
        port.write(request_frame(w, 4, framing))
        want = response_frame(w, 4, framing)
        assert port.read(len(want)) == want
        assert sim.read("operation_data[3].stopping_rate", unit=4) == (0, 20000)
