"""Answers that come late, or wrong: never taken as the answer to another request (issue #17 items 1, 12).

The devices here are our own small RTU/TCP servers on a socat pty pair and on 127.0.0.1 sockets, built
on umodbus's CRC (an implementation we did not write), answering after the client's timeout or with a
wrong unit, byte count or echo; plus the simulator over rtu+tcp with a latency longer than the timeout.
"""

from __future__ import annotations

import asyncio
import json
import os
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import serial
import yaml

from deployer.errors import BadAnswer
from deployer.testing.simulator import Faults, Simulator
from deployer.transport import clients as tp
from tests.helpers import count, profile_from

crc = pytest.importorskip("umodbus.client.serial.redundancy_check", reason="umodbus is a test extra")

TIMEOUT = 0.6
LATE = 0.9  # after the timeout, well before the line has been silent for another whole timeout


def _request_size(buf: bytes) -> int:
    """Length of the RTU request at the start of buf (0: not known yet)."""
    if len(buf) < 2:
        return 0
    if buf[1] in (3, 6):
        return 8
    if buf[1] == 16:
        return 9 + buf[6] if len(buf) >= 7 else 0
    return len(buf)  # anything else: take it all (answered with exception 01)


Answer = Callable[[int, bytes, bytes], bytes | None]  # (index, request, correct answer) -> what to send


class Device:
    """An RTU device on a byte stream: holding registers, a log of every request frame received,
    and a rule for each answer (late, wrong unit, ...)."""

    def __init__(self, regs: dict[int, int], *, delay: Callable[[int], float] = lambda i: 0.0,
                 answer: Answer = lambda i, req, good: good) -> None:
        self.regs = dict(regs)
        self.frames: list[bytes] = []
        self.delay = delay
        self.answer = answer
        self.stop = threading.Event()

    def handle(self, req: bytes) -> bytes:
        unit, fc = req[0], req[1]
        if fc == 3:
            addr, n = struct.unpack(">HH", req[2:6])
            pdu = bytes([fc, 2 * n]) + b"".join(struct.pack(">H", self.regs.get(a, 0)) for a in range(addr, addr + n))
        elif fc == 6:
            addr, value = struct.unpack(">HH", req[2:6])
            self.regs[addr] = value
            pdu = req[1:6]
        elif fc == 16:
            addr, n = struct.unpack(">HH", req[2:6])
            for i in range(n):
                self.regs[addr + i] = struct.unpack(">H", req[7 + 2 * i:9 + 2 * i])[0]
            pdu = req[1:6]
        else:  # a function this device does not have: exception 01, as a real one answers
            pdu = bytes([fc | 0x80, 1])
        return bytes(crc.add_crc(bytes([unit]) + pdu))

    def serve(self, read: Callable[[], bytes], write: Callable[[bytes], None]) -> None:
        buf = b""
        while not self.stop.is_set():
            chunk = read()
            if not chunk:
                continue
            buf += chunk
            while (size := _request_size(buf)) and len(buf) >= size:
                req, buf = buf[:size], buf[size:]
                if crc.get_crc(req[:-2]) != req[-2:]:
                    continue
                i = len(self.frames)
                self.frames.append(req)
                good = self.handle(req)
                out = self.answer(i, req, good)
                time.sleep(self.delay(i))
                if out is not None:
                    write(out)


@contextmanager
def on_pty(dev: Device, path: str) -> Iterator[None]:
    port = serial.Serial(path, timeout=0 if sys.platform == "win32" else 0.05)

    def read() -> bytes:
        if sys.platform == "win32":  # polled, as pymodbus polls a COM port (Wine ends a read that times out
            got = port.read(256)     # with ERROR_TIMEOUT, where Windows returns the bytes that came)
            return got or (time.sleep(0.001) or b"")
        return bytes(port.read(256))
    t = threading.Thread(target=dev.serve, args=(read, port.write), daemon=True)
    t.start()
    try:
        yield
    finally:
        dev.stop.set()
        t.join(5)
        port.close()


