"""Transports: one small interface, chosen by URL scheme, over pymodbus's async clients.

tcp://HOST[:PORT]  tls://HOST[:PORT]?cert=&key=&ca=  rtu:///dev/X?baudrate=&parity=&bytesize=&stopbits=
ascii:///dev/X?...  rtu+tcp://HOST:PORT.  Options on all: timeout (s), retries.

A transport sends exactly one request per call and never retries by itself (pymodbus's own
retries are off): the executor retries, counts attempts and reports them.

Serial timing: pymodbus 3.16's async serial client writes the next frame as soon as it is asked
(its RTU framer finds frame ends by length and CRC, not by silence), so the transports keep the
3.5-character silent interval themselves, per bus, and hold bus_lock() around each request.
Transports on one serial port share one open port: pymodbus opens ports with an exclusive lock.
"""

from __future__ import annotations

import abc
import asyncio
import functools
import os
import ssl
import time
import weakref
from collections.abc import Callable
from typing import Any, Literal

import serial
from pymodbus import FramerType
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient, AsyncModbusTlsClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

# URLs and errors live apart from pymodbus (commands that only parse URLs stay light); re-exported here
from .urls import DEFAULT_PORTS as DEFAULT_PORTS
from .urls import SERIAL_DEFAULTS as SERIAL_DEFAULTS
from .urls import BadURL as BadURL
from .urls import ConnectionLost as ConnectionLost
from .urls import DeviceURL as DeviceURL
from .urls import ExceptionResponse as ExceptionResponse
from .urls import LineSettings as LineSettings
from .urls import NoResponse as NoResponse
from .urls import TransportError as TransportError
from .urls import Unreachable as Unreachable
from .urls import describe as describe
from .urls import no_answer_hint as no_answer_hint
from .urls import pacing as pacing
from .urls import parse_url as parse_url
from .urls import verify as _verify


class Transport(abc.ABC):
    """One connection to one URL; any unit id on it. One request in flight at a time."""

    url: DeviceURL
    requests_sent: int  # requests put on the wire (every attempt counts)
    on_frame: Callable[[str, bytes], None] | None  # ("send" | "recv", raw bytes); recv may come in chunks

    @abc.abstractmethod
    async def connect(self) -> None:
        """Open the connection. Raises Unreachable."""

    @abc.abstractmethod
    async def reconnect(self) -> None:
        """Close and open again after a ConnectionLost. Raises Unreachable."""

    @abc.abstractmethod
    async def close(self) -> None: ...

    @abc.abstractmethod
    async def read_holding_registers(self, address: int, count: int, unit: int) -> list[int]:
        """FC03. Raises ExceptionResponse, NoResponse, ConnectionLost."""

    @abc.abstractmethod
    async def write_registers(self, address: int, values: list[int], unit: int) -> None:
        """FC16. unit 0 (broadcast) returns without waiting for an answer."""

    @abc.abstractmethod
    async def write_register(self, address: int, value: int, unit: int) -> None:
        """FC06."""

    @abc.abstractmethod
    async def read(self, function: int, address: int, count: int, unit: int) -> list[int]:
        """FC03 or FC04 (registers), FC01 or FC02 (bits, as 0/1). Raises like read_holding_registers."""

    @abc.abstractmethod
    async def write_coil(self, address: int, value: bool, unit: int) -> None:
        """FC05."""

    @abc.abstractmethod
    async def write_coils(self, address: int, values: list[bool], unit: int) -> None:
        """FC15."""

    @abc.abstractmethod
    async def read_device_identification(self, unit: int, read_code: int = 1) -> dict[int, bytes]:
        """FC43 / 14: object id -> bytes (basic objects with read code 1). Raises like the others."""

    @abc.abstractmethod
    def set_pacing(self, after_connect: float, between: float) -> None:
        """Seconds of silence after connecting and at least between two requests on this device's bus."""

    async def __aenter__(self) -> Transport:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


# ---- buses ---------------------------------------------------------------------------------


