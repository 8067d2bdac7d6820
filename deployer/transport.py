"""Transports: one small interface, chosen by URL scheme, over pymodbus's async clients.

tcp://HOST[:PORT]  tls://HOST[:PORT]?cert=&key=&ca=  rtu:///dev/X?baudrate=&parity=&bytesize=&stopbits=
ascii:///dev/X?...  rtu+tcp://HOST:PORT.  Options on all: timeout (s), retries.

A transport sends exactly one request per call and never retries by itself (pymodbus's own
retries are off): the executor retries, counts attempts and reports them.
"""

from __future__ import annotations

import abc
import asyncio
import difflib
import os
import ssl
import time
import urllib.parse
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

from pymodbus import FramerType
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient, AsyncModbusTlsClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException


class TransportError(Exception):
    """Base of everything a transport raises; the message is meant for the user."""


class BadURL(TransportError):
    """Malformed URL, unknown scheme or option (a usage error: exit 1)."""


class Unreachable(TransportError):
    """Could not connect (refused, no such serial device, TLS handshake failed)."""


class NoResponse(TransportError):
    """The device did not answer within the timeout (one attempt)."""


class ConnectionLost(TransportError):
    """The connection dropped; reconnect() may bring it back."""


class ExceptionResponse(TransportError):
    """The device answered with a Modbus exception response."""

    NAMES: ClassVar[dict[int, str]] = {
        1: "illegal function",
        2: "illegal data address",
        3: "illegal data value",
        4: "server device failure",
        5: "acknowledge",
        6: "server device busy",
        8: "memory parity error",
        10: "gateway path unavailable",
        11: "gateway target device failed to respond",
    }

    def __init__(self, function: int, code: int) -> None:
        self.function = function
        self.code = code
        super().__init__(f"exception {code:02d} ({self.NAMES.get(code, 'unknown')})")


@dataclass(frozen=True)
class DeviceURL:
    scheme: str  # tcp | tls | rtu | ascii | rtu+tcp
    host: str | None = None
    port: int | None = None
    path: str | None = None  # serial device
    options: dict[str, str] = field(default_factory=dict)
    timeout: float = 1.0
    retries: int = 2

    @property
    def bus(self) -> str:
        """Key of the half-duplex bus this device sits on; devices on one bus never talk at once."""
        if self.scheme in ("rtu", "ascii"):
            return f"serial:{self.path}"
        if self.scheme == "rtu+tcp":
            return f"gateway:{self.host}:{self.port}"
        return f"{self.scheme}:{self.host}:{self.port}"

    @property
    def shared_bus(self) -> bool:
        return self.scheme in ("rtu", "ascii", "rtu+tcp")


class Transport(abc.ABC):
    """One connection to one URL; any unit id on it. One request in flight at a time."""

    url: DeviceURL

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

    async def __aenter__(self) -> Transport:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


# ---- URLs ----------------------------------------------------------------------------------

DEFAULT_PORTS = {"tcp": 502, "tls": 802}
_COMMON = {"timeout", "retries"}
_OPTIONS: dict[str, set[str]] = {
    "tcp": _COMMON,
    "tls": _COMMON | {"cert", "key", "ca", "verify", "server_hostname"},
    "rtu": _COMMON | {"baudrate", "parity", "bytesize", "stopbits"},
    "ascii": _COMMON | {"baudrate", "parity", "bytesize", "stopbits"},
    "rtu+tcp": _COMMON,
}


