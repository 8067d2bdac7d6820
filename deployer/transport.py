"""Transports: one small interface, chosen by URL scheme, over pymodbus's async clients.

tcp://HOST[:PORT]  tls://HOST[:PORT]?cert=&key=&ca=  rtu:///dev/X?baudrate=&parity=&bytesize=&stopbits=
ascii:///dev/X?...  rtu+tcp://HOST:PORT.  Options on all: timeout (s), retries.

A transport sends exactly one request per call and never retries by itself (pymodbus's own
retries are off): the executor retries, counts attempts and reports them.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import ClassVar


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