class BusLock(asyncio.Lock):
    """An asyncio.Lock that the task holding it may take again (reentrant per task).

    Rule: the executor may hold the bus for a whole device session and issue requests from the
    same task; each request's own acquire then nests instead of deadlocking. Another task waits
    until the holder released as often as it acquired. Do not hold it and then await child tasks
    that talk on the same bus: they are other tasks and would wait for ever.
    """

    def __init__(self) -> None:
        super().__init__()
        self._owner: asyncio.Task[Any] | None = None
        self._depth = 0

    async def acquire(self) -> Literal[True]:
        task = asyncio.current_task()
        if task is not None and self._owner is task:
            self._depth += 1
            return True
        await super().acquire()
        self._owner, self._depth = task, 1
        return True

    def release(self) -> None:
        if self._owner is not asyncio.current_task():
            raise RuntimeError("bus lock released by a task that does not hold it")
        self._depth -= 1
        if self._depth == 0:
            self._owner = None
            super().release()


class _Bus:
    """What devices on one half-duplex bus share within one event loop."""

    def __init__(self) -> None:
        self.lock = BusLock()
        self.quiet_until = 0.0  # monotonic time before which nobody may start a frame
        self.line: _SerialLine | None = None  # the open serial port, shared by its transports
        self.opening = asyncio.Lock()


_BUSES: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, dict[str, _Bus]] = weakref.WeakKeyDictionary()


def _bus(url: DeviceURL) -> _Bus:
    buses = _BUSES.setdefault(asyncio.get_running_loop(), {})
    key = url.bus
    bus = buses.get(key)
    if bus is None:
        bus = buses[key] = _Bus()
    return bus


def bus_lock(url: DeviceURL) -> asyncio.Lock:
    """The lock of the bus ``url`` sits on: one per url.bus key (serial path, gateway) per event loop.

    Transports on a shared bus (rtu, ascii, rtu+tcp) hold it around each request, so two devices
    on one RS-485 line never talk at once. It is a BusLock: reentrant for the task holding it.
    """
    return _bus(url).lock


# ---- pymodbus-backed transports ----------------------------------------------------------------


def _char_time(url: DeviceURL) -> float:
    """Seconds per character on a serial line: start + data + parity + stop bits."""
    line = url.line
    return (1 + line.bytesize + (0 if line.parity == "N" else 1) + line.stopbits) / line.baudrate


BROADCAST_TURNAROUND = 0.1  # seconds of silence after a unit-0 write


def _silent_interval(url: DeviceURL) -> float:
    """Modbus over serial line 2.5.1.1: 3.5 character times between frames, fixed 1.75 ms above 19200 baud."""
    if url.line.baudrate > 19200:
        return 0.00175
    return 3.5 * _char_time(url)