@contextmanager
def on_tcp(dev: Device) -> Iterator[int]:
    """A serial gateway on 127.0.0.1: RTU frames over TCP, one connection at a time."""
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)
    srv.settimeout(0.05)

    def run() -> None:
        while not dev.stop.is_set():
            try:
                conn, _ = srv.accept()
            except TimeoutError:
                continue
            conn.settimeout(0.05)

            def read(c: socket.socket = conn) -> bytes:
                try:
                    data = c.recv(256)
                except TimeoutError:
                    return b""
                if not data:
                    raise ConnectionError
                return data
            try:
                dev.serve(read, conn.sendall)
            except OSError:
                pass
            finally:
                conn.close()

    t = threading.Thread(target=run, daemon=True)
    t.start()
    try:
        yield int(srv.getsockname()[1])
    finally:
        dev.stop.set()
        t.join(5)
        srv.close()


def read_frame(address: int, n: int, unit: int = 1) -> bytes:
    return bytes(crc.add_crc(struct.pack(">BBHH", unit, 3, address, n)))


def _url(kind: str, where: str, port: int = 0) -> str:
    if kind == "rtu":
        return f"rtu://{where}?timeout={TIMEOUT:g}&retries=2"
    return f"rtu+tcp://127.0.0.1:{port}?timeout={TIMEOUT:g}&retries=2"


@contextmanager
def device_at(kind: str, dev: Device, socat_pair: tuple[str, str]) -> Iterator[str]:
    if kind == "rtu":
        with on_pty(dev, socat_pair[0]):
            yield _url(kind, socat_pair[1])
    else:
        with on_tcp(dev) as port:
            yield _url(kind, "", port)


async def _two_reads(url: str, session_reads: list[tuple[int, int]]) -> tuple[list[list[int]], list[float]]:
    """The executor's own retry loop (Session) over a real transport: reads in order."""
    from deployer.execute.session import Session

    t = tp.open_transport(url)
    await t.connect()
    try:
        s = Session(t, 1, retries=t.url.retries, backoff=0.05, records=[])
        return [await s.read(a, n) for a, n in session_reads], t.late_answers
    finally:
        await t.close()


@pytest.mark.parametrize("kind", ["rtu", "rtu+tcp"])
def test_a_late_answer_is_never_the_next_requests_answer(kind: str, socat_pair: tuple[str, str]) -> None:
    """The issue's case: two same-size reads, the first answered after the timeout. Before, the
    late answer of the first read's first copy answered its retry, and the retry's answer the second read."""
    regs = {100 + i: 1 for i in range(10)} | {200 + i: 2 for i in range(10)}
    dev = Device(regs, delay=lambda i: LATE if i == 0 else 0.0)
    with device_at(kind, dev, socat_pair) as url:
        values, late = asyncio.run(_two_reads(url, [(100, 10), (200, 10)]))
    assert values == [[1] * 10, [2] * 10]
    assert dev.frames == [read_frame(100, 10), read_frame(200, 10)]  # each request reached the device once
    assert len(late) == 1 and late[0] > TIMEOUT


@pytest.mark.parametrize("kind", ["rtu", "rtu+tcp"])
def test_a_device_always_late_gets_every_request_once_and_right(kind: str, socat_pair: tuple[str, str]) -> None:
    regs = {100 + i: 1 for i in range(10)} | {200 + i: 2 for i in range(10)}
    dev = Device(regs, delay=lambda i: LATE)
    with device_at(kind, dev, socat_pair) as url:
        values, late = asyncio.run(_two_reads(url, [(100, 10), (200, 10), (100, 10)]))
    assert values == [[1] * 10, [2] * 10, [1] * 10]
    assert dev.frames == [read_frame(100, 10), read_frame(200, 10), read_frame(100, 10)]
    assert len(late) == 3