def parse_url(text: str, *, timeout: float | None = None, retries: int | None = None) -> DeviceURL:
    """Parse a device URL (DESIGN.md, "Device URLs"). Raises BadURL with a precise message.

    ``timeout`` / ``retries`` apply where the URL itself does not set them.
    """
    raw = text.strip()
    if "://" not in raw:
        raise BadURL(f"'{text}' is not a device URL (expected e.g. tcp://HOST:502 or rtu:///dev/ttyUSB0)")
    u = urllib.parse.urlsplit(raw)
    scheme = u.scheme.lower()
    if scheme not in _OPTIONS:
        hint = difflib.get_close_matches(scheme, list(_OPTIONS), n=1)
        raise BadURL(f"unknown scheme '{scheme}' in '{text}'" + (f"; did you mean '{hint[0]}'?" if hint else
                                                                  f" (known: {', '.join(_OPTIONS)})"))
    options: dict[str, str] = {}
    for key, values in urllib.parse.parse_qs(u.query, keep_blank_values=True).items():
        if key not in _OPTIONS[scheme]:
            hint = difflib.get_close_matches(key, sorted(_OPTIONS[scheme]), n=1)
            raise BadURL(f"unknown option '{key}' in {scheme} URL" + (f"; did you mean '{hint[0]}'?" if hint else
                         f" (known: {', '.join(sorted(_OPTIONS[scheme]))})"))
        options[key] = values[-1]

    def number(key: str, kind: type[float] | type[int], lo: float, hi: float) -> Any:
        try:
            v = kind(options[key])
        except ValueError:
            raise BadURL(f"option {key}={options[key]!r} is not a{'n integer' if kind is int else ' number'}") from None
        if not lo <= v <= hi:
            raise BadURL(f"option {key}={options[key]} is out of range ({lo:g}..{hi:g})")
        return v

    to = number("timeout", float, 0.001, 600) if "timeout" in options else (timeout if timeout is not None else 1.0)
    rt = number("retries", int, 0, 20) if "retries" in options else (retries if retries is not None else 2)
    if scheme in ("rtu", "ascii"):
        path = urllib.parse.unquote(u.netloc + u.path)
        if not path:
            raise BadURL(f"{scheme} URL needs a serial device path: {scheme}:///dev/ttyUSB0")
        if "baudrate" in options:
            number("baudrate", int, 50, 4_000_000)
        if "bytesize" in options:
            number("bytesize", int, 5, 8)
        if "stopbits" in options:
            number("stopbits", int, 1, 2)
        if "parity" in options:
            options["parity"] = options["parity"].upper()
            if options["parity"] not in ("N", "E", "O"):
                raise BadURL(f"option parity={options['parity']} must be N, E or O")
        return DeviceURL(scheme, path=path, options=options, timeout=to, retries=rt)
    try:
        host, port = u.hostname, u.port
    except ValueError:
        raise BadURL(f"bad port in '{text}'") from None
    if not host:
        raise BadURL(f"{scheme} URL needs a host: {scheme}://HOST:PORT")
    if u.path not in ("", "/"):
        raise BadURL(f"unexpected path '{u.path}' in {scheme} URL")
    if port is None:
        if scheme == "rtu+tcp":
            raise BadURL("rtu+tcp URL needs a port: rtu+tcp://HOST:PORT (the gateway's TCP port)")
        port = DEFAULT_PORTS[scheme]
    if scheme == "tls":
        if "verify" in options and options["verify"].lower() not in ("true", "false", "1", "0", "yes", "no"):
            raise BadURL(f"option verify={options['verify']} must be true or false")
        for key in ("cert", "key", "ca"):
            if key in options and not os.path.isfile(options[key]):
                raise BadURL(f"tls option {key}: no such file '{options[key]}'")
        if ("cert" in options) != ("key" in options):
            raise BadURL("tls options cert and key go together (the client certificate and its key)")
    return DeviceURL(scheme, host=host, port=port, options=options, timeout=to, retries=rt)


def describe(url: DeviceURL) -> str:
    """The URL as text, without file paths of keys (for reports and logs)."""
    if url.scheme in ("rtu", "ascii"):
        opts = {k: v for k, v in url.options.items() if k not in _COMMON}
        q = ("?" + "&".join(f"{k}={v}" for k, v in sorted(opts.items()))) if opts else ""
        return f"{url.scheme}://{url.path}{q}"
    host = f"[{url.host}]" if url.host and ":" in url.host else url.host
    return f"{url.scheme}://{host}:{url.port}"


# ---- buses ---------------------------------------------------------------------------------

_LOCKS: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, dict[str, asyncio.Lock]] = weakref.WeakKeyDictionary()


def bus_lock(url: DeviceURL) -> asyncio.Lock:
    """The lock of the half-duplex bus ``url`` sits on (one per serial path or gateway, per loop).

    Transports hold it around each request, so two devices on one RS-485 line never talk at
    once; the lock is not held between requests (fleets keep one device per bus anyway).
    """
    loop = asyncio.get_running_loop()
    locks = _LOCKS.setdefault(loop, {})
    return locks.setdefault(url.bus, asyncio.Lock())


# ---- the pymodbus-backed transport -----------------------------------------------------------


def _char_time(url: DeviceURL) -> float:
    """Seconds per character on a serial line: start + data + parity + stop bits."""
    baud = int(url.options.get("baudrate", 19200))
    bits = 1 + int(url.options.get("bytesize", 8)) + (0 if url.options.get("parity", "N") == "N" else 1) + int(
        url.options.get("stopbits", 1))
    return bits / baud


