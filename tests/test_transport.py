"""Transports against real peers: pymodbus servers started here (tcp, tls, rtu+tcp, rtu and ascii over a
socat pseudo-terminal pair) and a umodbus server. Self-contained: no deployer.simulator, no executor."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import ssl
import sys
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.framer import FramerAscii, FramerRTU
from pymodbus.pdu import DecodePDU, ModbusPDU
from pymodbus.pdu.register_message import WriteMultipleRegistersRequest
from pymodbus.server import ModbusSerialServer, ModbusTcpServer, ModbusTlsServer
from pymodbus.simulator import DataType, SimData, SimDevice

from deployer.errors import BadURL, ConnectionLost, ExceptionResponse, NoResponse, Unreachable
from deployer.transport import clients as tp
from tests.conftest import dead_port
from tests.helpers import umodbus_server as start_umodbus

pytestmark = pytest.mark.timeout(30)

REGS = 100  # every server holds registers 0..99 (others: exception 02)


# ---- real peers -----------------------------------------------------------------------------------


def _devices(units: tuple[int, ...]) -> list[SimDevice]:
    async def action(
        fc: int, start: int, address: int, count: int, registers: list[int], values: list[int] | list[bool] | None
    ) -> ExcCodes | None:
        # a device-like range check: values above 1000 are refused with exception 03
        if values is not None and any(int(v) > 1000 for v in values):
            return ExcCodes.ILLEGAL_VALUE
        return None

    return [
        SimDevice(id=u, simdata=[SimData(address=0, values=[0] * REGS, datatype=DataType.REGISTERS)], action=action)
        for u in units
    ]


@contextlib.asynccontextmanager
async def serve(
    kind: str,
    *,
    units: tuple[int, ...] = (1,),
    path: str = "",
    sslctx: ssl.SSLContext | None = None,
    trace_pdu: Callable[[bool, ModbusPDU], ModbusPDU | None] | None = None,
    trace_packet: Callable[[bool, bytes], bytes] | None = None,
) -> AsyncIterator[int]:
    """A pymodbus server; yields its TCP port (0 for serial)."""

    def silent_for_others(sending: bool, pdu: ModbusPDU) -> ModbusPDU | None:
        # pymodbus 3.16 answers 04 for a unit without a SimDevice even with ignore_missing_devices:
        # a real RS-485 device (and a gateway's line) stays silent instead
        if not sending and pdu.dev_id not in (0, *units):
            return None
        return trace_pdu(sending, pdu) if trace_pdu is not None else pdu

    common: dict[str, Any] = {"trace_pdu": silent_for_others, "trace_packet": trace_packet, "broadcast_enable": True}
    server: Any
    if kind == "tcp":
        server = ModbusTcpServer(_devices(units), framer=FramerType.SOCKET, address=("127.0.0.1", 0), **common)
    elif kind == "rtu+tcp":
        server = ModbusTcpServer(_devices(units), framer=FramerType.RTU, address=("127.0.0.1", 0), **common)
    elif kind == "tls":
        server = ModbusTlsServer(_devices(units), sslctx=sslctx, address=("127.0.0.1", 0), **common)
    else:  # a real RS-485 device stays silent for other unit ids
        server = ModbusSerialServer(
            _devices(units), framer=FramerType.RTU if kind == "rtu" else FramerType.ASCII, port=path, **common
        )
    await server.serve_forever(background=True)
    try:
        sockets = getattr(server.transport, "sockets", None)
        yield int(sockets[0].getsockname()[1]) if sockets else 0
    finally:
        await server.shutdown()


@pytest.fixture
def pty_pair(socat_pair: tuple[str, str]) -> tuple[str, str]:
    """Two linked pseudo-terminals (conftest's socat pair): (server end, client end)."""
    return socat_pair


def sent(t: tp.Transport) -> list[bytes]:
    """Collect the bytes a transport puts on the wire."""
    out: list[bytes] = []
    t.on_frame = lambda direction, data: out.append(data) if direction == "send" else None
    return out


# ---- URLs ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "expect"),
    [
        ("tcp://10.0.0.11", ("tcp", "10.0.0.11", 502, None, {})),
        (
            "tcp://10.0.0.11:5020?timeout=0.5&retries=4",
            ("tcp", "10.0.0.11", 5020, None, {"timeout": "0.5", "retries": "4"}),
        ),
        ("TCP://[::1]:5020", ("tcp", "::1", 5020, None, {})),
        (
            "rtu:///dev/ttyUSB0?baudrate=19200&parity=e&stopbits=1&bytesize=8",
            ("rtu", None, None, "/dev/ttyUSB0", {"baudrate": "19200", "parity": "E", "stopbits": "1", "bytesize": "8"}),
        ),
        (
            "ascii:///dev/ttyS0?baudrate=9600&bytesize=7&parity=E",
            ("ascii", None, None, "/dev/ttyS0", {"baudrate": "9600", "bytesize": "7", "parity": "E"}),
        ),
        ("rtu+tcp://gw.local:4001", ("rtu+tcp", "gw.local", 4001, None, {})),
        ("tls://plc", ("tls", "plc", 802, None, {})),
        (
            "tls://plc:8802?verify=false&server_hostname=plc.example",
            ("tls", "plc", 8802, None, {"verify": "false", "server_hostname": "plc.example"}),
        ),
    ],
)
def test_parse_url(text: str, expect: tuple[str, str | None, int | None, str | None, dict[str, str]]) -> None:
    u = tp.parse_url(text)
    assert (u.scheme, u.host, u.port, u.path, u.options) == expect


