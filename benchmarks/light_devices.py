"""A light Modbus/TCP device farm for the fleet benchmarks: many devices, little CPU per request.

    python -m benchmarks.light_devices N LATENCY_MS [--processes K] [--registers R]

Starts K worker processes (default 2) that serve N devices between them, each device on its own
127.0.0.1 port with R holding registers (default 1024, all 0), answering every request after
LATENCY_MS (0: at once). Prints one JSON line with the devices' URLs once every device listens,
then serves until stdin closes, and prints {"requests": ..., "cpu": ...}: what answering cost it.

Why not the project's simulator (``deployer.testing.simulator``): it is pymodbus's server with
the simulator's checks, about 0.27 ms of CPU per request, so on a 2-core machine a farm of them
caps any measurement of deployer near its goals. This one parses the MBAP header with ``struct``
and answers from a ``bytearray``: a few tens of microseconds per request. It is a real Modbus/TCP
device for what a fleet apply sends (tests/test_light_devices.py checks it against pymodbus's client
and mbpoll): Functions 03 and 04 (read), 06 and 16 (write), exception 02 for an address beyond its
registers, 03 for a bad count, 01 for any other function (43 included: no device identification).
Function 16 is all or nothing, as the spec asks of a request the device refuses.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import struct
import subprocess
import sys
import time
from typing import Any, cast

_MBAP = struct.Struct(">HHHB")  # transaction id, protocol id (0), length (unit + PDU), unit
_READ = struct.Struct(">BHH")  # function, address, count
_ONE = struct.Struct(">BHH")  # function 06: address, value


SERVED = [0]  # requests answered by this process (reported when it ends)


class Device:
    """One device: its holding registers (big-endian words in a bytearray) and its reply delay."""

    __slots__ = ("delay", "regs", "size")

    def __init__(self, registers: int, delay: float) -> None:
        self.size = registers
        self.regs = bytearray(2 * registers)
        self.delay = delay

    def answer(self, pdu: bytes) -> bytes:
        """The response PDU for a request PDU (an exception response for what it does not do)."""
        SERVED[0] += 1
        fc = pdu[0]
        if fc in (3, 4):
            if len(pdu) != 5:
                return bytes((fc | 0x80, 3))
            _, address, count = _READ.unpack(pdu)
            if not 1 <= count <= 125:
                return bytes((fc | 0x80, 3))
            if address + count > self.size:
                return bytes((fc | 0x80, 2))
            return bytes((fc, 2 * count)) + self.regs[2 * address : 2 * (address + count)]
        if fc == 6:
            if len(pdu) != 5:
                return bytes((0x86, 3))
            _, address, _value = _ONE.unpack(pdu)
            if address >= self.size:
                return bytes((0x86, 2))
            self.regs[2 * address : 2 * address + 2] = pdu[3:5]
            return bytes(pdu)  # the echo
        if fc == 16:
            if len(pdu) < 6:
                return bytes((0x90, 3))
            _, address, count = _READ.unpack_from(pdu)
            if not 1 <= count <= 123 or pdu[5] != 2 * count or len(pdu) != 6 + 2 * count:
                return bytes((0x90, 3))
            if address + count > self.size:
                return bytes((0x90, 2))
            self.regs[2 * address : 2 * (address + count)] = pdu[6:]
            return bytes(pdu[:5])
        return bytes((fc | 0x80, 1))  # illegal function (43: no identification objects, as the simulator)


class _Connection(asyncio.Protocol):
    __slots__ = ("buf", "device", "loop", "transport")

    def __init__(self, device: Device) -> None:
        self.device = device
        self.buf = b""
        self.transport: asyncio.Transport | None = None
        self.loop = asyncio.get_running_loop()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)  # uvloop's transports do not subclass asyncio's

    def connection_lost(self, exc: Exception | None) -> None:
        self.transport = None

    def data_received(self, data: bytes) -> None:
        buf = self.buf + data if self.buf else data
        while len(buf) >= 8:
            tid, pid, length, unit = _MBAP.unpack_from(buf)
            if pid != 0 or not 2 <= length <= 254:  # not Modbus/TCP: drop the connection, as devices do
                assert self.transport is not None
                self.transport.close()
                self.buf = b""
                return
            end = 6 + length
            if len(buf) < end:
                break
            pdu = self.device.answer(buf[7:end])
            reply = _MBAP.pack(tid, 0, len(pdu) + 1, unit) + pdu
            if self.device.delay:
                self.loop.call_later(self.device.delay, self._send, reply)
            else:
                self._send(reply)
            buf = buf[end:]
        self.buf = buf

    def _send(self, reply: bytes) -> None:
        if self.transport is not None:
            self.transport.write(reply)


async def serve(count: int, latency_ms: float, registers: int, ready: Any) -> None:
    """Serve ``count`` devices on ports of 127.0.0.1; ``ready(urls)`` once all listen; until stdin closes."""
    loop = asyncio.get_running_loop()
    servers = []
    urls = []
    for _ in range(count):
        dev = Device(registers, latency_ms / 1000)
        server = await loop.create_server(lambda d=dev: _Connection(d), "127.0.0.1", 0, backlog=64)  # type: ignore[misc]
        servers.append(server)
        urls.append(f"tcp://127.0.0.1:{server.sockets[0].getsockname()[1]}")
    ready(urls)
    started = time.process_time()  # what serving costs, not starting up and listening
    await loop.run_in_executor(None, sys.stdin.read)
    for s in servers:
        s.close()
    print(json.dumps({"requests": SERVED[0], "cpu": time.process_time() - started}), flush=True)


def _loop_factory() -> Any:
    """uvloop's event loop where it is installed (deployer's dependency, not on Windows): the devices' answers
    cost the shared machine less CPU, so the farm takes less of what deployer is measured on."""
    try:
        import uvloop
    except ImportError:
        return None
    return uvloop.new_event_loop


def _raise_nofile(need: int) -> None:
    if sys.platform == "win32":
        return  # no such limit: sockets are handles there
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and soft < need:
        resource.setrlimit(resource.RLIMIT_NOFILE, (min(need, hard) if hard != resource.RLIM_INFINITY else need, hard))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("devices", type=int)
    ap.add_argument("latency_ms", type=float)
    ap.add_argument("--processes", type=int, default=2)
    ap.add_argument("--registers", type=int, default=1024)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:  # one process's share: its URLs on stdout, then serve
        _raise_nofile(args.devices + 256)
        with asyncio.Runner(loop_factory=_loop_factory()) as runner:
            runner.run(
                serve(args.devices, args.latency_ms, args.registers, lambda urls: print(json.dumps(urls), flush=True))
            )
        return
    k = max(1, min(args.processes, args.devices))
    shares = [args.devices // k + (1 if i < args.devices % k else 0) for i in range(k)]
    workers = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "benchmarks.light_devices",
                str(n),
                str(args.latency_ms),
                "--registers",
                str(args.registers),
                "--worker",
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
        )
        for n in shares
    ]
    urls: list[str] = []
    # devices interleaved over the workers: a fleet's neighbours in inventory order land on different cores
    lists = []
    for w in workers:
        assert w.stdout is not None
        lists.append(json.loads(w.stdout.readline()))
    for i in range(max(shares)):
        urls.extend(lst[i] for lst in lists if i < len(lst))
    print(json.dumps(urls), flush=True)
    sys.stdin.read()
    for w in workers:
        assert w.stdin is not None
        w.stdin.close()
    served = {"requests": 0, "cpu": 0.0}
    for w in workers:
        assert w.stdout is not None
        last = json.loads(w.stdout.readline() or "{}")
        served["requests"] += last.get("requests", 0)
        served["cpu"] += last.get("cpu", 0.0)
        w.wait()
    print(json.dumps(served), flush=True)  # the farm's own cost: CPU seconds for the requests it answered


if __name__ == "__main__":
    main()