def test_bytes_nobody_asked_for_are_drained_before_the_next_request(socat_pair: tuple[str, str]) -> None:
    """A stray answer (e.g. to another master, or a device answering twice) after a good answer: the next
    request waits until the line is quiet, and takes only its own answer."""
    regs = {100 + i: 1 for i in range(10)} | {200 + i: 2 for i in range(10)}
    # answer 0 comes twice: the second copy (same shape as read 2's answer) arrives while the client settles
    dev = Device(regs, answer=lambda i, req, good: good + good if i == 0 else good)
    with device_at("rtu", dev, socat_pair) as url:
        values, late = asyncio.run(_two_reads(url, [(100, 10), (200, 10)]))
    assert values == [[1] * 10, [2] * 10]
    assert dev.frames == [read_frame(100, 10), read_frame(200, 10)] and late == []


def _bad(answer: Answer, request: Callable[[tp.Transport], Any], kind: str = "rtu",
         socat_pair: tuple[str, str] = ("", "")) -> str:
    dev = Device({100 + i: 7 for i in range(4)}, answer=answer)

    async def main() -> str:
        t = tp.open_transport(url.replace("retries=2", "retries=0"))
        await t.connect()
        try:
            with pytest.raises(BadAnswer) as e:
                await request(t)
            return str(e.value)
        finally:
            await t.close()

    with device_at(kind, dev, socat_pair) as url:
        return asyncio.run(main())


def _unit(n: int) -> Answer:
    return lambda i, req, good: bytes(crc.add_crc(bytes([n]) + good[1:-2]))


@pytest.mark.parametrize("kind", ["rtu", "rtu+tcp"])
def test_wrong_answers_are_named_not_called_silence(kind: str, socat_pair: tuple[str, str]) -> None:
    read = lambda t: t.read_holding_registers(100, 4, 1)  # noqa: E731
    assert _bad(_unit(2), read, kind, socat_pair) == "an answer from unit 2 to a request for unit 1"

    def short(i: int, req: bytes, good: bytes) -> bytes:
        return bytes(crc.add_crc(bytes([1, 3, 6]) + good[3:9]))
    assert _bad(short, read, kind, socat_pair) == \
        "an answer with 6 bytes of registers to a read of 4 registers (8 bytes)"

    def echo(i: int, req: bytes, good: bytes) -> bytes:
        return bytes(crc.add_crc(bytes([1, 16]) + struct.pack(">HH", 101, 2)))
    assert _bad(echo, lambda t: t.write_registers(100, [1, 2], 1), kind, socat_pair) == \
        "an answer echoing address 101, count 2 to a write of address 100, count 2"

    def other_fc(i: int, req: bytes, good: bytes) -> bytes:
        return bytes(crc.add_crc(bytes([1, 4, 8]) + bytes(8)))
    assert _bad(other_fc, read, kind, socat_pair) == "an answer with function code 4 to a function 3 request"

    def garbled(i: int, req: bytes, good: bytes) -> bytes:
        return good[:-1] + bytes([good[-1] ^ 0xFF])
    assert _bad(garbled, read, kind, socat_pair) == "a garbled answer (CRC error)"


def test_a_wrong_answer_is_reported_as_such_after_the_retries(socat_pair: tuple[str, str]) -> None:
    dev = Device({100: 7}, answer=_unit(9))
    with device_at("rtu", dev, socat_pair) as url, pytest.raises(Exception) as e:
        asyncio.run(_two_reads(url, [(100, 1)]))
    assert str(e.value) == "an answer from unit 9 to a request for unit 1 (after 3 attempts)"


PROFILE = """\
profile: late-dev
parameters:
  p1: {register: 100, type: uint16}
  p2: {register: 200, type: uint16}
"""


