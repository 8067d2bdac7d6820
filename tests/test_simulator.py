"""The simulator behaves like a real device: over TCP and over a socat pty pair, with a real client."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
from pymodbus import FramerType
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException
from pymodbus.pdu import ModbusPDU

from deployer.profile import Profile, builtin_profile
from deployer.testing.simulator import Faults, Simulator, SimulatorThread
from tests.conftest import simulate_process
from tests.helpers import profile_from

pytestmark = pytest.mark.timeout(90)

DEV = """\
profile: dev
limits: {max_write_registers: 10, max_read_registers: 4}
parameters:
  a: {register: 100, type: uint16, max: 100, default: 1}
  b: {register: 101, type: uint32, max: 1000, default: 2}
  c: {register: 103, type: int16, min: -5, max: 5}
  ro: {register: 104, type: uint16, access: read-only, default: 7}
  wo: {register: 105, type: uint16, access: write-only}
  far: {register: 200, type: uint16}
"""


def tcp_client(sim: Simulator, timeout: float = 1) -> AsyncModbusTcpClient:
    host, port = sim.url.removeprefix("tcp://").rsplit(":", 1)
    return AsyncModbusTcpClient(host, port=int(port), retries=0, timeout=timeout)


def run(profile: Profile, body: Any, **kw: Any) -> Any:
    async def main() -> Any:
        async with Simulator(profile, **kw) as sim:
            client = tcp_client(sim, kw.pop("client_timeout", 1) if False else 1)
            assert await client.connect()
            try:
                return await body(sim, client)
            finally:
                client.close()

    return asyncio.run(main())


def exc(r: ModbusPDU) -> int | None:
    return int(r.exception_code) if r.isError() else None


@pytest.fixture
def dev(tmp_path: Path) -> Profile:
    return profile_from(tmp_path, DEV)


def test_defaults_and_reads(dev: Profile) -> None:
    async def body(sim: Simulator, c: AsyncModbusTcpClient) -> None:
        r = await c.read_holding_registers(100, count=4, device_id=1)
        assert r.registers == [1, 0, 2, 0]
        assert (await c.read_holding_registers(104, count=1, device_id=1)).registers == [7]
        assert exc(await c.read_holding_registers(99, count=2, device_id=1)) == 2  # undeclared 99
        assert exc(await c.read_holding_registers(104, count=2, device_id=1)) == 2  # write-only 105
        assert exc(await c.read_holding_registers(106, count=1, device_id=1)) == 2  # gap
        assert exc(await c.read_holding_registers(100, count=5, device_id=1)) == 3  # above max_read 4

    run(dev, body)


def test_partial_write_stops_at_the_bad_value(dev: Profile) -> None:
    async def body(sim: Simulator, c: AsyncModbusTcpClient) -> None:
        # a=5 ok, b=5000 > max 1000 -> exception 03; a stays written, c not
        r = await c.write_registers(100, [5, 0, 5000, 3], device_id=1)
        assert exc(r) == 3
        assert sim.read("a") == (5,) and sim.read("b") == (0, 2) and sim.read("c") == (0,)
        assert sim.log[-1].result == "exception 03"

    run(dev, body)


def test_read_only_split_and_limits(dev: Profile) -> None:
    async def body(sim: Simulator, c: AsyncModbusTcpClient) -> None:
        assert exc(await c.write_registers(104, [1], device_id=1)) == 2  # read-only
        assert exc(await c.write_registers(102, [1], device_id=1)) == 3  # lower word of b only
        assert exc(await c.write_registers(100, [1, 0], device_id=1)) == 3  # upper word of b only
        assert exc(await c.write_registers(100, [1] * 11, device_id=1)) in (2, 3)  # > 10 and past the block
        before = sim.registers()
        assert exc(await c.write_register(200, 9, device_id=1)) is None  # FC06
        assert sim.read("far") == (9,)
        assert {k: v for k, v in sim.registers().items() if k != 200} == {k: v for k, v in before.items() if k != 200}
        assert exc(await c.write_registers(105, [3], device_id=1)) is None  # write-only accepts writes

    run(dev, body)


def test_write_limit_answers_03_and_writes_nothing(tmp_path: Path) -> None:
    prof = profile_from(
        tmp_path,
        "profile: p\nlimits: {max_write_registers: 4}\nparameters:\n"
        + "".join(f"  r{i}: {{register: {i}, type: uint16}}\n" for i in range(10)),
    )

    async def body(sim: Simulator, c: AsyncModbusTcpClient) -> None:
        assert exc(await c.write_registers(0, [9] * 5, device_id=1)) == 3
        assert all(v == 0 for v in sim.registers().values())
        assert exc(await c.write_registers(0, [9] * 4, device_id=1)) is None

    run(prof, body)


def test_unknown_function_and_unknown_unit(dev: Profile) -> None:
    async def body(sim: Simulator, c: AsyncModbusTcpClient) -> None:
        assert exc(await c.read_coils(100, count=1, device_id=1)) == 1  # a drive has no coils
        assert exc(await c.read_holding_registers(100, count=1, device_id=9)) == 0x0B  # gateway: target silent
        # a function code nobody implements (0x41), as raw bytes: MBAP, unit 1, FC 41h
        host, port = sim.url.removeprefix("tcp://").rsplit(":", 1)
        reader, writer = await asyncio.open_connection(host, int(port))
        writer.write(bytes.fromhex("0001 0000 0002 01 41"))
        answer = await asyncio.wait_for(reader.read(64), 2)
        writer.close()
        # exception 01 (illegal function); pymodbus 3.16 puts 80h, not C1h, in the function byte
        assert answer[:7] == bytes.fromhex("0001 0000 0003 01") and answer[7] & 0x80 and answer[8] == 1

    run(dev, body)


def _mbap_frames(data: bytes) -> list[bytes]:
    """Split Modbus/TCP answers: each is its MBAP header (7 bytes, length counts unit + PDU) and PDU."""
    frames, i = [], 0
    while i + 6 <= len(data):
        n = int.from_bytes(data[i + 4 : i + 6], "big")
        frames.append(data[i : i + 6 + n])
        i += 6 + n
    return frames


async def _exchange(sim: Simulator, requests: bytes, answers: int) -> list[bytes]:
    """Send the requests in one write (one TCP segment here) and collect that many answers."""
    host, port = sim.url.removeprefix("tcp://").rsplit(":", 1)
    reader, writer = await asyncio.open_connection(host, int(port))
    writer.write(requests)
    got = b""
    try:
        while len(_mbap_frames(got)) < answers:
            got += await asyncio.wait_for(reader.read(65536), 5)
    finally:
        writer.close()
    return _mbap_frames(got)


def test_pipelined_requests_are_each_answered_in_order(dev: Profile) -> None:
    async def body(sim: Simulator, c: AsyncModbusTcpClient) -> None:
        # 100 reads in one segment (a gateway or a pipelining client sends them so); pymodbus's own
        # handler answered only the first of a segment, and none once the segment passed 260 bytes
        reads = b"".join(
            tid.to_bytes(2, "big") + bytes.fromhex("0000 0006 01 03 0064") + (1 + tid % 4).to_bytes(2, "big")
            for tid in range(1, 101)
        )
        frames = await _exchange(sim, reads, 100)
        assert [int.from_bytes(f[:2], "big") for f in frames] == list(range(1, 101))
        regs = [1, 0, 2, 0]
        for tid, f in zip(range(1, 101), frames, strict=True):
            n = 1 + tid % 4
            assert f[7:9] == bytes([3, 2 * n]) and f[9:] == b"".join(r.to_bytes(2, "big") for r in regs[:n])
        # writes and reads interleaved in one segment take effect in order
        mixed = (
            bytes.fromhex("0201 0000 0006 01 06 0064 0005")
            + bytes.fromhex("0202 0000 0006 01 03 0064 0001")
            + bytes.fromhex("0203 0000 0006 01 06 0064 0009")
            + bytes.fromhex("0204 0000 0006 01 03 0064 0001")
        )
        frames = await _exchange(sim, mixed, 4)
        assert [f[:2].hex() for f in frames] == ["0201", "0202", "0203", "0204"]
        assert frames[1][9:] == bytes.fromhex("0005") and frames[3][9:] == bytes.fromhex("0009")
        assert sim.read("a") == (9,)

    run(dev, body)


@pytest.mark.parametrize(
    "request_pdu",
    ["08 0000 0000", "0B", "11", "14 07 06 0004 0001 0002", "18 0064", "2B 0E 01 00"],
    ids=[
        "08-diagnostics",
        "0B-comm-event-counter",
        "11-report-server-id",
        "14-read-file-record",
        "18-read-fifo",
        "2B-device-identification",
    ],
)
def test_functions_a_drive_does_not_have_answer_01(dev: Profile, request_pdu: str) -> None:
    async def body(sim: Simulator, c: AsyncModbusTcpClient) -> None:
        pdu = bytes.fromhex(request_pdu)
        frame = bytes.fromhex("0007 0000") + (len(pdu) + 1).to_bytes(2, "big") + b"\x01" + pdu
        (answer,) = await _exchange(sim, frame, 1)
        assert answer[:2] == bytes.fromhex("0007") and answer[7] & 0x80 and answer[8] == 1, answer.hex()
        assert sim.log[-1].result == "exception 01"

    run(dev, body)


def test_broadcast_applies_to_every_unit_without_answer(dev: Profile) -> None:
    async def body(sim: Simulator, c: AsyncModbusTcpClient) -> None:
        await c.write_registers(100, [42], device_id=0, no_response_expected=True)
        await asyncio.sleep(0.2)
        assert sim.read("a", 1) == (42,) and sim.read("a", 2) == (42,)
        assert sim.log[-1].result == "broadcast"

    run(dev, body, units=(1, 2))


def test_busy_drop_fail_register(dev: Profile) -> None:
    faults = Faults(busy_first=1, drop_every=4, fail_registers=frozenset({103}))

    async def body(sim: Simulator, c: AsyncModbusTcpClient) -> None:
        assert exc(await c.write_registers(100, [3], device_id=1)) == 6  # 1: busy, nothing written
        assert sim.read("a") == (1,)
        assert exc(await c.write_registers(100, [3], device_id=1)) is None  # 2
        assert exc(await c.write_registers(100, [4, 0, 9, 1], device_id=1)) == 4  # 3: a, b written; c fails
        assert sim.read("a") == (4,) and sim.read("b") == (0, 9) and sim.read("c") == (0,)
        with pytest.raises(ModbusException):  # 4: dropped -> the client times out
            r = await c.read_holding_registers(100, count=1, device_id=1)
            raise AssertionError(f"answered: {r}")
        assert [e.result for e in sim.log] == ["exception 06", "ok", "exception 04", "dropped"]

    run(dev, body, faults=faults)


def test_latency_and_baud_delay(dev: Profile) -> None:
    async def body(sim: Simulator, c: AsyncModbusTcpClient) -> float:
        t = time.monotonic()
        await c.read_holding_registers(100, count=1, device_id=1)
        return time.monotonic() - t

    assert run(dev, body, faults=Faults(latency_ms=200)) >= 0.2
    # 8 + 7 characters + 7 for the silent intervals at 300 baud, 11 bits each: 0.8 s
    assert run(dev, body, faults=Faults(baud=300)) >= 0.8


def test_disconnect_after(dev: Profile) -> None:
    async def body(sim: Simulator, c: AsyncModbusTcpClient) -> None:
        for _ in range(2):
            assert not (await c.read_holding_registers(100, count=1, device_id=1)).isError()
        with pytest.raises(ModbusException):
            await c.read_holding_registers(100, count=1, device_id=1)
        assert sim.log[-1].result == "disconnected"

    run(dev, body, faults=Faults(disconnect_after=2))


def test_log_file_and_state_file(dev: Profile, tmp_path: Path) -> None:
    log, state = tmp_path / "log.jsonl", tmp_path / "state.json"

    async def body(sim: Simulator, c: AsyncModbusTcpClient) -> None:
        await c.write_registers(100, [8], device_id=1)
        await c.read_holding_registers(99, count=1, device_id=1)

    run(dev, body, log_path=str(log), state_path=str(state))
    lines = [json.loads(x) for x in log.read_text().splitlines()]
    assert [(x["function"], x["address"], x["result"]) for x in lines] == [(16, 100, "ok"), (3, 99, "exception 02")]
    assert lines[0]["request_hex"] == "0110006400010200" + "08"
    assert json.loads(state.read_text())["units"]["1"]["100"] == 8


def test_fifty_concurrent_clients_ten_thousand_requests() -> None:
    prof = builtin_profile("example-inverter")
    f07 = prof.parameter("F07").address

    async def main() -> int:
        async with Simulator(prof) as sim:
            host, port = sim.url.removeprefix("tcp://").rsplit(":", 1)

            async def worker(k: int) -> int:
                c = AsyncModbusTcpClient(host, port=int(port), retries=0, timeout=10)
                assert await c.connect()
                errors = 0
                for i in range(200):
                    if i % 2:
                        r = await c.write_registers(f07, [0, (k * 200 + i) % 60000], device_id=1)
                    else:
                        r = await c.read_holding_registers(f07, count=2, device_id=1)
                    errors += r.isError()
                c.close()
                return errors

            errors = sum(await asyncio.gather(*(worker(k) for k in range(50))))
            assert len(sim.log) == 10_000
            return errors

    assert asyncio.run(main()) == 0


# ---- serial: RTU over a pseudo-terminal pair ---------------------------------------------------


def test_rtu_over_pty(dev: Profile, socat_pair: tuple[str, str]) -> None:
    a, b = socat_pair

    async def main() -> None:
        async with Simulator(dev, listen=f"rtu://{a}") as sim:
            c = AsyncModbusSerialClient(b, framer=FramerType.RTU, baudrate=19200, retries=0, timeout=1)
            assert await c.connect()
            try:
                r = await c.read_holding_registers(100, count=3, device_id=1)
                assert r.registers == [1, 0, 2]
                assert exc(await c.read_holding_registers(100, count=5, device_id=1)) == 3
                assert exc(await c.write_registers(100, [5, 0, 5000, 3], device_id=1)) == 3  # partial write
                assert sim.read("a") == (5,) and sim.read("b") == (0, 2) and sim.read("c") == (0,)
                assert exc(await c.read_holding_registers(99, count=1, device_id=1)) == 2
                with pytest.raises(ModbusException):  # another unit on the bus: silence, the client times out
                    r = await c.read_holding_registers(100, count=1, device_id=7)
                    raise AssertionError(r)
            finally:
                c.close()

    asyncio.run(main())


# ---- the command and interop ----------------------------------------------------------------------


def test_cli_simulate_serves_and_dumps_state(tmp_path: Path) -> None:
    state = tmp_path / "state.json"
    proc, url, port = simulate_process("omron-m1", "--state", str(state))
    try:
        assert port != 0 and url == f"tcp://127.0.0.1:{port}"  # the port the system gave, reported

        async def query() -> None:
            c = AsyncModbusTcpClient("127.0.0.1", port=port, retries=0, timeout=2)
            assert await c.connect()
            await c.write_registers(0x1102, [0, 1000], device_id=1)
            c.close()

        asyncio.run(query())
        proc.send_signal(signal.SIGUSR1)  # dump while serving
        deadline = time.monotonic() + 10
        while not state.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert json.loads(state.read_text())["units"]["1"]["4355"] == 1000
        state.unlink()
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
    assert json.loads(state.read_text())["units"]["1"]["4355"] == 1000  # and again on exit


MBPOLL = shutil.which("mbpoll")
needs_mbpoll = pytest.mark.skipif(MBPOLL is None, reason="mbpoll (libmodbus) is not installed; CI installs it")


def mbpoll(*args: str) -> subprocess.CompletedProcess[str]:
    assert MBPOLL is not None
    return subprocess.run([MBPOLL, *args], capture_output=True, text=True, timeout=20)


@needs_mbpoll
def test_mbpoll_reads_and_writes_over_tcp(dev: Profile) -> None:
    with SimulatorThread(dev) as sim:
        port = sim.url.rsplit(":", 1)[1]
        # -0: addresses are 0-based (protocol addresses); -1: one poll; -t 4: holding registers
        out = mbpoll("-m", "tcp", "-p", port, "-a", "1", "-0", "-r", "100", "-c", "3", "-t", "4", "-1", "127.0.0.1")
        assert out.returncode == 0, out.stderr
        assert "[100]: \t1" in out.stdout and "[102]: \t2" in out.stdout
        out = mbpoll("-m", "tcp", "-p", port, "-a", "1", "-0", "-r", "100", "-t", "4", "-1", "127.0.0.1", "77")
        assert out.returncode == 0, out.stderr
        assert sim.read("a") == (77,)
        out = mbpoll("-m", "tcp", "-p", port, "-a", "1", "-0", "-r", "99", "-t", "4", "-1", "127.0.0.1")
        assert "Illegal data address" in out.stdout + out.stderr
        out = mbpoll("-m", "tcp", "-p", port, "-a", "1", "-0", "-r", "100", "-t", "4", "-1", "127.0.0.1", "500")
        assert "Illegal data value" in out.stdout + out.stderr  # above max 100
        assert sim.read("a") == (77,)


@needs_mbpoll
def test_mbpoll_over_rtu(dev: Profile, socat_pair: tuple[str, str]) -> None:
    a, b = socat_pair
    with SimulatorThread(dev, listen=f"rtu://{a}"):
        out = mbpoll(
            "-m", "rtu", "-b", "19200", "-P", "none", "-a", "1", "-0", "-r", "100", "-c", "3", "-t", "4", "-1", b
        )
        assert out.returncode == 0, out.stdout + out.stderr
        assert "[100]: \t1" in out.stdout and "[102]: \t2" in out.stdout


def test_init_from_recipe(dev: Profile, tmp_path: Path) -> None:
    from deployer.recipe.loader import load_recipe
    from deployer.testing.simulator import init_from_recipe

    (tmp_path / "r.yaml").write_text("recipe: r\nprofile: dev.yaml\nparameters: {a: 9, b: 300}\n")
    init = init_from_recipe(load_recipe(str(tmp_path / "r.yaml")))

    async def body(sim: Simulator, c: AsyncModbusTcpClient) -> None:
        assert (await c.read_holding_registers(100, count=3, device_id=1)).registers == [9, 0, 300]

    run(dev, body, init=init)
    assert os.path.exists(tmp_path / "dev.yaml")