class PymodbusTransport(Transport):
    """Base of the transports: one pymodbus async client, its retries off, one request per call.

    Results are translated: exception response -> ExceptionResponse, no answer -> NoResponse,
    dropped/not connected -> ConnectionLost, failed connect -> Unreachable naming the URL.
    """

    def __init__(self, url: DeviceURL) -> None:
        self.url = url
        self.requests_sent = 0
        self.on_frame: Callable[[str, bytes], None] | None = None
        self._client: Any = None
        self._shared = url.shared_bus
        # pymodbus 3.16's async clients send the next frame at once: the transport keeps the silence
        self._gap = _silent_interval(url) if self._shared else 0.0
        self._quiet_until = 0.0  # this connection's own quiet time (after a broadcast)
        self._answered = False  # any answer on this connection yet (tells a refused TLS session)
        self._sent_bytes = 0  # length of the last frame sent: a broadcast's own line time
        self._after_connect, self._between = pacing(url)  # pauses some devices need (URL options, profile)

    # -- hooks for the subclasses

    @abc.abstractmethod
    def _make_client(self) -> Any:
        """A new, unconnected pymodbus async client."""

    def set_pacing(self, after_connect: float, between: float) -> None:
        self._after_connect, self._between = after_connect, between

    def _paced(self) -> bool:
        return self._shared or bool(self._after_connect or self._between)

    def _connected(self) -> None:
        """A connection opened: nothing is sent before the device's pause after connecting."""
        if self._after_connect:
            quiet = time.monotonic() + self._after_connect
            self._quiet_until = max(self._quiet_until, quiet)
            bus = _bus(self.url)
            bus.quiet_until = max(bus.quiet_until, quiet)

    def _common(self) -> dict[str, Any]:
        # retries=0: a late answer to a first copy would hide a double write (docs/design.md, transports)
        # reconnect_delay=0: pymodbus must not reconnect behind our back, the executor decides
        return {"timeout": self.url.timeout, "retries": 0, "trace_packet": self._trace,
                "reconnect_delay": 0, "reconnect_delay_max": 0}

    async def _why_not(self) -> str:
        """Why connect() returned False (pymodbus swallows the reason): probe once more ourselves."""
        return "connection failed"

    def _lost(self, why: str) -> ConnectionLost:
        return ConnectionLost(f"{describe(self.url)}: {why}")

    def _trace(self, sending: bool, data: bytes) -> bytes:
        if sending:
            self._sent_bytes = len(data)
        if self.on_frame is not None:
            self.on_frame("send" if sending else "recv", data)
        return data

    # -- connection

    async def connect(self) -> None:
        where = describe(self.url)
        self._answered = False
        try:
            client = self._make_client()
        except ssl.SSLError as e:
            raise Unreachable(f"{where}: TLS setup failed: {e.reason or e}") from None
        except (OSError, ValueError) as e:
            raise Unreachable(f"{where}: {e}") from None
        try:
            ok = await client.connect()
        except Exception as e:  # asyncio and pyserial raise a zoo of errors for a bad peer
            client.close()
            raise Unreachable(f"{where}: cannot connect: {e}") from None
        if not ok or not client.connected:
            client.close()
            raise Unreachable(f"{where}: {await self._why_not()}")
        self._client = client
        self._connected()

    async def reconnect(self) -> None:
        await self.close()
        await self.connect()

    async def _settle(self) -> None:
        """Before closing: let a last broadcast's turnaround pass, so the devices carry it out."""
        wait = self._quiet_until - time.monotonic()
        if wait > 0:
            await asyncio.sleep(wait)

    async def close(self) -> None:
        if self._client is not None:
            await self._settle()
            self._client.close()
            self._client = None

    # -- requests

    async def _run(self, function: int, call: Callable[[Any], Any], *, no_answer: bool = False) -> Any:
        if self._client is None or not self._client.connected:
            raise ConnectionLost(f"{describe(self.url)}: not connected")
        # a shared line, or a device that needs pauses: requests of every device on its bus take turns
        bus = _bus(self.url) if self._paced() else None
        if bus is not None:
            await bus.lock.acquire()
        try:
            if bus is not None:
                self._claim(bus)
            wait = max(self._quiet_until, bus.quiet_until if bus is not None else 0.0) - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            self.requests_sent += 1
            try:
                result = await call(self._client)
            except ConnectionException as e:
                raise self._lost(str(e)) from None
            except ModbusIOException:
                if self._client is None or not self._client.connected:
                    raise self._lost("the connection closed") from None
                raise NoResponse(f"no answer within {self.url.timeout:g} s") from None
            except ModbusException as e:
                raise NoResponse(str(e)) from None
            finally:
                # the next frame may start only after the silent interval (serial buses) and the pause
                # the device needs between requests
                quiet = time.monotonic() + max(self._gap, self._between)
                if no_answer:
                    # broadcast: nobody answers, so give the devices the turnaround delay to carry it out
                    # (serial line spec 2.4.1: 100-200 ms); pymodbus returned as soon as the frame was
                    # queued, so its own time on the line comes first
                    quiet += BROADCAST_TURNAROUND + (self._sent_bytes * _char_time(self.url) if self._shared else 0)
                self._quiet_until = quiet
                if bus is not None:
                    bus.quiet_until = quiet
            if no_answer:
                return None
            self._answered = True
            if result.isError():
                raise ExceptionResponse(function, int(getattr(result, "exception_code", 0)))
            return result
        finally:
            if bus is not None:
                bus.lock.release()

    def _claim(self, bus: _Bus) -> None:
        """Called under the bus lock before a request (the shared serial line routes its frames here)."""

    async def read_holding_registers(self, address: int, count: int, unit: int) -> list[int]:
        r = await self._run(3, lambda c: c.read_holding_registers(address, count=count, device_id=unit))
        regs = list(r.registers)
        if len(regs) != count:
            raise NoResponse(f"answer has {len(regs)} registers, asked for {count}")
        return regs

    async def write_registers(self, address: int, values: list[int], unit: int) -> None:
        await self._run(16, lambda c: c.write_registers(address, values, device_id=unit,
                                                        no_response_expected=unit == 0), no_answer=unit == 0)

    async def write_register(self, address: int, value: int, unit: int) -> None:
        await self._run(6, lambda c: c.write_register(address, value, device_id=unit,
                                                      no_response_expected=unit == 0), no_answer=unit == 0)

    async def read(self, function: int, address: int, count: int, unit: int) -> list[int]:
        if function == 3:
            return await self.read_holding_registers(address, count, unit)
        if function == 4:
            r = await self._run(4, lambda c: c.read_input_registers(address, count=count, device_id=unit))
            values = list(r.registers)
        elif function in (1, 2):
            call = "read_coils" if function == 1 else "read_discrete_inputs"
            r = await self._run(function, lambda c: getattr(c, call)(address, count=count, device_id=unit))
            bits = list(r.bits)  # padded to whole bytes: the answer carries ceil(count / 8) bytes
            if len(bits) < count:
                raise NoResponse(f"answer has {len(bits)} bits, asked for {count}")
            return [1 if b else 0 for b in bits[:count]]
        else:
            raise ValueError(f"function {function} is not a read")
        if len(values) != count:
            raise NoResponse(f"answer has {len(values)} registers, asked for {count}")
        return values

    async def write_coil(self, address: int, value: bool, unit: int) -> None:
        await self._run(5, lambda c: c.write_coil(address, value, device_id=unit,
                                                  no_response_expected=unit == 0), no_answer=unit == 0)

    async def write_coils(self, address: int, values: list[bool], unit: int) -> None:
        await self._run(15, lambda c: c.write_coils(address, values, device_id=unit,
                                                    no_response_expected=unit == 0), no_answer=unit == 0)

    async def read_device_identification(self, unit: int, read_code: int = 1) -> dict[int, bytes]:
        objects: dict[int, bytes] = {}
        object_id = 0
        for _ in range(8):  # 'more follows' pages; a device repeating itself must not loop for ever
            r = await self._run(43, functools.partial(_read_identification, read_code=read_code,
                                                      object_id=object_id, unit=unit))
            for oid, value in dict(r.information).items():
                objects[int(oid)] = value[0] if isinstance(value, list) else bytes(value)
            if not r.more_follows or r.next_object_id <= object_id:
                break
            object_id = r.next_object_id
        return objects