def test_timeout_and_retries_from_url_or_arguments() -> None:
    u = tp.parse_url("tcp://h:1?timeout=0.5&retries=4", timeout=9, retries=9)
    assert (u.timeout, u.retries) == (0.5, 4)  # the URL wins
    u = tp.parse_url("tcp://h:1", timeout=9, retries=0)
    assert (u.timeout, u.retries) == (9, 0)
    u = tp.parse_url("tcp://h:1")
    assert (u.timeout, u.retries) == (1.0, 2)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("10.0.0.1", "'10.0.0.1' is not a device URL (expected e.g. tcp://HOST:502 or rtu:///dev/ttyUSB0)"),
        ("tpc://10.0.0.1", "unknown scheme 'tpc' in 'tpc://10.0.0.1'; did you mean 'tcp'?"),
        ("foo://h", "unknown scheme 'foo' in 'foo://h' (known: tcp, tls, rtu, ascii, rtu+tcp)"),
        ("rtu:///dev/x?baud=9600", "unknown option 'baud' in rtu URL; did you mean 'baudrate'?"),
        (
            "tcp://h?baudrate=9600",
            "unknown option 'baudrate' in tcp URL (known: device_identification, "
            "pause_after_connect, pause_between_requests, retries, timeout)",
        ),
        ("rtu:///dev/x?parity=X", "option parity=X must be N, E or O"),
        ("rtu:///dev/x?baudrate=fast", "option baudrate='fast' is not an integer"),
        ("rtu:///dev/x?timeout=abc", "option timeout='abc' is not a number"),
        ("tcp://h?retries=1.5", "option retries='1.5' is not an integer"),
        ("tcp://h:1?timeout=0", "option timeout=0 is out of range (0.001..600)"),
        ("ascii:///dev/x?bytesize=9", "option bytesize=9 is out of range (5..8)"),
        ("rtu:///dev/x?stopbits=3", "option stopbits=3 is out of range (1..2)"),
        ("rtu+tcp://gw", "rtu+tcp URL needs a port: rtu+tcp://HOST:PORT (the gateway's TCP port)"),
        ("rtu://", "rtu URL needs a serial device path: rtu:///dev/ttyUSB0 or rtu://COM3"),
        ("tcp://:502", "tcp URL needs a host: tcp://HOST:PORT"),
        ("tcp://h:99999", "bad port in 'tcp://h:99999'"),
        ("tcp://h:0", "bad port in 'tcp://h:0' (1..65535)"),
        ("tcp://h/x", "unexpected path '/x' in tcp URL"),
        ("tls://h?verify=maybe", "option verify=maybe must be true or false"),
        ("tls://h?cert=/nonexistent.crt&key=/x", "tls option cert: no such file '/nonexistent.crt'"),
    ],
)
def test_bad_urls(text: str, message: str) -> None:
    with pytest.raises(BadURL) as err:
        tp.parse_url(text)
    assert str(err.value) == message