class PymodbusTransport(Transport):
    """All schemes on pymodbus's async clients, with pymodbus's own retries off."""

    def __init__(self, url: DeviceURL) -> None:
        self.url = url
        self.requests_sent = 0
        self.on_frame: Callable[[str, bytes], None] | None = None
        self._client: Any = None
        self._shared = url.shared_bus
        # Modbus RTU: at least 3.5 character times of silence between frames (1.75 ms above 19200 baud)
        self._gap = (max(3.5 * _char_time(url), 0.00175) if url.scheme in ("rtu", "ascii", "rtu+tcp") else 0.0)
        self._last = 0.0

    def _trace(self, sending: bool, data: bytes) -> bytes:
        if self.on_frame is not None:
            self.on_frame("send" if sending else "recv", data)
        return data

    def _make_client(self) -> Any:
        u = self.url
        host, port, path = u.host or "", u.port or 0, u.path or ""
        common: dict[str, Any] = {"timeout": u.timeout, "retries": 0, "trace_packet": self._trace,
                                  "reconnect_delay": 0, "reconnect_delay_max": 0}
        if u.scheme == "tcp":
            return AsyncModbusTcpClient(host, port=port, framer=FramerType.SOCKET, **common)
        if u.scheme == "rtu+tcp":
            return AsyncModbusTcpClient(host, port=port, framer=FramerType.RTU, **common)
        if u.scheme == "tls":
            return AsyncModbusTlsClient(host, port=port, sslctx=self._ssl_context(), **common)
        framer = FramerType.RTU if u.scheme == "rtu" else FramerType.ASCII
        o = u.options
        return AsyncModbusSerialClient(
            path, framer=framer, baudrate=int(o.get("baudrate", 19200)), bytesize=int(o.get("bytesize", 8)),
            parity=o.get("parity", "N"), stopbits=int(o.get("stopbits", 1)), **common)

    def _ssl_context(self) -> ssl.SSLContext:
        o = self.url.options
        verify = o.get("verify", "true").lower() in ("true", "1", "yes")
        ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=o.get("ca"))
        if not verify:
            ctx.check_hostname = False
            ctx.verify_mode = ssl.CERT_NONE
        if "cert" in o:
            ctx.load_cert_chain(o["cert"], o["key"])
        return ctx

    async def connect(self) -> None:
        where = describe(self.url)
        if self.url.scheme in ("rtu", "ascii") and self.url.path and not self.url.path.startswith(
                ("socket://", "rfc2217://", "loop://")) and not os.path.exists(self.url.path):
            raise Unreachable(f"{where}: no such serial device '{self.url.path}'")
        try:
            self._client = self._make_client()
        except ssl.SSLError as e:
            raise Unreachable(f"{where}: TLS setup failed: {e.reason or e}") from None
        except (OSError, ValueError) as e:
            raise Unreachable(f"{where}: {e}") from None
        try:
            ok = await self._client.connect()
        except ssl.SSLError as e:
            raise Unreachable(f"{where}: TLS handshake failed: {e.reason or e}") from None
        except Exception as e:  # pyserial and asyncio raise a zoo of errors for a bad port
            raise Unreachable(f"{where}: cannot connect: {e}") from None
        if not ok or not self._client.connected:
            self._client.close()
            self._client = None
            what = "connection refused or timed out"
            if self.url.scheme in ("rtu", "ascii"):
                what = "cannot open the serial port"
            elif self.url.scheme == "tls" and await self._tcp_reachable():
                what = ("TLS handshake failed (check ca=, cert= and key=, or verify=false for a self-signed "
                        "device certificate)")
            raise Unreachable(f"{where}: {what}")

    async def _tcp_reachable(self) -> bool:
        """Whether a plain TCP connection opens: tells a refused port from a failed TLS handshake."""
        try:
            _, writer = await asyncio.wait_for(asyncio.open_connection(self.url.host, self.url.port),
                                               self.url.timeout)
        except (TimeoutError, OSError):
            return False
        writer.close()
        return True

    async def reconnect(self) -> None:
        await self.close()
        await self.connect()

    async def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None

    async def _run(self, function: int, call: Callable[[Any], Any], *, no_answer: bool = False) -> Any:
        if self._client is None or not self._client.connected:
            raise ConnectionLost("not connected")
        lock = bus_lock(self.url) if self._shared else None
        if lock is not None:
            await lock.acquire()
        try:
            if self._gap:
                wait = self._last + self._gap - time.monotonic()
                if wait > 0:
                    await asyncio.sleep(wait)
            self.requests_sent += 1
            try:
                result = await call(self._client)
            except ConnectionException as e:
                raise ConnectionLost(str(e)) from None
            except ModbusIOException:
                if self._client is None or not self._client.connected:
                    raise ConnectionLost("the connection closed") from None
                raise NoResponse(f"no answer within {self.url.timeout:g} s") from None
            except ModbusException as e:
                raise NoResponse(str(e)) from None
            finally:
                self._last = time.monotonic()
            if no_answer:
                return None
            if result.isError():
                raise ExceptionResponse(function, int(getattr(result, "exception_code", 0)))
            return result
        finally:
            if lock is not None:
                lock.release()

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


def open_transport(url: DeviceURL | str) -> Transport:
    """The transport for a URL (not yet connected)."""
    return PymodbusTransport(parse_url(url) if isinstance(url, str) else url)