def _read_identification(client: Any, *, read_code: int, object_id: int, unit: int) -> Any:
    return client.read_device_information(read_code=read_code, object_id=object_id, device_id=unit)


class TcpTransport(PymodbusTransport):
    """tcp://: Modbus/TCP (MBAP header)."""

    def _make_client(self) -> Any:
        return AsyncModbusTcpClient(self.url.host or "", port=self.url.port or 502, framer=FramerType.SOCKET,
                                    **self._common())

    async def _why_not(self) -> str:
        try:
            _, writer = await asyncio.wait_for(asyncio.open_connection(self.url.host, self.url.port),
                                               self.url.timeout)
        except ConnectionRefusedError:
            return "connection refused"
        except TimeoutError:
            return f"connection timed out after {self.url.timeout:g} s"
        except OSError as e:
            return f"cannot connect: {e.strerror or e}"
        writer.close()
        return "connection failed"


class RtuOverTcpTransport(TcpTransport):
    """rtu+tcp://: RTU frames (unit id + CRC) over a TCP socket to a serial gateway; shares the gateway's bus."""

    def _make_client(self) -> Any:
        return AsyncModbusTcpClient(self.url.host or "", port=self.url.port or 0, framer=FramerType.RTU,
                                    **self._common())


class _HostnameContext(ssl.SSLContext):
    """An SSLContext that verifies a fixed name (server_hostname=) instead of the host connected to."""

    hostname: str | None = None

    def wrap_bio(self, incoming: ssl.MemoryBIO, outgoing: ssl.MemoryBIO, server_side: bool = False,
                 server_hostname: str | bytes | None = None, session: ssl.SSLSession | None = None) -> ssl.SSLObject:
        return super().wrap_bio(incoming, outgoing, server_side, self.hostname or server_hostname, session)