def test_describe_hides_key_files_and_open_transport_picks_the_class(tmp_path: Path) -> None:
    key = tmp_path / "secret.key"
    key.write_text("x")
    u = tp.parse_url(f"tls://plc:802?cert={key}&key={key}&ca={key}&verify=false&timeout=2")
    assert tp.describe(u) == "tls://plc:802?verify=false"
    assert (
        tp.describe(tp.parse_url("rtu:///dev/ttyUSB0?parity=E&baudrate=9600&timeout=1"))
        == "rtu:///dev/ttyUSB0?baudrate=9600&parity=E"
    )
    assert tp.describe(tp.parse_url("tcp://[::1]")) == "tcp://[::1]:502"
    kinds = {
        s: type(tp.open_transport(u))
        for s, u in [
            ("tcp", "tcp://h"),
            ("tls", "tls://h"),
            ("rtu+tcp", "rtu+tcp://h:1"),
            ("rtu", "rtu:///dev/x"),
            ("ascii", "ascii:///dev/x"),
        ]
    }
    assert kinds == {
        "tcp": tp.TcpTransport,
        "tls": tp.TlsTransport,
        "rtu+tcp": tp.RtuOverTcpTransport,
        "rtu": tp.SerialTransport,
        "ascii": tp.SerialTransport,
    }


def test_bus_keys(tmp_path: Path) -> None:
    target = tmp_path / "ttyUSB0"
    target.write_text("")
    link = tmp_path / "by-id"
    link.symlink_to(target)
    # rtu and ascii on one wire, and a symlink to it, are one bus; gateways by host:port
    assert tp.parse_url(f"rtu://{link}").bus == tp.parse_url(f"ascii://{target}").bus
    assert tp.parse_url("rtu+tcp://gw:4001").bus == tp.parse_url("rtu+tcp://gw:4001?timeout=3").bus
    assert tp.parse_url("rtu+tcp://gw:4001").bus != tp.parse_url("rtu+tcp://gw:4002").bus
    assert not tp.parse_url("tcp://h").shared_bus and tp.parse_url("rtu+tcp://gw:1").shared_bus


# ---- TCP ---------------------------------------------------------------------------------------------


def test_tcp_round_trip_and_counters() -> None:
    async def main() -> None:
        async with serve("tcp") as port:
            t = tp.open_transport(f"tcp://127.0.0.1:{port}?timeout=1")
            frames = sent(t)
            async with t:
                await t.write_registers(10, [1, 2, 1000], 1)
                await t.write_register(13, 7, 1)
                assert await t.read_holding_registers(10, 4, 1) == [1, 2, 1000, 7]
                assert t.requests_sent == 3
            # MBAP: transaction id, protocol 0, length 13, unit 1, FC16 at 10, 3 registers, 6 bytes
            assert frames[0][2:] == bytes.fromhex("0000 000D 01 10 000A 0003 06 0001 0002 03E8")

    asyncio.run(main())


def test_exception_response_carries_function_and_code() -> None:
    async def main() -> None:
        async with serve("tcp") as port, tp.open_transport(f"tcp://127.0.0.1:{port}") as t:
            with pytest.raises(ExceptionResponse) as err:
                await t.read_holding_registers(REGS + 50, 1, 1)
            assert (err.value.function, err.value.code) == (3, 2)
            assert str(err.value) == "exception 02 (illegal data address)"
            with pytest.raises(ExceptionResponse) as err:
                await t.write_registers(0, [5, 2000], 1)
            assert (err.value.function, err.value.code) == (16, 3)
            assert await t.read_holding_registers(0, 2, 1) == [0, 0]  # the connection is still usable

    asyncio.run(main())


def test_refused_connection_is_unreachable_fast() -> None:
    async def main() -> None:
        port = dead_port()
        t = tp.open_transport(f"tcp://127.0.0.1:{port}?timeout=2")
        start = time.monotonic()
        with pytest.raises(Unreachable) as err:
            await t.connect()
        assert time.monotonic() - start < 1.0  # refused: no waiting for the timeout
        assert str(err.value) == f"tcp://127.0.0.1:{port}: connection refused"
        with pytest.raises(ConnectionLost):
            await t.read_holding_registers(0, 1, 1)

    asyncio.run(main())


