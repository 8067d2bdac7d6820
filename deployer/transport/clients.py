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
import contextlib
import errno
import functools
import itertools
import os
import re
import ssl
import struct
import time
import weakref
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass
from typing import Any, Literal

from pymodbus import FramerType
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient, AsyncModbusTlsClient
from pymodbus.exceptions import ConnectionException, ModbusException
from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU
from pymodbus.pdu.mei_message import ReadDeviceInformationResponse

from ..errors import BadAnswer, ConnectionLost, ExceptionResponse, NoResponse, TransportError, Unreachable

# URLs and errors live apart from pymodbus (commands that only parse URLs stay light); re-exported here
from .urls import DEFAULT_PORTS as DEFAULT_PORTS
from .urls import SERIAL_DEFAULTS as SERIAL_DEFAULTS
from .urls import DeviceURL as DeviceURL
from .urls import LineSettings as LineSettings
from .urls import describe as describe
from .urls import no_answer_hint as no_answer_hint
from .urls import pacing as pacing
from .urls import parse_url as parse_url
from .urls import recorded as recorded
from .urls import verify as _verify
from .urls import windows_port

_BACKOFF = 0.05  # seconds before a connection's second attempt, doubling, unless its caller gives the session's


class Transport(abc.ABC):
    """One connection to one URL; any unit id on it. One request in flight at a time."""

    url: DeviceURL
    requests_sent: int  # requests put on the wire (every attempt counts)
    on_frame: Callable[[str, bytes], None] | None  # ("send" | "recv", raw bytes); recv may come in chunks
    late_answers: list[float]  # seconds after their request of answers that came after the timeout
    # connections that failed though a test connection right after got through, before the one made (each tried
    # again, up to the URL's retries, ``backoff`` seconds after the first, doubling: as the session's requests)
    connect_failures: int = 0
    backoff: float = _BACKOFF
    # answers carry nothing that names their request (RTU, ASCII, rtu+tcp: no transaction id): an answer that
    # came late can pass for the answer to the next request of its shape (deployer.execute.trust)
    shifts: bool = False
    desyncs: int = 0  # times the line went out of step on this transport's requests (shifts only)
    answered_in_sync: bool = True  # the last answer was the first thing after a request sent in_sync()

    def in_sync(self) -> contextlib.AbstractContextManager[None]:
        """Requests sent inside wait until the line has been silent long enough that nothing sent earlier
        is still answered, and ``answered_in_sync`` then says whether their answer came first."""
        return contextlib.nullcontext()

    def silence(self) -> tuple[float, float]:
        """Seconds: the longest silence in_sync() waited for, and the longest the device stayed silent after a
        request (from the first request sent since it last answered)."""
        return 0.0, 0.0

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


# ---- answers: what comes back, matched to the one request in flight ----------------------------


READS = (1, 2, 3, 4)  # function codes whose answer carries a byte count
STRAY_QUIET = 0.1  # seconds of silence that end the settling after bytes nobody asked for
# how much longer than the longest wait seen the line must stay silent before a request whose answer must be its
# own (a confirming read) or the retry of an unanswered one: an answer still on its way would have come meanwhile
SILENCE_MARGIN = 1.5


@dataclass(frozen=True)
class _Expect:
    """The request in flight, as far as its answer must echo it."""

    unit: int
    function: int
    address: int
    count: int  # registers or bits read (FC01-04) or written (FC15, FC16); 1 for FC05, FC06
    value: int | None = None  # FC05, FC06: the value an answer echoes
    tid: int = 0  # Modbus/TCP transaction id (MBAP framing only)


_NOBODY = _Expect(unit=-1, function=-1, address=0, count=0)  # frames nobody asked for are only counted


async def _answer(future: asyncio.Future[Any], timeout: float) -> Any:
    """The answer of the request in flight (the receiver sets ``future``), or TimeoutError after ``timeout``.

    The request's task awaits the answer's own future, so the answer wakes it in one turn of the event loop
    (a waiter between them took two, and with a few hundred devices in flight each turn is milliseconds of
    their work: a fleet's requests took twice their devices' answer time). A timer gives up on it. When the run
    is interrupted the future is cancelled with the task: the receiver drops an answer that comes after."""
    if not future.done():
        timer = asyncio.get_running_loop().call_later(timeout, _too_late, future)
        try:
            return await future
        finally:
            timer.cancel()
            if future.done() and not future.cancelled():
                future.exception()  # interrupted just as it timed out: its TimeoutError is seen, never logged
    return future.result()