class TlsTransport(TcpTransport):
    """tls://: Modbus/TCP Security; client certificate from cert=/key=, trust from ca= (else the system's)."""

    def ssl_context(self) -> ssl.SSLContext:
        o = self.url.options
        ctx = _HostnameContext(ssl.PROTOCOL_TLS_CLIENT)
        ctx.hostname = o.get("server_hostname") or None
        ctx.minimum_version = ssl.TLSVersion.TLSv1_2  # Modbus/TCP Security requires TLS 1.2 or later
        if _verify(self.url):
            if "ca" in o:
                ctx.load_verify_locations(cafile=o["ca"])
            else:
                ctx.load_default_certs(ssl.Purpose.SERVER_AUTH)
        else:  # a self-signed device certificate: encryption without authentication, on request only
            ctx.check_hostname = False
            ctx.verify_mode = ssl.CERT_NONE
        if "cert" in o:
            ctx.load_cert_chain(o["cert"], o["key"])
        return ctx

    def _lost(self, why: str) -> ConnectionLost:
        if not self._answered:  # TLS 1.3: the server checks our certificate after the handshake, then closes
            why += " before any answer (did the device refuse our client certificate? check cert= and key=)"
        return super()._lost(why)

    def _make_client(self) -> Any:
        return AsyncModbusTlsClient(self.url.host or "", port=self.url.port or 802, sslctx=self.ssl_context(),
                                    **self._common())

    async def _why_not(self) -> str:
        try:
            _, writer = await asyncio.wait_for(
                asyncio.open_connection(self.url.host, self.url.port, ssl=self.ssl_context()), self.url.timeout)
        except ssl.SSLError as e:
            why = e.reason or str(e)
            if isinstance(e, ssl.SSLCertVerificationError) and e.verify_message:
                why += f": {e.verify_message}"  # e.g. "Hostname mismatch, certificate is not valid for 'x'"
            return (f"TLS handshake failed: {why} (check ca=, cert= and key=, or verify=false for a "
                    f"self-signed device certificate)")
        except ConnectionRefusedError:
            return "connection refused"
        except TimeoutError:
            return f"connection or TLS handshake timed out after {self.url.timeout:g} s"
        except OSError as e:
            return f"cannot connect: {e.strerror or e}"
        writer.close()
        return "TLS connection failed"


class _SerialLine:
    """One open serial port shared by every transport on it (pymodbus locks the port exclusively)."""

    def __init__(self, settings: tuple[str, ...]) -> None:
        self.client: Any = None
        self.settings = settings
        self.users = 0
        self.active: PymodbusTransport | None = None  # who sent the last request: gets the frames

    def trace(self, sending: bool, data: bytes) -> bytes:
        return self.active._trace(sending, data) if self.active is not None else data