def _connecting_to(port: int) -> bool:
    """A socket of this machine's (IPv4) sends SYNs to ``port`` unanswered: state SYN_SENT in /proc/net/tcp."""
    rows = Path("/proc/net/tcp").read_text().splitlines()[1:]
    return any(r.split()[2].endswith(f":{port:04X}") and r.split()[3] == "02" for r in rows)


@pytest.mark.skipif(sys.platform != "linux", reason="Linux drops a SYN while its listener's queue is full")
@pytest.mark.parametrize("retries", [2, 0])
def test_a_connection_that_fails_though_the_device_takes_others_is_tried_again(retries: int) -> None:
    """A gateway whose one connection slot another master holds a moment: Linux drops the client's SYN (and
    sends it again only after a second); the slot frees while pymodbus waits, its connect times out, and our
    probe gets through: the failure has passed, so the connection is tried again (``retries``), and made; the
    device's report says so (its notices), and the session's backoff is the wait before the next try.
    Without retries, unreachable, saying so."""
    import socket
    import threading

    from deployer.execute.connect import connect_notice, connected
    from tests.rtu_devices import Device, on_tcp, read_frame

    dev, accepting = Device({0: 7}), threading.Event()
    with on_tcp(dev, backlog=0, accepting=accepting) as port:
        other = socket.create_connection(("127.0.0.1", port))  # the other master, queued: the queue is full

        async def free_the_slot() -> None:
            while not _connecting_to(port):  # our SYN, dropped
                await asyncio.sleep(0.005)
            other.close()
            accepting.set()

        notices: list[str] = []
        failures: list[int] = []

        async def main() -> list[int]:
            freeing = asyncio.create_task(free_the_slot())
            url = tp.parse_url(f"rtu+tcp://127.0.0.1:{port}?timeout=0.5&retries={retries}")
            try:
                # the run's backoff reaches the connection's retries (0.2 s, not the transport's own 0.05 s): the
                # gateway's one slot is free again by then, on a loaded machine too
                async with connected(url, 1, None, backoff=0.2, notices=notices) as session:
                    assert session.transport.backoff == 0.2
                    failures.append(session.transport.connect_failures)
                    return await session.transport.read_holding_registers(0, 1, 1)
            finally:
                await freeing

        if retries:
            assert asyncio.run(main()) == [7]
            # once here; twice when a loaded machine's loop missed the second connection within the timeout too
            assert failures[0] in (1, 2) and notices == [connect_notice(failures[0])]
            assert connect_notice(1) == (
                "connecting failed once, though a test connection right after it got through; tried again (the URL's "
                "retries): the device or its gateway was slow to take a connection"
            )
            assert connect_notice(2).startswith("connecting failed 2 times, though a test connection after each got ")
        else:
            with pytest.raises(Unreachable) as err:
                asyncio.run(main())
            assert str(err.value) == (
                f"rtu+tcp://127.0.0.1:{port}: connection failed, though a test connection right after got through"
            )
    assert dev.frames == ([read_frame(0, 1)] if retries else [])


def test_swallowed_request_is_no_response_after_the_timeout() -> None:
    swallow = {"on": False}

    def trace_pdu(sending: bool, pdu: ModbusPDU) -> ModbusPDU | None:
        return None if swallow["on"] and not sending else pdu

    async def main() -> None:
        async with (
            serve("tcp", trace_pdu=trace_pdu) as port,
            tp.open_transport(f"tcp://127.0.0.1:{port}?timeout=0.3") as t,
        ):
            assert await t.read_holding_registers(0, 1, 1) == [0]
            swallow["on"] = True
            start = time.monotonic()
            with pytest.raises(NoResponse, match=r"no answer within 0.3 s"):
                await t.write_registers(0, [1], 1)
            elapsed = time.monotonic() - start
            assert 0.25 <= elapsed < 1.5  # one attempt: pymodbus's own retries are off
            assert t.requests_sent == 2

    asyncio.run(main())


def test_server_gone_is_connection_lost_then_unreachable() -> None:
    async def main() -> None:
        async with serve("tcp") as port:
            t = tp.open_transport(f"tcp://127.0.0.1:{port}?timeout=0.5")
            await t.connect()
            assert await t.read_holding_registers(0, 1, 1) == [0]
        await asyncio.sleep(0.05)  # let the close reach the client
        with pytest.raises((ConnectionLost, NoResponse)):
            await t.read_holding_registers(0, 1, 1)
        with pytest.raises(Unreachable, match="connection refused"):
            await t.reconnect()

    asyncio.run(main())


