"""RTU devices on a byte stream for the late-answer tests: on a socat pty, or behind an rtu+tcp gateway.

``Device`` answers from its own registers (frames made with umodbus's CRC) by a rule per answer (late,
wrong unit, ...); ``SlowServer`` is umodbus's own RTU server (an implementation we did not write) on a
pty of its own, behind our relay, which holds each answer back as a slow device does. Both take one
request at a time: requests that come while one is being answered wait, as in a real device's buffer.
"""

from __future__ import annotations

import os
import select
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import pytest
import serial

crc = pytest.importorskip("umodbus.client.serial.redundancy_check", reason="umodbus is a test extra")


def request_size(buf: bytes) -> int:
    """Length of the RTU request at the start of buf (0: not known yet)."""
    if len(buf) < 2:
        return 0
    if buf[1] in (1, 2, 3, 4, 5, 6):
        return 8
    if buf[1] in (15, 16):
        return 9 + buf[6] if len(buf) >= 7 else 0
    if buf[1] == 43:  # read device identification: unit, 43, 14, read code, object id, CRC
        return 7
    return len(buf)  # anything else: take it all (answered with exception 01)


def answer_size(buf: bytes) -> int:
    """Length of the RTU answer at the start of buf (0: not known yet)."""
    if len(buf) < 3:
        return 0
    fc = buf[1]
    return 5 if fc & 0x80 else 5 + buf[2] if fc in (1, 2, 3, 4) else 8


def read_frame(address: int, n: int, unit: int = 1) -> bytes:
    return bytes(crc.add_crc(struct.pack(">BBHH", unit, 3, address, n)))


Answer = Callable[[int, bytes, bytes], bytes | None]  # (index, request, correct answer) -> what to send


class Device:
    """An RTU device on a byte stream: holding registers, a log of every request frame received,
    and a rule for each answer (late, wrong unit, ...)."""

    def __init__(
        self,
        regs: dict[int, int],
        *,
        delay: Callable[[int], float] = lambda i: 0.0,
        answer: Answer = lambda i, req, good: good,
    ) -> None:
        self.regs = dict(regs)
        self.frames: list[bytes] = []
        self.delay = delay
        self.answer = answer
        self.stop = threading.Event()

    def handle(self, req: bytes) -> bytes | None:
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
                self.regs[addr + i] = struct.unpack(">H", req[7 + 2 * i : 9 + 2 * i])[0]
            pdu = req[1:6]
        else:  # a function this device does not have: exception 01, as a real one answers
            pdu = bytes([fc | 0x80, 1])
        return bytes(crc.add_crc(bytes([unit]) + pdu))

    def late(self, i: int, req: bytes) -> float:
        """Seconds the answer to request number ``i`` is held back."""
        return self.delay(i)

    def serve(self, read: Callable[[], bytes], write: Callable[[bytes], None]) -> None:
        buf = b""
        while not self.stop.is_set():
            chunk = read()
            if not chunk:
                continue
            buf += chunk
            while (size := request_size(buf)) and len(buf) >= size:
                req, buf = buf[:size], buf[size:]
                if crc.get_crc(req[:-2]) != req[-2:]:
                    continue
                i = len(self.frames)
                self.frames.append(req)
                good = self.handle(req)
                out = self.answer(i, req, good) if good is not None else None
                time.sleep(self.late(i, req))
                if out is not None:
                    write(out)


class SlowServer(Device):
    """umodbus's RTU server (holding registers ``regs``, functions 3, 6, 16, unit 1) on a pty of its own;
    each request goes to it, and its answer is held back ``delay`` seconds: every answer (``always``), or
    only the next read's after ``arm()`` (a device late once)."""

    def __init__(self, regs: dict[int, int], delay: float, *, always: bool) -> None:
        super().__init__(regs)
        self.seconds, self.always, self.armed = delay, always, 0
        self._lock = threading.Lock()
        self._server: object = None

    def arm(self) -> None:
        with self._lock:
            self.armed = 1

    def late(self, i: int, req: bytes) -> float:
        if self.always:
            return self.seconds
        with self._lock:
            if self.armed and req[1] in (1, 2, 3, 4):
                self.armed -= 1
                return self.seconds
        return 0.0

    def handle(self, req: bytes) -> bytes | None:
        os.write(self._master, req)
        got, deadline = b"", time.monotonic() + 2
        while not ((size := answer_size(got)) and len(got) >= size) and time.monotonic() < deadline:
            if select.select([self._master], [], [], 0.05)[0]:
                got += os.read(self._master, 256)
        return got or None

    @contextmanager
    def running(self) -> Iterator[SlowServer]:
        import tty  # POSIX (termios): the suite's serial tests need pseudo-terminals

        from umodbus import conf
        from umodbus.server.serial import get_server
        from umodbus.server.serial.rtu import RTUServer

        self._master, slave = os.openpty()
        tty.setraw(slave)
        port = serial.Serial(os.ttyname(slave), baudrate=115200)
        conf.SIGNED_VALUES = False
        server = get_server(RTUServer, port)
        regs = self.regs

        @server.route(slave_ids=[1], function_codes=[3], addresses=list(regs))  # type: ignore[untyped-decorator]
        def read(slave_id: int, function_code: int, address: int) -> int:
            return regs[address]

        @server.route(slave_ids=[1], function_codes=[6, 16], addresses=list(regs))  # type: ignore[untyped-decorator]
        def write(slave_id: int, function_code: int, address: int, value: int) -> None:
            regs[address] = value

        thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
        thread.start()
        try:
            yield self
        finally:
            server.shutdown()
            thread.join(5)
            port.close()
            os.close(slave)
            os.close(self._master)


@contextmanager
def on_pty(dev: Device, path: str) -> Iterator[None]:
    port = serial.Serial(path, timeout=0 if sys.platform == "win32" else 0.05)

    def read() -> bytes:
        if sys.platform == "win32":  # polled, as pymodbus polls a COM port (Wine ends a read that times out
            got = port.read(256)  # with ERROR_TIMEOUT, where Windows returns the bytes that came)
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
def on_tcp(dev: Device, *, backlog: int = 4, accepting: threading.Event | None = None) -> Iterator[int]:
    """A serial gateway on 127.0.0.1: RTU frames over TCP, one connection at a time; ``backlog``: how many
    connections the system queues for it; ``accepting``: it takes none until this is set."""
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", 0))
    srv.listen(backlog)
    srv.settimeout(0.05)

    def run() -> None:
        while accepting is not None and not accepting.wait(0.05):
            if dev.stop.is_set():
                return
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