class SerialTransport(PymodbusTransport):
    """rtu:// and ascii://: a serial port; transports on one port share one pymodbus client."""

    def __init__(self, url: DeviceURL) -> None:
        super().__init__(url)
        self._line: _SerialLine | None = None
        self._opening: _SerialLine | None = None

    def _settings(self) -> tuple[str, ...]:
        line = self.url.line
        return (self.url.scheme, str(line.baudrate), str(line.bytesize), line.parity, str(line.stopbits))

    def _make_client(self) -> Any:
        line = self.url.line
        common = self._common()
        # one client serves every transport on the port: the line routes frames to the active one
        common["trace_packet"] = self._opening.trace if self._opening is not None else self._trace
        return AsyncModbusSerialClient(
            self.url.path or "", framer=FramerType.RTU if self.url.scheme == "rtu" else FramerType.ASCII,
            baudrate=line.baudrate, bytesize=line.bytesize, parity=line.parity, stopbits=line.stopbits, **common)

    async def connect(self) -> None:
        path = self.url.path or ""
        where = describe(self.url)
        if not path.startswith(("socket://", "rfc2217://", "loop://")) and not os.path.exists(path):
            raise Unreachable(f"{where}: no such serial device '{path}'")
        if self._line is not None:
            return
        bus = _bus(self.url)
        async with bus.opening:  # two transports connecting at once must not both open the port
            line = bus.line
            if line is not None and not line.client.connected:
                line.client.close()  # dropped (e.g. USB adapter unplugged): open it afresh
                bus.line = line = None
            if line is None:
                problem = self._probe()
                if problem is not None:
                    raise Unreachable(f"{where}: {problem}")
                line = self._opening = _SerialLine(self._settings())
                try:
                    await super().connect()
                finally:
                    self._opening = None
                line.client = self._client
                bus.line = line
            elif line.settings != self._settings():
                have = "{} baudrate={} bytesize={} parity={} stopbits={}".format(*line.settings)
                raise Unreachable(f"{where}: the port is already open here as {have}; devices on one line must "
                                  f"use the same framing and settings")
            line.users += 1
            self._line, self._client = line, line.client

    def _probe(self) -> str | None:
        """Open and configure the port as pymodbus will, then close it: why it cannot be used, or None.

        pymodbus swallows the reason, and when configuring fails after the port opened (a pty refusing
        7E1) its half-built transport keeps the port locked until garbage collection; our own probe
        closes it for certain and says what went wrong.
        """
        o = self.url.options
        port: Any = None
        try:
            line = self.url.line
            port = serial.serial_for_url(self.url.path, exclusive=True, baudrate=line.baudrate,
                                         bytesize=line.bytesize, parity=line.parity, stopbits=line.stopbits,
                                         timeout=self.url.timeout)
            port.timeout = 0  # what pymodbus sets next: it reconfigures the port
            port.write_timeout = 0
        except Exception as e:  # pyserial raises SerialException, termios.error, ValueError
            text = str(e.args[1]) if isinstance(e.args, tuple) and len(e.args) == 2 and e.args[0] == 22 else str(e)
            if text == "Invalid argument":
                settings = " ".join(f"{k}={o[k]}" for k in ("baudrate", "bytesize", "parity", "stopbits") if k in o)
                return f"the port rejects these line settings ({settings or 'defaults'}): Invalid argument"
            return f"cannot open the serial port: {text}"
        finally:
            if port is not None:
                port.close()
        return None

    async def _why_not(self) -> str:
        return self._probe() or "cannot open the serial port"

    def _claim(self, bus: _Bus) -> None:
        if self._line is not None:
            self._line.active = self

    async def close(self) -> None:
        if self._line is not None:
            await self._settle()
        line, self._line, self._client = self._line, None, None
        if line is None:
            return
        line.users -= 1
        if line.active is self:
            line.active = None
        if line.users <= 0:
            line.client.close()
            bus = _bus(self.url)
            if bus.line is line:
                bus.line = None


_CLASSES: dict[str, type[PymodbusTransport]] = {
    "tcp": TcpTransport, "tls": TlsTransport, "rtu+tcp": RtuOverTcpTransport,
    "rtu": SerialTransport, "ascii": SerialTransport,
}


def open_transport(url: DeviceURL | str) -> Transport:
    """The transport for a URL, chosen by scheme (not yet connected). A string goes through parse_url."""
    u = parse_url(url) if isinstance(url, str) else url
    return _CLASSES[u.scheme](u)