def test_broadcast_does_not_wait_for_an_answer() -> None:
    async def main() -> None:
        async with serve("tcp", units=(1, 2)) as port, tp.open_transport(f"tcp://127.0.0.1:{port}?timeout=2") as t:
            start = time.monotonic()
            await t.write_registers(20, [42], 0)
            assert time.monotonic() - start < 0.5  # returns at once (timeout=2): nobody answers a broadcast
            # the next request waits out the turnaround delay (pymodbus's server even drops a request that
            # arrives in the same TCP segment as the broadcast), then sees it applied on every unit
            assert await t.read_holding_registers(20, 1, 1) == [42]
            assert time.monotonic() - start >= tp.BROADCAST_TURNAROUND
            assert await t.read_holding_registers(20, 1, 2) == [42]

    asyncio.run(main())


# ---- TLS ---------------------------------------------------------------------------------------------


def server_context(pki: dict[str, str]) -> ssl.SSLContext:
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH, cafile=pki["ca"])
    ctx.load_cert_chain(pki["server_crt"], pki["server_key"])
    ctx.verify_mode = ssl.CERT_REQUIRED  # Modbus/TCP Security: mutual authentication
    return ctx


def test_tls_mutual_authentication(pki: dict[str, str]) -> None:
    async def main() -> None:
        async with serve("tls", sslctx=server_context(pki)) as port:
            mine = f"cert={pki['client_crt']}&key={pki['client_key']}"
            t = tp.open_transport(f"tls://127.0.0.1:{port}?{mine}&ca={pki['ca']}&timeout=2")
            async with t:
                await t.write_registers(5, [0, 1000], 1)
                assert await t.read_holding_registers(5, 2, 1) == [0, 1000]
            # the certificate names localhost and 127.0.0.1: verifying another name must fail
            t = tp.open_transport(f"tls://127.0.0.1:{port}?{mine}&ca={pki['ca']}&server_hostname=localhost")
            async with t:
                assert await t.read_holding_registers(5, 2, 1) == [0, 1000]
            with pytest.raises(Unreachable, match="TLS handshake failed.*match"):
                await tp.open_transport(
                    f"tls://127.0.0.1:{port}?{mine}&ca={pki['ca']}&server_hostname=plc.example"
                ).connect()
            with pytest.raises(Unreachable) as err:
                await tp.open_transport(f"tls://127.0.0.1:{port}?{mine}&ca={pki['other_ca']}&timeout=2").connect()
            assert str(err.value).startswith(f"tls://127.0.0.1:{port}: TLS handshake failed: ")
            assert "CERTIFICATE_VERIFY_FAILED" in str(err.value)
            # verify=false: encrypted, the device is not authenticated (a self-signed device certificate)
            t = tp.open_transport(f"tls://127.0.0.1:{port}?{mine}&ca={pki['other_ca']}&verify=false")
            async with t:
                assert await t.read_holding_registers(5, 2, 1) == [0, 1000]

    asyncio.run(main())


def test_tls_without_client_certificate_is_refused_by_the_device(pki: dict[str, str]) -> None:
    """TLS 1.3: the handshake completes on our side and the server closes once it misses our certificate."""

    async def main() -> None:
        async with serve("tls", sslctx=server_context(pki)) as port:
            t = tp.open_transport(f"tls://127.0.0.1:{port}?ca={pki['ca']}&timeout=0.5")
            await t.connect()
            with pytest.raises(ConnectionLost, match="before any answer .*client certificate"):
                await t.read_holding_registers(0, 1, 1)
            await t.close()

    asyncio.run(main())


def test_tls_refused_is_not_reported_as_a_handshake_failure(pki: dict[str, str]) -> None:
    async def main() -> None:
        port = dead_port()
        with pytest.raises(Unreachable) as err:
            await tp.open_transport(f"tls://127.0.0.1:{port}?ca={pki['ca']}").connect()
        assert str(err.value) == f"tls://127.0.0.1:{port}: connection refused"

    asyncio.run(main())


# ---- RTU over TCP (serial gateways) ------------------------------------------------------------------