def _wake_up(future: asyncio.Future[None]) -> None:
    if not future.done():
        future.set_result(None)


def _too_late(future: asyncio.Future[Any]) -> None:
    if not future.done():
        future.set_exception(TimeoutError())


def _words(pdu: bytes) -> list[int]:
    """The registers of a read's answer PDU (function, byte count, big-endian words)."""
    n, odd = divmod(len(pdu) - 2, 2)
    if n < 0 or odd:  # never from a checked answer; as the word-by-word reading would have it
        return [int.from_bytes(pdu[i : i + 2], "big") for i in range(2, len(pdu), 2)]
    return list(struct.unpack_from(f">{n}H", pdu, 2))


class _Receiver:
    """Reads one connection's bytes itself, instead of pymodbus's transaction manager.

    pymodbus 3.16 hands the next complete frame to whatever request waits, so on RTU and ASCII
    (no transaction id) a late answer to a timed-out request became the answer to the next one,
    and it drops frames from another unit without a word. Here every frame is matched to the
    request in flight: unit, function, byte count, echoed address/count/value; Modbus/TCP also by
    transaction id. After a request went unanswered, or bytes came that nobody asked for, the line
    is dirty: the next request first waits until nothing has arrived for a whole timeout, or longer when
    the device was seen to take longer (``settle``), and discards it all, except a late answer to that
    very request, which a retry of the same request takes instead of sending it again.

    An answer later than that settling still looks like the answer to the next request of its shape. So
    the receiver also says how far an answer can be told apart: ``desyncs`` counts what put the line out of
    step (unanswered requests, answers that were wrong, bytes nobody asked for), ``longest_wait`` is the
    longest the device was seen to stay silent after a request, and a request sent ``synced`` (after the
    line was silent for ``resync_wait``) has an answer ``in_sync`` when it was the first thing that came
    after it. deployer.execute.trust decides what to believe from that.
    """

    def __init__(self, framing: str, trace: Callable[[bool, bytes], bytes]) -> None:
        self.framing = framing  # "rtu" | "ascii" | "mbap"
        self.trace = trace
        self.buf = bytearray()
        self.last_rx = 0.0  # monotonic time of the last byte received
        self.expect: _Expect | None = None
        self.future: asyncio.Future[bytes | TransportError] | None = None
        self.dirty_since: float | None = None  # line must settle before the next request
        self.long_settle = False  # a request went unanswered: settle for a whole timeout, else briefly
        self.late_for: _Expect | None = None  # the request that went unanswered
        self.late: bytes | TransportError | None = None  # its answer, when it came during the settling
        self.late_after = 0.0  # seconds after its request that the late answer came
        self.late_in_sync = False  # the late answer is the first thing that came after a synced request
        self.sent_at = 0.0
        self.desyncs = 0  # requests unanswered, answers wrong, stray bytes drained (serial framings)
        self.waiting_since: float | None = None  # last request sent since bytes last came (None: none since)
        self.longest_wait = 0.0  # longest silence from a request to the next bytes (at least the device's delay)
        self.longest_silence = 0.0  # the same from the first request since bytes came (at most its delay)
        self.silent_since: float | None = None  # first request sent since bytes last came
        self.synced = False  # the request in flight was sent after the line had been silent for resync_wait
        self.crossed = False  # something other than its answer came since the request in flight was sent
        self.in_sync = False  # the last answer taken was the first thing that came after a synced request
        self.owed = 0  # answers still to come: requests sent less frames received (serial framings)
        self._wake: asyncio.Future[None] | None = None  # a settling's pause, ended early by a frame

    # -- called by pymodbus's protocol for every chunk received (replaces TransactionManager.callback_data)

    def feed(self, data: bytes, addr: object = None) -> int:
        chunk = bytes(data)
        now = self.last_rx = time.monotonic()
        if self.waiting_since is not None:  # the first bytes since a request: how long the device stayed silent
            self.longest_wait = max(self.longest_wait, now - self.waiting_since)
            self.longest_silence = max(self.longest_silence, now - (self.silent_since or self.waiting_since))
            self.waiting_since = self.silent_since = None
        self.trace(False, chunk)
        self.buf += chunk
        while self.buf:
            target = self.expect or self.late_for
            if target is None:
                if self.framing == "mbap":
                    self.buf.clear()
                    break
                self.dirty_since = self.dirty_since or self.last_rx  # nobody asked: drain before sending
                self.crossed = True
            got = self._frame(target or _NOBODY)
            if got is None:
                break  # wait for more bytes
            self.owed = max(0, self.owed - 1)  # a frame came: one answer less on its way
            if self._wake is not None and not self._wake.done():
                self._wake.set_result(None)  # a settling waits for less now
            if target is None:
                continue
            if self.expect is not None:
                self._answer(got)
            elif isinstance(got, (bytes, ExceptionResponse)):
                self._keep_late(got)  # the timed-out request's answer
            else:  # a frame that does not answer the timed-out request is discarded with the rest
                self.crossed = True
        return len(data)

    def _keep_late(self, got: bytes | ExceptionResponse) -> None:
        self.late, self.late_after = got, self.last_rx - self.sent_at
        self.late_in_sync = self.synced and not self.crossed
        self.crossed = True  # anything after it is not the first to come

    def _answer(self, got: bytes | TransportError) -> None:
        if self.future is not None and self.future.done():
            # the timeout fired in this same turn of the loop, before the request's task saw it: the
            # answer is kept as the late answer of the request unanswered() is about to give up on
            if isinstance(got, (bytes, ExceptionResponse)):
                self._keep_late(got)
            return
        if self.future is not None:
            self.future.set_result(got)
        self.expect = None
        self.in_sync = self.synced and not self.crossed
        self.crossed = True
        if isinstance(got, BadAnswer) and self.framing != "mbap":
            self.dirty_since = self.last_rx  # what is left of a garbled frame may still be coming
            self.desyncs += 1

    def lost(self, exc: Exception | None) -> None:
        if self.future is not None and not self.future.done():
            self.future.set_result(ConnectionLost(f"the connection closed{f': {exc}' if exc else ''}"))

    # -- framing: one frame from the start of buf, checked against the request; None: incomplete

    def _frame(self, want: _Expect) -> bytes | TransportError | None:
        if self.framing == "mbap":
            return self._mbap(want)
        if self.framing == "ascii":
            start = self.buf.find(b":")
            if start < 0:
                self.buf.clear()
                return None
            del self.buf[:start]
            end = self.buf.find(b"\r\n")
            if end < 0:
                return None
            text = bytes(self.buf[1:end])
            del self.buf[: end + 2]
            try:
                raw = bytes.fromhex(text.decode("ascii"))
            except ValueError:
                return BadAnswer("a garbled answer (not hexadecimal ASCII)")
            if len(raw) < 3 or (-sum(raw[:-1])) & 0xFF != raw[-1]:
                return BadAnswer("a garbled answer (LRC error)")
            return self._check(want, raw[0], raw[1:-1])
        # RTU: the frame's length follows from its function code
        if len(self.buf) < 3:
            return None
        fc = self.buf[1]
        size = (
            5
            if fc & 0x80
            else 5 + self.buf[2]
            if fc in READS
            else 8
            if fc in (5, 6, 15, 16)
            else ReadDeviceInformationResponse.calculateRtuFrameSize(bytes(self.buf))
            if fc == 43
            else 0
        )
        if size == 0:
            self.buf.clear()
            return BadAnswer(f"an answer with function code {fc} to a function {want.function} request")
        if len(self.buf) < size:
            return None
        frame = bytes(self.buf[:size])
        del self.buf[:size]
        if FramerRTU.compute_CRC(frame[:-2]) != int.from_bytes(frame[-2:], "big"):
            return BadAnswer("a garbled answer (CRC error)")
        return self._check(want, frame[0], frame[1:-2])

    def _mbap(self, want: _Expect) -> bytes | TransportError | None:
        while len(self.buf) >= 7:
            size = 6 + int.from_bytes(self.buf[4:6], "big")
            if len(self.buf) < size:
                return None
            frame = bytes(self.buf[:size])
            del self.buf[:size]
            if int.from_bytes(frame[0:2], "big") != want.tid:
                continue  # a late answer to an earlier transaction: not this request's
            if frame[2:4] != b"\0\0" or size < 8:
                return BadAnswer("a malformed Modbus/TCP answer (protocol id or length)")
            return self._check(want, frame[6], frame[7:])
        return None

    def _check(self, want: _Expect, unit: int, pdu: bytes) -> bytes | TransportError:
        """The answer's PDU (function code first), or what is wrong with it."""
        if unit != want.unit:
            return BadAnswer(f"an answer from unit {unit} to a request for unit {want.unit}")
        fc = pdu[0]
        if fc == want.function | 0x80 and len(pdu) == 2:
            return ExceptionResponse(want.function, pdu[1])
        if fc != want.function:
            return BadAnswer(f"an answer with function code {fc} to a function {want.function} request")
        if want.function == 43:  # read device identification: pymodbus parses the objects
            if len(pdu) < 7 or pdu[1] != 0x0E:
                return BadAnswer("a malformed device identification answer")
            return pdu
        if want.function in READS:
            bits = want.function in (1, 2)
            size = (want.count + 7) // 8 if bits else 2 * want.count
            if len(pdu) < 2 or pdu[1] != size or len(pdu) != 2 + size:
                got = pdu[1] if len(pdu) > 1 else 0
                what = "bits" if bits else "registers"
                one = ("coil" if want.function == 1 else "input") if bits else "register"
                return BadAnswer(
                    f"an answer with {got} bytes of {what} to a read of {want.count} "
                    f"{one}{'s' if want.count != 1 else ''} ({size} bytes)"
                )
            return pdu
        echo_a = int.from_bytes(pdu[1:3], "big") if len(pdu) == 5 else -1
        echo_b = int.from_bytes(pdu[3:5], "big") if len(pdu) == 5 else -1
        b = want.count if want.function in (15, 16) else want.value
        if echo_a != want.address or echo_b != b:
            what = "count" if want.function in (15, 16) else "value"
            return BadAnswer(
                f"an answer echoing address {echo_a}, {what} {echo_b} to a write of address {want.address}, {what} {b}"
            )
        return pdu

    # -- the request's side

    def patience(self, timeout: float) -> float:
        """Silence that ends the settling after an unanswered request: a whole timeout, or longer when the
        device was seen to stay silent longer (its answer is then caught by the retry, not by the next request)."""
        return max(timeout, SILENCE_MARGIN * self.longest_wait)

    def resync_wait(self, timeout: float) -> float:
        """Silence before a request whose answer must be its own, once every request sent had its answer:
        twice the timeout, or longer when the device was seen to stay silent longer. While answers are
        still owed (a slow device works through requests that timed out), until they came, or until the
        line was silent for four times the timeout, or 1.5 times the longest silence seen from a request to
        the next bytes: an answer that does not come then was lost (a request the device never heard)."""
        quiet = max(2 * timeout, SILENCE_MARGIN * self.longest_wait)
        if self.owed:
            quiet = max(quiet, 4 * timeout, SILENCE_MARGIN * self.longest_silence)
        return quiet

    def _quiet(self, timeout: float, resync: bool) -> float:
        if resync:
            return self.resync_wait(timeout)
        if self.long_settle and self.late is None:
            return self.patience(timeout)
        # bytes nobody asked for, or the late answer came: what else comes is drained briefly (a session that
        # saw a request unanswered confirms its values after a resync anyway: deployer.execute.trust)
        return min(timeout, STRAY_QUIET)

    async def _pause(self, seconds: float) -> None:
        """Sleep ``seconds``, or until a frame comes (the answer waited for, the last one owed)."""
        loop = asyncio.get_running_loop()
        self._wake = woken = loop.create_future()
        timer = loop.call_later(seconds, _wake_up, woken)
        try:
            await woken
        finally:
            timer.cancel()
            self._wake = None

    async def settle(self, timeout: float, resync: _Expect | None = None) -> None:
        """Wait until the line has been silent since it went dirty, discarding what came: for ``patience``
        after an unanswered request (a slow device's answer may still come), else for STRAY_QUIET (a device
        answering twice, noise: the line is busy now, not slow). ``resync``: the request about to go out,
        whose answer must be its own: for ``resync_wait`` since the last request or bytes, dirty or not,
        or until the late answer of its own timed-out copy came."""
        if resync is None and self.dirty_since is None:
            return
        if self.dirty_since is not None and not self.long_settle:
            self.desyncs += 1  # bytes nobody asked for came: someone's answer, but whose
        while (
            left := self._quiet(timeout, resync is not None)
            - (time.monotonic() - max(self.last_rx, self.dirty_since or 0.0, self.sent_at))
        ) > 0:
            if resync is not None and self.late is not None and self.late_for == resync:
                self.long_settle = False  # taken by this request instead of sending it; drained before the next
                return
            await self._pause(left)
        if resync is not None:
            self.owed = 0  # what did not come in that silence is taken as lost
        self.dirty_since, self.long_settle = None, False
        self.buf.clear()

    def start(self, want: _Expect | None, synced: bool = False) -> None:
        """A request goes out now; ``want`` None: nobody answers (broadcast). ``synced``: after ``settle``
        with ``resync``."""
        self.buf.clear()
        self.late_for = self.late = None
        self.expect = want
        self.sent_at = now = time.monotonic()
        self.synced, self.crossed, self.in_sync = synced, False, False
        if want is not None:
            self.owed += 1
            self.waiting_since = now
            self.silent_since = self.silent_since or now
        self.future = asyncio.get_running_loop().create_future() if want is not None else None

    def take_late(self, want: _Expect) -> tuple[bytes | TransportError, float, bool] | None:
        """A late answer to ``want`` itself that came while the line settled (the retry need not be sent):
        the answer, seconds after its request, and whether it was the first thing after a synced request."""
        if self.late is None or self.late_for != want:
            return None
        late, self.late = self.late, None
        self.late_for = None
        return late, self.late_after, self.late_in_sync

    def unanswered(self) -> None:
        """The request in flight timed out: its answer may still come."""
        self.late_for, self.expect = self.expect, None
        if self.framing == "mbap":
            self.late_for = None  # a transaction id tells a late answer apart: nothing to wait for
        else:
            self.dirty_since, self.long_settle = time.monotonic(), True
            self.desyncs += 1


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