def test_apply_to_an_always_late_device_snapshots_the_truth(socat_pair: tuple[str, str], tmp_path: Path) -> None:
    """A real `deployer apply` process: the snapshot holds what the device held, every request reached
    it once, the report says the device answered late."""
    profile_from(tmp_path, PROFILE)
    recipe = tmp_path / "r.yaml"
    recipe.write_text(f"recipe: late\nprofile: dev.yaml\ndevice: {{url: 'rtu://{socat_pair[1]}?timeout={TIMEOUT:g}', "
                      "unit: 1}\nparameters:\n  p1: 11\n  p2: 22\n")
    dev = Device({100: 1, 200: 2}, delay=lambda i: LATE)
    with on_pty(dev, socat_pair[0]):
        run = subprocess.run([sys.executable, "-m", "deployer", "apply", str(recipe), "--yes", "--report",
                              str(tmp_path / "report.json"), "--state-dir", str(tmp_path / "state")],
                             capture_output=True, text=True, timeout=300, env=os.environ | {"NO_COLOR": "1"})
    assert run.returncode == 0, run.stdout + run.stderr
    report = json.loads((tmp_path / "report.json").read_text())
    d = report["devices"][0]
    snap = yaml.safe_load(Path(d["snapshot"]).read_text())
    assert snap["parameters"] == {"p1": 1, "p2": 2}
    assert dev.regs[100] == 11 and dev.regs[200] == 22
    # register requests (the device's identification, FC43, is asked once too and answered exception 01)
    sent = [(r["function"], r["address"], r["count"]) for r in d["requests"] if r["function"] in (3, 6, 16)]
    got = [(f[1], struct.unpack(">H", f[2:4])[0], 1 if f[1] == 6 else struct.unpack(">H", f[4:6])[0])
           for f in dev.frames if f[1] in (3, 6, 16)]
    assert len(dev.frames) - len(got) == len(d["requests"]) - len(sent) <= 1
    assert got == sent and len(got) == len(set(got)) + 2  # the two reads twice (snapshot, read-back), writes once
    assert any("after the timeout" in n for n in d["notices"])


def test_simulator_over_rtu_tcp_slower_than_the_timeout(tmp_path: Path) -> None:
    prof = profile_from(tmp_path, PROFILE)
    sim = Simulator(prof, listen="rtu+tcp://127.0.0.1:0", init={100: 1, 200: 2}, faults=Faults(latency_ms=LATE * 1000))

    async def main() -> tuple[list[list[int]], list[float]]:
        async with sim:
            return await _two_reads(f"{sim.url}?timeout={TIMEOUT:g}&retries=2",
                                    [(100, 1), (200, 1)])

    values, late = asyncio.run(main())
    assert values == [[1], [2]] and len(late) == 2
    assert count(sim.log, 3, address=100) == 1 and count(sim.log, 3, address=200) == 1


def test_an_answer_in_the_same_turn_as_its_timeout_is_kept_for_the_retry() -> None:
    """The timer gave up on the request (its future holds TimeoutError) and the answer came in the same
    turn of the event loop, before the request's task resumed: the answer is not lost, the retry of that
    very request takes it instead of sending again."""
    from pymodbus.framer import FramerRTU

    async def run() -> None:
        rx = tp._Receiver("rtu", lambda _out, chunk: chunk)
        want = tp._Expect(unit=1, function=3, address=100, count=1)
        rx.start(want)
        assert rx.future is not None
        tp._too_late(rx.future)  # the timeout fires first...
        pdu = bytes([1, 3, 2, 0x12, 0x34])
        rx.feed(pdu + FramerRTU.compute_CRC(pdu).to_bytes(2, "big"))  # ...then the answer, same turn
        with pytest.raises(TimeoutError):
            await tp._answer(rx.future, 1.0)
        rx.unanswered()
        late = rx.take_late(want)
        assert late is not None and late[0] == bytes([3, 2, 0x12, 0x34])

    asyncio.run(run())