def rtu_frame(address: int, values: list[int], unit: int) -> bytes:
    return bytes(
        FramerRTU(DecodePDU(False)).buildFrame(
            WriteMultipleRegistersRequest(address=address, registers=values, dev_id=unit)
        )
    )


def test_rtu_over_tcp_gateway() -> None:
    async def main() -> None:
        async with serve("rtu+tcp", units=(4,)) as port:
            t = tp.open_transport(f"rtu+tcp://127.0.0.1:{port}?timeout=1")
            frames = sent(t)
            async with t:
                await t.write_registers(16, [0, 1000, 500], 4)
                assert await t.read_holding_registers(16, 3, 4) == [0, 1000, 500]
            async with tp.open_transport(f"rtu+tcp://127.0.0.1:{port}?timeout=0.2") as quick:
                with pytest.raises(NoResponse):  # unit 5 is not behind the gateway: silence, like RS-485
                    await quick.read_holding_registers(16, 1, 5)
            assert frames[0] == rtu_frame(16, [0, 1000, 500], 4)
            assert frames[0] == bytes.fromhex("04 10 0010 0003 06 0000 03E8 01F4") + frames[0][-2:]

    asyncio.run(main())


# ---- serial over pseudo-terminals ----------------------------------------------------------------------


def test_missing_serial_device_is_unreachable(tmp_path: Path) -> None:
    async def main() -> None:
        with pytest.raises(Unreachable) as err:
            await tp.open_transport(f"rtu://{tmp_path}/ttyNOPE").connect()
        assert str(err.value) == f"rtu://{tmp_path}/ttyNOPE: no such serial device '{tmp_path}/ttyNOPE'"

    asyncio.run(main())


def test_port_held_by_another_process_is_unreachable_with_the_reason(pty_pair: tuple[str, str]) -> None:
    a, _ = pty_pair

    async def main() -> None:
        async with serve("rtu", path=a):  # the server holds end A exclusively
            held = (
                "is in use by another program"
                if sys.platform == "win32"
                else "cannot open the serial port: .*exclusively lock"
            )
            with pytest.raises(Unreachable, match=held):
                await tp.open_transport(f"rtu://{a}").connect()

    asyncio.run(main())


def test_line_settings_a_pty_rejects_are_reported_and_leave_the_port_free(pty_pair: tuple[str, str]) -> None:
    """This kernel's ptys refuse 7E1 ("Invalid argument"): a clear Unreachable, and the port is not left locked."""
    _, b = pty_pair

    async def main() -> None:
        try:
            async with tp.open_transport(f"ascii://{b}?bytesize=7&parity=E"):
                pass  # a kernel that accepts it: nothing to report
        except Unreachable as e:
            assert str(e) == (
                f"ascii://{b}?bytesize=7&parity=E: the port rejects these line settings "
                f"(bytesize=7 parity=E): Invalid argument"
            )
        async with tp.open_transport(f"ascii://{b}") as t:  # 8N1 opens at once: nothing kept the port locked
            assert t.requests_sent == 0

    asyncio.run(main())


def test_rtu_round_trip_on_a_pty(pty_pair: tuple[str, str]) -> None:
    a, b = pty_pair

    async def main() -> None:
        async with serve("rtu", path=a, units=(3,)):
            t = tp.open_transport(f"rtu://{b}?baudrate=19200&timeout=1")
            frames = sent(t)
            async with t:
                await t.write_registers(30, [11, 22, 33], 3)
                assert await t.read_holding_registers(30, 3, 3) == [11, 22, 33]
                with pytest.raises(ExceptionResponse) as err:
                    await t.write_registers(30, [1, 5000], 3)
                assert err.value.code == 3
                with pytest.raises(NoResponse):  # nobody at unit 9: a serial line stays silent
                    await t.read_holding_registers(30, 1, 9)
            assert frames[0] == rtu_frame(30, [11, 22, 33], 3)

    asyncio.run(main())


def test_rtu_broadcast_reaches_every_unit(pty_pair: tuple[str, str]) -> None:
    a, b = pty_pair

    async def main() -> None:
        async with serve("rtu", path=a, units=(1, 2)), tp.open_transport(f"rtu://{b}?timeout=1") as t:
            start = time.monotonic()
            await t.write_registers(60, [7, 8], 0)
            assert time.monotonic() - start < 0.5  # nobody answers: no waiting for the timeout
            assert await t.read_holding_registers(60, 2, 1) == [7, 8]  # after the turnaround delay
            assert time.monotonic() - start >= tp.BROADCAST_TURNAROUND
            assert await t.read_holding_registers(60, 2, 2) == [7, 8]

    asyncio.run(main())