def _receiver(client: Any, url: DeviceURL) -> _Receiver:
    """Take over reading a pymodbus client's answers (its transaction manager only sends, from now on)."""
    ctx = client.ctx
    rx = _Receiver(
        "mbap" if url.scheme in ("tcp", "tls") else "ascii" if url.scheme == "ascii" else "rtu", ctx.trace_packet
    )
    ctx.callback_data = rx.feed
    gone = ctx.callback_disconnected

    def disconnected(exc: Exception | None) -> None:
        rx.lost(exc)
        gone(exc)

    ctx.callback_disconnected = disconnected
    return rx


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
        self._rx: _Receiver | None = None  # reads the answers (see _Receiver)
        self.late_answers: list[float] = []  # seconds after the request, of answers taken late
        self._after_connect, self._between = pacing(url)  # pauses some devices need (URL options, profile)
        self.shifts = self._shared  # RTU, ASCII, rtu+tcp: no transaction id
        self.desyncs = 0
        self.answered_in_sync = True
        self._resync = False  # in in_sync(): requests wait for the resync silence
        self._resynced = 0.0  # the longest resync silence waited for
        self._slowest = 0.0  # the receiver's longest_silence, kept past a close

    @contextlib.contextmanager
    def in_sync(self) -> Iterator[None]:
        self._resync, was = True, self._resync
        try:
            yield
        finally:
            self._resync = was

    def silence(self) -> tuple[float, float]:
        return self._resynced, max(self._slowest, *self.late_answers, 0.0)

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
        return {
            "timeout": self.url.timeout,
            "retries": 0,
            "trace_packet": self._trace,
            "reconnect_delay": 0,
            "reconnect_delay_max": 0,
        }

    async def _why_not(self) -> str | None:
        """Why connect() returned False (pymodbus swallows the reason): probe once more ourselves. None: the
        probe got through, the failure has passed."""
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
        for attempt in itertools.count():
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
            if ok and client.connected:
                break
            client.close()
            why = await self._why_not()
            if why is not None:
                raise Unreachable(f"{where}: {why}")
            if attempt >= self.url.retries:
                times = f" {attempt + 1} times" if attempt else ""
                raise Unreachable(
                    f"{where}: connection failed{times}, though a test connection right after got through"
                )
            # the device took our probe's connection: the failure passed (a gateway's connection slots full a
            # moment, this process too busy to see its connection made within the timeout); tried again, as a
            # request that timed out is
            self.connect_failures += 1
            await asyncio.sleep(self.backoff * 2**attempt)
        if _connected_to_itself(client):
            # on loopback, a connect to a port nothing listens on can meet itself (TCP simultaneous open)
            # when the kernel hands out that very port as the local one: no device, refused as such
            client.close()
            raise Unreachable(f"{where}: connection refused")
        self._client = client
        self._rx = _receiver(client, self.url)
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
            self._client = self._rx = None

    # -- requests

    async def _run(self, want: _Expect, call: Callable[[Any], Awaitable[Any]]) -> bytes | None:
        """Send one request and wait for its answer's PDU (function code first); unit 0: no answer."""
        if self._client is None or not self._client.connected or self._rx is None:
            raise ConnectionLost(f"{describe(self.url)}: not connected")
        rx = self._rx
        no_answer = want.unit == 0 and want.function not in READS
        resync = self._resync and self.shifts and not no_answer
        # a shared line, or a device that needs pauses: requests of every device on its bus take turns
        bus = _bus(self.url) if self._paced() else None
        if bus is not None:
            await bus.lock.acquire()
        desyncs = rx.desyncs
        try:
            if bus is not None:
                self._claim(bus)
            # an unanswered request or stray bytes: let the line fall silent for a whole timeout first
            await rx.settle(self.url.timeout)
            late = rx.take_late(want)
            if late is None and resync:  # this request's answer must be its own: no other may be on its way
                self._resynced = max(self._resynced, rx.resync_wait(self.url.timeout))
                await rx.settle(self.url.timeout, want)
                late = rx.take_late(want)
            if late is not None:  # the timed-out copy of this very request was answered meanwhile
                self.late_answers.append(late[1])
                self.answered_in_sync = late[2]
                return self._result(want, late[0])
            self.answered_in_sync = False
            wait = max(self._quiet_until, bus.quiet_until if bus is not None else 0.0) - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
                if resync:  # bytes may have come during the pause: silent long enough again
                    await rx.settle(self.url.timeout, want)
            rx.start(None if no_answer else want, resync)
            self.requests_sent += 1
            try:
                await call(self._client)  # pymodbus builds the frame and writes it; the answer comes to rx
                if rx.expect is not None and rx.framing == "mbap":
                    rx.expect = _Expect(
                        want.unit, want.function, want.address, want.count, want.value, self._client.ctx.next_tid
                    )  # the id pymodbus just used
                if no_answer:
                    return None
                assert rx.future is not None
                try:
                    got = await _answer(rx.future, self.url.timeout)
                except TimeoutError:
                    rx.unanswered()
                    if self._client is None or not self._client.connected:
                        raise self._lost("the connection closed") from None
                    raise NoResponse(f"no answer within {self.url.timeout:g} s") from None
            except ConnectionException as e:
                raise self._lost(str(e)) from None
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
            if isinstance(got, ConnectionLost):
                raise self._lost(str(got))
            self.answered_in_sync = rx.in_sync
            return self._result(want, got)
        finally:
            self.desyncs += rx.desyncs - desyncs
            self._slowest = max(self._slowest, rx.longest_silence)
            if bus is not None:
                bus.lock.release()

    def _result(self, want: _Expect, got: bytes | TransportError) -> bytes:
        self._answered = True
        if isinstance(got, TransportError):
            raise got
        return got

    def _claim(self, bus: _Bus) -> None:
        """Called under the bus lock before a request (the shared serial line routes its frames here)."""

    async def read_holding_registers(self, address: int, count: int, unit: int) -> list[int]:
        pdu = await self._run(
            _Expect(unit, 3, address, count),
            lambda c: c.read_holding_registers(address, count=count, device_id=unit, no_response_expected=True),
        )
        assert pdu is not None
        return _words(pdu)

    async def write_registers(self, address: int, values: list[int], unit: int) -> None:
        await self._run(
            _Expect(unit, 16, address, len(values)),
            lambda c: c.write_registers(address, values, device_id=unit, no_response_expected=True),
        )

    async def write_register(self, address: int, value: int, unit: int) -> None:
        await self._run(
            _Expect(unit, 6, address, 1, value),
            lambda c: c.write_register(address, value, device_id=unit, no_response_expected=True),
        )

    async def read(self, function: int, address: int, count: int, unit: int) -> list[int]:
        if function == 3:
            return await self.read_holding_registers(address, count, unit)
        if function == 4:
            pdu = await self._run(
                _Expect(unit, 4, address, count),
                lambda c: c.read_input_registers(address, count=count, device_id=unit, no_response_expected=True),
            )
            assert pdu is not None
            return _words(pdu)
        if function in (1, 2):
            call = "read_coils" if function == 1 else "read_discrete_inputs"
            pdu = await self._run(
                _Expect(unit, function, address, count),
                lambda c: getattr(c, call)(address, count=count, device_id=unit, no_response_expected=True),
            )
            assert pdu is not None
            return [(pdu[2 + i // 8] >> (i % 8)) & 1 for i in range(count)]  # least significant bit first
        raise ValueError(f"function {function} is not a read")

    async def write_coil(self, address: int, value: bool, unit: int) -> None:
        await self._run(
            _Expect(unit, 5, address, 1, 0xFF00 if value else 0),
            lambda c: c.write_coil(address, value, device_id=unit, no_response_expected=True),
        )

    async def write_coils(self, address: int, values: list[bool], unit: int) -> None:
        await self._run(
            _Expect(unit, 15, address, len(values)),
            lambda c: c.write_coils(address, values, device_id=unit, no_response_expected=True),
        )

    async def read_device_identification(self, unit: int, read_code: int = 1) -> dict[int, bytes]:
        objects: dict[int, bytes] = {}
        object_id = 0
        for _ in range(8):  # 'more follows' pages; a device repeating itself must not loop for ever
            pdu = await self._run(
                _Expect(unit, 43, read_code, object_id),
                functools.partial(_read_identification, read_code=read_code, object_id=object_id, unit=unit),
            )
            r: Any = _DECODER.decode(pdu or b"")  # pymodbus parses the objects
            if r is None:
                raise BadAnswer("an identification answer pymodbus cannot read")
            for oid, value in dict(r.information).items():
                objects[int(oid)] = value[0] if isinstance(value, list) else bytes(value)
            if not r.more_follows or r.next_object_id <= object_id:
                break
            object_id = r.next_object_id
        return objects


def _read_identification(client: Any, *, read_code: int, object_id: int, unit: int) -> Any:
    return client.read_device_information(
        read_code=read_code, object_id=object_id, device_id=unit, no_response_expected=True
    )


_DECODER = DecodePDU(False)  # answers (is_server False)


def _connected_to_itself(client: Any) -> bool:
    transport = getattr(getattr(client, "ctx", None), "transport", None)
    if transport is None or not hasattr(transport, "get_extra_info"):
        return False
    local, peer = transport.get_extra_info("sockname"), transport.get_extra_info("peername")
    return isinstance(local, tuple) and local == peer


class TcpTransport(PymodbusTransport):
    """tcp://: Modbus/TCP (MBAP header)."""

    def _make_client(self) -> Any:
        return AsyncModbusTcpClient(
            self.url.host or "", port=self.url.port or 502, framer=FramerType.SOCKET, **self._common()
        )

    async def _why_not(self) -> str | None:
        try:
            _, writer = await asyncio.wait_for(asyncio.open_connection(self.url.host, self.url.port), self.url.timeout)
        except ConnectionRefusedError:
            return "connection refused"
        except TimeoutError:
            return f"connection timed out after {self.url.timeout:g} s"
        except OSError as e:
            return f"cannot connect: {e.strerror or e}"
        writer.close()
        return None


class RtuOverTcpTransport(TcpTransport):
    """rtu+tcp://: RTU frames (unit id + CRC) over a TCP socket to a serial gateway; shares the gateway's bus."""

    def _make_client(self) -> Any:
        return AsyncModbusTcpClient(
            self.url.host or "", port=self.url.port or 0, framer=FramerType.RTU, **self._common()
        )


class _HostnameContext(ssl.SSLContext):
    """An SSLContext that verifies a fixed name (server_hostname=) instead of the host connected to."""

    hostname: str | None = None

    def wrap_bio(
        self,
        incoming: ssl.MemoryBIO,
        outgoing: ssl.MemoryBIO,
        server_side: bool = False,
        server_hostname: str | bytes | None = None,
        session: ssl.SSLSession | None = None,
    ) -> ssl.SSLObject:
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
        return AsyncModbusTlsClient(
            self.url.host or "", port=self.url.port or 802, sslctx=self.ssl_context(), **self._common()
        )

    async def _why_not(self) -> str | None:
        try:
            _, writer = await asyncio.wait_for(
                asyncio.open_connection(self.url.host, self.url.port, ssl=self.ssl_context()), self.url.timeout
            )
        except ssl.SSLError as e:
            why = e.reason or str(e)
            if isinstance(e, ssl.SSLCertVerificationError) and e.verify_message:
                why += f": {e.verify_message}"  # e.g. "Hostname mismatch, certificate is not valid for 'x'"
            return (
                f"TLS handshake failed: {why} (check ca=, cert= and key=, or verify=false for a "
                f"self-signed device certificate)"
            )
        except ConnectionRefusedError:
            return "connection refused"
        except TimeoutError:
            return f"connection or TLS handshake timed out after {self.url.timeout:g} s"
        except OSError as e:
            return f"cannot connect: {e.strerror or e}"
        writer.close()
        return None


class _SerialLine:
    """One open serial port shared by every transport on it (pymodbus locks the port exclusively)."""

    def __init__(self, settings: tuple[str, ...]) -> None:
        self.client: Any = None
        self.rx: _Receiver | None = None
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
            self.url.serial_device,
            framer=FramerType.RTU if self.url.scheme == "rtu" else FramerType.ASCII,
            baudrate=line.baudrate,
            bytesize=line.bytesize,
            parity=line.parity,
            stopbits=line.stopbits,
            **common,
        )

    async def connect(self) -> None:
        path = self.url.path or ""
        where = describe(self.url)
        if windows_port(path) is not None:
            if os.name != "nt":
                raise Unreachable(
                    f"{where}: no such serial device '{path}' (COM ports are Windows' names; "
                    f"deployer scan --list-ports shows this system's serial ports)"
                )
        elif not path.startswith(("socket://", "rfc2217://", "loop://")) and not os.path.exists(path):
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
                    # pymodbus starts its port's transport on the loop's next turn; on Windows a transport
                    # closed before that (a refusal right after opening) tried a fileno a COM port lacks
                    await asyncio.sleep(0)
                finally:
                    self._opening = None
                line.client, line.rx = self._client, self._rx
                bus.line = line
            elif line.settings != self._settings():
                have = "{} baudrate={} bytesize={} parity={} stopbits={}".format(*line.settings)
                raise Unreachable(
                    f"{where}: the port is already open here as {have}; devices on one line must "
                    f"use the same framing and settings"
                )
            line.users += 1
            self._line, self._client, self._rx = line, line.client, line.rx

    def _probe(self) -> str | None:
        """Open and configure the port as pymodbus will, then close it: why it cannot be used, or None.

        pymodbus swallows the reason, and when configuring fails after the port opened (a pty refusing
        7E1) its half-built transport keeps the port locked until garbage collection; our own probe
        closes it for certain and says what went wrong.
        """
        o = self.url.options
        port: Any = None
        try:
            import serial  # here, not at import: on Linux pyserial needs termios, which TCP never does

            line = self.url.line
            port = serial.serial_for_url(
                self.url.serial_device,
                exclusive=True,
                baudrate=line.baudrate,
                bytesize=line.bytesize,
                parity=line.parity,
                stopbits=line.stopbits,
                timeout=self.url.timeout,
            )
            port.timeout = 0  # what pymodbus sets next: it reconfigures the port
            port.write_timeout = 0
        except Exception as e:  # pyserial raises SerialException, termios.error, ValueError
            # termios.error and OSError carry (errno, text): EINVAL is the line settings the port refuses
            code = e.args[0] if len(e.args) == 2 and isinstance(e.args[0], int) else getattr(e, "errno", None)
            inner = _WIN_ERROR.search(str(e))  # pyserial on Windows: "... Original message: OSError(22, ...)"
            if code is None and inner is not None:
                code = int(inner.group(1))
            if code == errno.EINVAL:
                settings = " ".join(f"{k}={o[k]}" for k in ("baudrate", "bytesize", "parity", "stopbits") if k in o)
                return f"the port rejects these line settings ({settings or 'defaults'}): {os.strerror(code)}"
            return _windows_open_error(str(e), self.url.path or "") or f"cannot open the serial port: {e}"
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
        line, self._line, self._client, self._rx = self._line, None, None, None
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


_WIN_OPEN = re.compile(r"could not open port .*: \w+\((\d+), '([^']*)', None, (\d+)\)$")
_WIN_ERROR = re.compile(r"\w+Error\((\d+), '[^']*', None, \d+\)")


def _windows_open_error(said: str, path: str) -> str | None:
    """pyserial's Windows error (``could not open port '\\\\.\\COM7': FileNotFoundError(2, ...)``) said plainly,
    by the port's name; None for any other text."""
    found = _WIN_OPEN.search(said)
    if found is None:
        return None
    name, winerror = (windows_port(path) or path), int(found.group(3))
    if winerror in (2, 3):  # ERROR_FILE_NOT_FOUND, ERROR_PATH_NOT_FOUND
        return f"no such serial port {name} (deployer scan --list-ports shows this system's serial ports)"
    if winerror == 5:  # ERROR_ACCESS_DENIED: Windows opens a COM port for one program at a time
        return f"{name} is in use by another program (a terminal, a vendor's tool): close it and run again"
    return f"cannot open {name}: {found.group(2)}"


_CLASSES: dict[str, type[PymodbusTransport]] = {
    "tcp": TcpTransport,
    "tls": TlsTransport,
    "rtu+tcp": RtuOverTcpTransport,
    "rtu": SerialTransport,
    "ascii": SerialTransport,
}


def open_transport(url: DeviceURL | str) -> Transport:
    """The transport for a URL, chosen by scheme (not yet connected). A string goes through parse_url."""
    u = parse_url(url) if isinstance(url, str) else url
    return _CLASSES[u.scheme](u)