def test_ascii_bytes_on_the_wire(pty_pair: tuple[str, str]) -> None:
    a, b = pty_pair

    async def main() -> None:
        async with serve("ascii", path=a, units=(4,)):
            t = tp.open_transport(f"ascii://{b}?timeout=1")
            frames = sent(t)
            async with t:
                await t.write_registers(0x0010, [0, 1000], 4)
                assert await t.read_holding_registers(0x0010, 2, 4) == [0, 1000]
            built = FramerAscii(DecodePDU(False)).buildFrame(
                WriteMultipleRegistersRequest(address=0x0010, registers=[0, 1000], dev_id=4)
            )
            # LRC by hand: 04+10+00+10+00+02+04+00+00+03+E8 = 115h; -15h & FFh = EBh
            assert frames[0] == built == b":04100010000204000003E8EB\r\n"

    asyncio.run(main())


def test_rtu_keeps_the_silent_interval_between_frames(pty_pair: tuple[str, str]) -> None:
    """pymodbus 3.16's async client sends the next frame at once; the transport waits 3.5 characters."""
    a, b = pty_pair

    async def main() -> None:
        async with serve("rtu", path=a):
            t = tp.open_transport(f"rtu://{b}?baudrate=1200&timeout=2")
            events: list[tuple[str, float]] = []
            t.on_frame = lambda d, data: events.append((d, time.monotonic()))
            async with t:
                for i in range(4):
                    await t.write_registers(0, [i], 1)
            sends = [ts for d, ts in events if d == "send"]
            last_recv = [max(ts for d, ts in events if d == "recv" and ts < s) for s in sends[1:]]
            gap = 3.5 * 10 / 1200  # 8N1: 10 bits a character
            assert len(sends) == 4
            assert all(s - r >= gap * 0.95 for s, r in zip(sends[1:], last_recv, strict=True))

    asyncio.run(main())


def test_two_transports_on_one_line_never_interleave(pty_pair: tuple[str, str]) -> None:
    """Two devices on one RS-485 line, driven by two concurrent tasks with a transport each."""
    a, b = pty_pair
    baud = 4800
    gap = 3.5 * 10 / baud

    async def main() -> None:
        async with serve("rtu", path=a, units=(1, 2)):
            events: list[tuple[int, str, float, bytes]] = []
            transports = [tp.open_transport(f"rtu://{b}?baudrate={baud}&timeout=1") for _ in (1, 2)]
            for unit, t in enumerate(transports, 1):
                t.on_frame = (lambda u: lambda d, data: events.append((u, d, time.monotonic(), data)))(unit)
                await t.connect()

            async def worker(unit: int, t: tp.Transport) -> None:
                for i in range(10):  # 20 requests: write, read back
                    await t.write_registers(40, [unit * 100 + i], unit)
                    assert await t.read_holding_registers(40, 1, unit) == [unit * 100 + i]

            await asyncio.gather(*(worker(u, t) for u, t in enumerate(transports, 1)))
            for t in transports:
                await t.close()
            assert [t.requests_sent for t in transports] == [20, 20]
            sends = [(u, ts, data) for u, d, ts, data in events if d == "send"]
            assert len(sends) == 40 and {data[0] for _, _, data in sends} == {1, 2}
            # the tasks really ran at once: the line switched between the devices many times
            assert sum(1 for x, y in itertools.pairwise(sends) if x[0] != y[0]) >= 10
            # every request is answered (to its own transport) before the next request starts, after 3.5 chars
            for k, (_u, ts, _) in enumerate(sends[1:], 1):
                prev_u, prev_ts, _ = sends[k - 1]
                answers = [e for e in events if e[1] == "recv" and prev_ts < e[2] < ts]
                assert answers and all(e[0] == prev_u for e in answers)
                assert ts - answers[-1][2] >= gap * 0.95

    asyncio.run(main())


def test_one_port_different_settings_is_refused(pty_pair: tuple[str, str]) -> None:
    _, b = pty_pair

    async def main() -> None:
        async with tp.open_transport(f"rtu://{b}?baudrate=9600"):
            with pytest.raises(Unreachable, match="already open here as rtu baudrate=9600"):
                await tp.open_transport(f"rtu://{b}?baudrate=19200").connect()
            with pytest.raises(Unreachable, match="already open"):
                await tp.open_transport(f"ascii://{b}?baudrate=9600").connect()
        # closed by its last user: the port opens again with other settings
        async with tp.open_transport(f"rtu://{b}?baudrate=19200"):
            pass

    asyncio.run(main())


def test_bus_lock_is_reentrant_for_its_holder(pty_pair: tuple[str, str]) -> None:
    """The executor may hold the bus for a whole device session: its own requests nest, others wait."""
    a, b = pty_pair

    async def main() -> None:
        async with serve("rtu", path=a, units=(1, 2)):
            one, two = tp.open_transport(f"rtu://{b}?timeout=1"), tp.open_transport(f"rtu://{b}?timeout=1")
            await one.connect()
            await two.connect()
            lock = tp.bus_lock(one.url)
            assert lock is tp.bus_lock(two.url) and isinstance(lock, tp.BusLock)
            order: list[str] = []

            async def other() -> None:
                await two.write_registers(50, [2], 2)
                order.append("other")

            async with lock:  # a device session
                task = asyncio.create_task(other())
                for i in range(3):
                    async with asyncio.timeout(2):  # not wait_for: that runs the call in another task
                        await one.write_registers(50, [i], 1)  # nests, no deadlock
                    order.append(f"session{i}")
                await asyncio.sleep(0.1)
                assert not task.done()  # the other device waits for the session to end
            await asyncio.wait_for(task, 2)
            assert order == ["session0", "session1", "session2", "other"]
            with pytest.raises(RuntimeError, match="does not hold"):
                lock.release()
            await one.close()
            await two.close()

    asyncio.run(main())


# ---- interop: a Modbus server we did not write ---------------------------------------------------------


@pytest.fixture
def umodbus_server() -> Iterator[tuple[int, dict[int, int]]]:
    store: dict[int, int] = {100: 0, 101: 500, 102: 7}
    with start_umodbus(store) as port:
        yield port, store


def test_umodbus_interop(umodbus_server: tuple[int, dict[int, int]]) -> None:
    port, store = umodbus_server

    async def main() -> None:
        async with tp.open_transport(f"tcp://127.0.0.1:{port}?timeout=2") as t:
            assert await t.read_holding_registers(100, 3, 1) == [0, 500, 7]
            await t.write_registers(100, [0, 1000], 1)
            await t.write_register(102, 65535, 1)
            assert await t.read_holding_registers(100, 3, 1) == [0, 1000, 65535]
            with pytest.raises(ExceptionResponse) as err:
                await t.read_holding_registers(200, 1, 1)  # no route: umodbus answers 02
            assert err.value.code == 2

    asyncio.run(main())
    assert store == {100: 0, 101: 1000, 102: 65535}


def test_a_socket_connected_to_itself_is_no_device() -> None:
    """On loopback a connect to a port nothing listens on can meet itself (TCP simultaneous open, when the
    kernel picks that port as the local one): the transport must take it as refused, not read its own
    requests back as answers. Made here on purpose by binding the client to the port it connects to."""
    import socket

    from pymodbus.client import AsyncModbusTcpClient

    from deployer.profile import builtin_profile
    from deployer.testing.simulator import Simulator
    from deployer.transport.clients import _connected_to_itself

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = int(s.getsockname()[1])
    s.close()

    async def main() -> tuple[bool, bool]:
        c = AsyncModbusTcpClient("127.0.0.1", port=port, source_address=("127.0.0.1", port), timeout=1, retries=0)
        assert await c.connect()
        looped = _connected_to_itself(c)
        c.close()
        async with Simulator(builtin_profile("omron-m1")) as sim:
            host, real_port = sim.url.removeprefix("tcp://").rsplit(":", 1)
            d = AsyncModbusTcpClient(host, port=int(real_port), timeout=1, retries=0)
            assert await d.connect()
            real = _connected_to_itself(d)
            d.close()
        return looped, real

    assert asyncio.run(main()) == (True, False)
