"""A simulated device that behaves like a real drive, on pymodbus's server.

Registers come from a profile: only declared registers exist (others answer exception 02),
read-only ones refuse writes, writes are applied in address order and stop at the first bad
value with exception 03 (the earlier registers stay written, as real drives do), requests
beyond the device's limits or splitting a multi-register value answer 03, unit 0 writes
everywhere and answers nothing. Faults (latency, line time, dropped answers, busy, failing
registers, disconnects) make the failure paths of the executor testable on a real socket.
Quirks model devices that do not follow the book, whatever the profile says: a shorter write
limit, all-or-nothing writes, Function 06 only, pauses the device needs, Function 43 identity.
With ``nonvolatile`` it keeps RAM and non-volatile memory apart, as drives do: writes reach RAM, only the
profile's commit stores them, and a power cycle (``power_cycle``; SIGUSR2 under ``deployer simulate``)
brings back what was stored.

    async with Simulator(profile) as sim:      # tcp://127.0.0.1:<free port>
        ... sim.url ... sim.log ... sim.read("F07")
"""

from __future__ import annotations

import asyncio
import itertools
import json
import operator
import re
import signal
import ssl
import sys
import threading
import time
import urllib.parse
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from decimal import Decimal
from typing import Any

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ModbusIOException, NoSuchIdException
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.pdu.mei_message import ReadDeviceInformationRequest, ReadDeviceInformationResponse
from pymodbus.server import ModbusSerialServer, ModbusTcpServer, ModbusTlsServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice

from ..profile import Parameter, Profile
from ..profile.model import BIT_TABLES, REGISTER_TYPES, SPACE, RegisterType
from ..recipe.loader import Recipe


@dataclass
class Faults:
    """Misbehaviour on demand. Mutable: tests and the demo switch faults while serving."""

    latency_ms: float = 0
    late_reads: int | None = None  # a number: latency_ms delays only that many next reads (counted down); None: all
    baud: int | None = None  # delay answers by the line time of request + answer on a B-baud 8E1 line
    drop_every: int = 0  # swallow every Nth request (no answer)
    busy_first: int = 0  # answer the first N write requests with exception 06, writing nothing
    fail_registers: frozenset[int] = frozenset()  # a write reaching one of these answers exception 04
    complain_registers: frozenset[int] = frozenset()  # a write reaching one of these is carried out, then 04
    disconnect_after: int = 0  # close the connection(s) after every N requests (TCP)
    # after a write: when a rule's condition on parameter values holds, its register is set (a drive tripping)
    rules: tuple[FaultRule, ...] = ()


_OPS: dict[str, Callable[[Decimal, Decimal], bool]] = {
    "<=": operator.le,
    ">=": operator.ge,
    "==": operator.eq,
    "!=": operator.ne,
    "<": operator.lt,
    ">": operator.gt,
}
_RULE = re.compile(r"\s*([A-Za-z_][\w.\[\]]*)\s*(<=|>=|==|!=|<|>)\s*(.+?)\s*:\s*(\S+?)\s*=\s*(\S+)\s*")


@dataclass(frozen=True)
class FaultRule:
    """``F07 < 2 s: 0x30=7``: after a write, when F07 holds less than 2 s, register 0x30 (a wire address) is
    set to 7, as a drive trips on a setting it cannot run with. The value is in any unit convertible to the
    parameter's, or one of its labels (``stop_mode == coast``)."""

    text: str
    parameter: str
    op: str
    value: Decimal  # engineering, in the parameter's unit (a label: its raw value)
    register: int
    raw: int
    by_label: bool = False

    def holds(self, p: Parameter, words: Sequence[int]) -> bool:
        got = Decimal(int(p.decode(list(words)))) if self.by_label else p.to_engineering(list(words))
        return _OPS[self.op](got, self.value)


def parse_address(text: str) -> int:
    """A register address or raw value as ``deployer simulate`` takes them (4354, 0x1102, 1102h); ValueError if
    it is not one."""
    from ..profile import parse_register

    return parse_register(text)


def parse_set(item: str) -> tuple[int, int]:
    """``--set [TABLE:]ADDR=RAW`` as (the simulator's key for that table and address, the raw value), for
    ``init``; ValueError saying what is wrong, in the option's words."""
    addr, sep, raw = item.partition("=")
    if not sep:
        raise ValueError(f"--set {item}: expected ADDR=RAW, e.g. 0x10=8")
    table, _, addr = addr.strip().rpartition(":") if ":" in addr else ("holding", "", addr)
    if table not in SPACE:
        raise ValueError(f"--set {item}: '{table}' is not a table (holding, coil, discrete, input)")
    try:
        address, value = parse_address(addr.strip()), parse_address(raw.strip())
    except ValueError:
        raise ValueError(f"--set {item}: expected ADDR=RAW with numbers, e.g. 0x10=8") from None
    bit = table in ("coil", "discrete")
    if value > (1 if bit else 0xFFFF):
        raise ValueError(f"--set {item}: {'a bit holds 0 or 1' if bit else 'a register holds 0..65535'}")
    return SPACE[table] << 16 | address, value


def parse_identity(items: Sequence[str]) -> dict[int, str] | None:
    """``--identity OBJECT=TEXT`` (a name of the profile format's identity objects or an object id 0..255) as the
    objects a simulated device answers with (None: none given); ValueError in the option's words."""
    from ..profile import IDENTITY_OBJECTS

    objects: dict[int, str] | None = None
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        oid = IDENTITY_OBJECTS.get(key, int(key) if key.isdigit() else -1)
        if not sep or not 0 <= oid <= 255:
            raise ValueError(
                f"--identity {item}: expected OBJECT=TEXT with OBJECT one of "
                f"{', '.join(IDENTITY_OBJECTS)} or an object id 0..255"
            )
        objects = {**(objects or {}), oid: text}
    return objects


def parse_fault_rule(text: str, profile: Profile) -> FaultRule:
    """A rule from its text; ValueError with the accepted form."""
    from ..profile import parse_register
    from ..profile import units as units_

    m = _RULE.fullmatch(text)
    if m is None:
        raise ValueError(
            f"'{text}' is not a fault rule: PARAMETER OP VALUE: REGISTER=RAW, e.g. 'F07 < 2 s: 0x30=7' "
            "(OP one of < <= > >= == !=)"
        )
    name, op, value, reg, raw = m.groups()
    p = profile.get(name)
    if p is None or p.is_string or p.register_type != "holding":
        raise ValueError(f"'{text}': {name} is not a numeric holding-register parameter of profile {profile.id}")
    labels = dict(p.values)
    try:
        register, word = parse_register(reg), parse_register(raw)
    except ValueError:
        raise ValueError(f"'{text}': expected REGISTER=RAW with numbers, e.g. 0x30=7") from None
    if value in labels:
        return FaultRule(text, name, op, Decimal(labels[value]), register, word, by_label=True)
    num, _, unit = value.partition(" ")
    try:
        amount = Decimal(num)
    except ArithmeticError:
        raise ValueError(f"'{text}': '{value}' is not a number with an optional unit, nor a label of {name}") from None
    if unit.strip():
        if p.unit is None:
            raise ValueError(f"'{text}': {name} has no unit")
        amount = units_.convert(amount, units_.normalize(unit.strip()), p.unit, cycles_as_angles=p.cycles_as_angles)
    return FaultRule(text, name, op, amount, register, word)


@dataclass
class Quirks:
    """How a device departs from the book, independent of the profile's limits (the profile may not know)."""

    max_write_registers: int = 0  # FC16 carrying more registers answers 03 and writes nothing (0: no limit)
    all_or_nothing: bool = False  # one bad value refuses the whole request (03), nothing of it is written
    fc06_only: bool = False  # FC16 answers 01 (illegal function); FC06 takes a 32-bit value word by word
    pause_after_connect_ms: float = 0  # requests sooner after a connection opened are not answered
    request_gap_ms: float = 0  # requests sooner after the previous answer are not answered
    # TCP connections served at once (0: any); one more is closed as it opens, as a gateway refuses it
    max_connections: int = 0
    # Function 43 / 14 objects (object id -> text); None: the profile's identity objects, else exception 01
    identity: dict[int, str] | None = None
    # function codes never answered (an RS-485 device that lacks one and stays silent, as many do for 43)
    silent_functions: frozenset[int] = frozenset()


@dataclass
class LogEntry:
    time: float
    unit: int
    function: int
    address: int
    count: int
    values: list[int] | None
    request_hex: str
    result: str = "ok"  # ok | exception NN | dropped | broadcast | no answer | disconnected | too soon


@dataclass
class _Listen:
    scheme: str
    host: str = "127.0.0.1"
    port: int = 5020
    path: str = ""
    baudrate: int = 19200
    options: dict[str, str] = field(default_factory=dict)


def parse_listen(url: str) -> _Listen:
    u = urllib.parse.urlsplit(url)
    if u.scheme in ("rtu", "ascii"):
        q = urllib.parse.parse_qs(u.query)
        return _Listen(
            u.scheme, path=urllib.parse.unquote(u.netloc + u.path), baudrate=int(q.get("baudrate", ["19200"])[-1])
        )
    if u.scheme in ("tcp", "rtu+tcp", "tls"):
        opts = {k: v[-1] for k, v in urllib.parse.parse_qs(u.query).items()}
        if u.scheme == "tls" and not {"cert", "key"} <= opts.keys():
            raise ValueError("tls listen URL needs ?cert=FILE&key=FILE (and ca=FILE to require client certificates)")
        return _Listen(u.scheme, host=u.hostname or "127.0.0.1", port=5020 if u.port is None else u.port, options=opts)
    raise ValueError(
        f"cannot listen on '{url}' (tcp://HOST:PORT, tls://HOST:PORT?cert=&key=&ca=, "
        "rtu+tcp://HOST:PORT, rtu:///dev/X, ascii:///dev/X)"
    )


def _frame_chars(function: int, count: int, request: bool) -> int:
    """Characters of an RTU frame (unit + PDU + CRC) for a read or write of ``count`` registers (or coils)."""
    if function in (3, 4):
        return 8 if request else 5 + 2 * count
    if function in (1, 2):
        return 8 if request else 5 + (count + 7) // 8
    if function == 16:
        return 9 + 2 * count if request else 8
    if function == 15:
        return 9 + (count + 7) // 8 if request else 8
    return 8


# the table each function code reaches
_FC_TABLE: dict[int, RegisterType] = {
    1: "coil",
    5: "coil",
    15: "coil",
    2: "discrete",
    4: "input",
    3: "holding",
    6: "holding",
    16: "holding",
}


def initial_registers(profile: Profile) -> dict[int, int]:
    """Power-on values by key (Parameter.key; a holding register's key is its address): each parameter's
    default (its factory setting, engineering), else zero; fields OR'ed into their register."""
    regs: dict[int, int] = {a: 0 for a in _action_registers(profile)}
    for p in profile.parameters:
        words = p.default_registers() or (p.encode_text("") if p.is_string else (0,) * p.count)
        if p.mask:
            regs[p.key] = regs.get(p.key, 0) | words[0]
            continue
        for i, w in enumerate(words):
            regs[p.key + i] = w
    return regs


def _action_registers(profile: Profile) -> set[int]:
    """Registers the profile's unlock/lock/commit writes, preconditions and health checks use (they exist on
    the device; a health register the profile does not declare as a parameter is writable from outside, so a
    test or `mbpoll` can make the device fault)."""
    regs = {c.address for c in profile.preconditions} | {c.key for c in profile.health}
    for act in (*profile.unlock, *profile.lock, *profile.commit):
        regs.update(range(act.key, act.key + len(act.registers)))
    return regs


def init_from_recipe(recipe: Recipe) -> dict[int, int]:
    """Key (Parameter.key: the wire address for holding registers) -> raw value for every value of a recipe
    (for ``--init``)."""
    regs: dict[int, int] = {}
    for d in recipe.desired:
        k = d.parameter.key
        if d.parameter.mask:  # fields of one register: each sets its own bits
            regs[k] = (regs.get(k, 0) & ~d.parameter.mask) | d.registers[0]
            continue
        regs.update((k + i, w) for i, w in enumerate(d.registers))
    return regs


class _Units:
    """pymodbus's SimCore answers 04 for an unknown unit; a bus stays silent, a gateway says 0x0B.

    Also the gate of the bit tables: pymodbus keeps coils 16 to a register and cannot refuse one
    undeclared or read-only coil, so ``sim.check_table`` does (and answers 01 for a table the profile
    does not use at all)."""

    def __init__(self, core: Any, sim: Simulator) -> None:
        self.core = core
        self.sim = sim
        self.identity = sim.identity_objects()  # Function 43 objects of every unit (None: answers 01)

    def device_ids(self) -> list[int]:
        return list(self.core.device_ids())

    async def async_getValues(self, device_id: int, func_code: int, address: int, count: int = 1) -> Any:
        if device_id not in self.core.devices:
            raise NoSuchIdException(str(device_id))
        refused = self.sim.check_table(func_code, address, count, write=False)
        if refused is not None:
            return refused
        return await self.core.async_getValues(device_id, func_code, address, count)

    async def async_setValues(self, device_id: int, func_code: int, address: int, values: Any) -> Any:
        if device_id not in self.core.devices:
            raise NoSuchIdException(str(device_id))
        refused = self.sim.check_table(func_code, address, len(values), write=True)
        if refused is not None:
            return refused
        return await self.core.async_setValues(device_id, func_code, address, values)


class _DeviceIdRequest(ReadDeviceInformationRequest):
    """Function 43 / 14 answered from the simulator's own objects: pymodbus's server answers from one
    identity per process, and simulated devices differ (or have none and answer 01)."""

    async def datastore_update(self, context: Any, device_id: int) -> ModbusPDU:
        objects = getattr(context, "identity", None)
        if device_id not in getattr(context, "core", context).devices:
            raise NoSuchIdException(str(device_id))
        if not objects:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_FUNCTION)
        if not 1 <= self.read_code <= 4:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
        if self.read_code == 4:  # one specific object
            if self.object_id not in objects:
                return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_ADDRESS)
            wanted = {self.object_id}
        else:
            lo, hi = {1: (0, 2), 2: (0, 0x7F), 3: (0, 0xFF)}[self.read_code]
            start = self.object_id if self.object_id in objects and lo <= self.object_id <= hi else lo
            wanted = {i for i in objects if start <= i <= hi}
        return ReadDeviceInformationResponse(
            read_code=self.read_code,
            information={i: objects[i].encode("latin-1") for i in sorted(wanted)},
            dev_id=device_id,
            transaction_id=self.transaction_id,
        )


# What the simulated device answers (the tables its profile does not use answer 01 as well); every
# other function code gets exception 01, as a drive's does (pymodbus's server would also answer
# diagnostics, event counters, report server id, file records, FIFO queues, device identification).
FUNCTIONS = frozenset({1, 2, 3, 4, 5, 6, 15, 16})


class _InOrderHandler(ServerRequestHandler):
    """One connection: every request of a segment answered, in order, one at a time.

    pymodbus's handler decodes one frame per segment and keeps the rest until more bytes arrive,
    so requests a client pipelines (as gateways and real clients do) went unanswered.
    """

    def __init__(self, owner: Any, functions: frozenset[int], sim: Simulator) -> None:
        super().__init__(owner, owner.trace_packet, owner.trace_pdu, owner.trace_connect)  # type: ignore[no-untyped-call]
        self._functions = functions
        self._sim = sim
        self._waiting: bytes | None = None  # what a connection over Quirks.max_connections sent before its admission
        # pymodbus drops a whole buffer longer than one frame; complete frames are taken out at once
        # here, so only a partial frame stays, and a read of many pipelined requests is kept whole
        self.max_buffer_size = 1 << 20
        self._queue: asyncio.Queue[tuple[Any, Any]] = asyncio.Queue()
        self._worker: asyncio.Task[None] | None = None

    def callback_connected(self) -> None:
        super().callback_connected()
        if self._over_limit():  # a connection closed just before may not be counted out yet: a moment's grace
            self._waiting = b""
            asyncio.get_running_loop().call_later(0.1, self._admit)

    def _over_limit(self) -> bool:
        limit = self._sim.quirks.max_connections
        older = list(self.server.active_connections)  # in the order they opened: the oldest are served
        return bool(limit) and self.unique_id in older and older.index(self.unique_id) >= limit

    def _admit(self) -> None:
        held, self._waiting = self._waiting, None
        if self._over_limit():
            self._sim.refused_connections += 1
            self.close()
        elif held:
            self.callback_data(held)

    def callback_data(self, data: bytes, addr: tuple[Any, ...] | None = None) -> int:
        if self._waiting is not None:  # not admitted yet: kept until it is
            self._waiting += data
            return len(data)
        used = 0
        while used < len(data):
            try:
                n, pdu = self.framer.handleFrame(
                    self.trace_packet(False, data[used:]), self.request_dev_id, self.request_transaction_id
                )
            except ModbusIOException as exc:  # what pymodbus's handler answers to an undecodable frame
                reply = ExceptionResponse(
                    exc.fcode or 0,
                    exception_code=ExcCodes.ILLEGAL_FUNCTION,
                    device_id=exc.dev_id,
                    transaction=exc.transaction_id,
                )
                self.server_send(reply, addr)  # type: ignore[no-untyped-call]
                return len(data)
            if not n:
                break
            used += n
            if pdu is not None:
                pdu = self.trace_pdu(False, pdu)
            if pdu is not None:
                self._queue.put_nowait((pdu, addr))
        if self._worker is None and not self._queue.empty():
            self._worker = asyncio.get_running_loop().create_task(self._answer())
        return used

    async def _answer(self) -> None:
        while True:
            pdu, addr = await self._queue.get()
            if pdu.function_code not in self._functions and pdu.dev_id in self.server.context.device_ids():
                reply = ExceptionResponse(pdu.function_code, ExcCodes.ILLEGAL_FUNCTION)
                reply.transaction_id, reply.dev_id = pdu.transaction_id, pdu.dev_id
                if pdu.dev_id:
                    self.server_send(reply, addr)  # type: ignore[no-untyped-call]
                continue
            self.last_pdu, self.last_addr = pdu, addr
            await self.handle_request()  # type: ignore[no-untyped-call]

    def callback_disconnected(self, exc: Exception | None) -> None:
        if self._worker is not None:
            self._worker.cancel()
        super().callback_disconnected(exc)


class Simulator:
    def __init__(
        self,
        profile: Profile,
        *,
        listen: str = "tcp://127.0.0.1:0",
        units: Sequence[int] = (1,),
        init: Mapping[int, int] | None = None,
        faults: Faults | None = None,
        log_path: str | None = None,
        state_path: str | None = None,
        strict_limits: bool = True,
        gap_reads: bool = False,
        quirks: Quirks | None = None,
        nonvolatile: bool = False,
    ) -> None:
        if not profile.parameters:
            raise ValueError(f"profile {profile.id} declares no registers to simulate")
        self.profile = profile
        self.listen = parse_listen(listen)
        self.units = tuple(units)
        self.faults = faults or Faults()
        self.quirks = quirks or Quirks()
        self.log: list[LogEntry] = []
        self.log_path = log_path
        self.state_path = state_path
        self.strict_limits = strict_limits
        # answer reads of undeclared registers between declared ones (with zeros), as many devices do;
        # writes to them still answer 02
        self.gap_reads = gap_reads
        self.url = ""
        self._server: Any = None
        self._log_file: Any = None
        self._requests = 0  # since start, for drop_every / disconnect_after
        self._window = 0
        self._writes = 0  # write requests, for busy_first
        self.refused_connections = 0  # connections closed as they opened (Quirks.max_connections)
        # requests awaiting their answer; several TCP clients may reuse a transaction id, so FIFO per key
        self._pending: dict[tuple[int, int, int], deque[LogEntry]] = {}
        self._owner: dict[int, list[Parameter]] = {}  # by key; several bit fields may share a register
        for p in profile.parameters:
            for a in range(p.key, p.key + p.count):
                self._owner.setdefault(a, []).append(p)
        self._used = {p.register_type for p in profile.parameters}
        self._bit_count = 0  # the coils of the request being served (pymodbus passes registers to the action)
        self._action_regs = _action_registers(profile)
        self._extra = sorted(self._action_regs - self._owner.keys())
        self._used.update(REGISTER_TYPES[a >> 16] for a in self._extra)
        self._unlock_regs = {a.key + i: w for a in profile.unlock for i, w in enumerate(a.registers)}
        # the writes after which the device is busy for a while: (key, the words written) -> ms
        self._waits = {
            (a.key, a.registers): a.wait_ms for a in (*profile.unlock, *profile.lock, *profile.commit) if a.wait_ms
        }
        # RAM and non-volatile memory (``nonvolatile``): what a power cycle brings back, per unit, by key; the
        # writes that store RAM there are the profile's commit actions (key, the words written)
        self.nonvolatile = nonvolatile
        self._stored: dict[int, dict[int, int]] = {}
        self._commits = {(a.key, a.registers) for a in profile.commit}
        self.power_cycles = 0
        self._busy_until = 0.0  # a declared wait after an unlock/commit/lock write: busy (06) meanwhile
        self._connected_at = 0.0  # monotonic time the last connection opened (a required pause after it)
        self._answered_at = 0.0  # monotonic time of the last answer (a required gap before the next request)
        start = initial_registers(profile)
        for a, v in (init or {}).items():
            if a not in self._owner and a not in self._extra:
                table, address = REGISTER_TYPES[a >> 16], a & 0xFFFF
                what = "register" if table == "holding" else f"{table} {'register' if table == 'input' else ''}"
                raise ValueError(f"init: {what.strip()} {address} is not declared in profile {profile.id}")
            start[a] = v
        self._start_values = start
        for rule in self.faults.rules:
            if rule.register not in self._owner and rule.register not in self._extra:
                raise ValueError(
                    f"fault rule '{rule.text}': register {rule.register} is not declared in profile "
                    f"{profile.id} (a parameter, or a register of its health checks)"
                )
        self.functions = FUNCTIONS  # the function codes this device answers; others get exception 01
        if self.identity_objects():  # Function 43 / 14 (device identification) when it has objects
            self.functions = self.functions | {43}

    # ---- lifecycle ---------------------------------------------------------------------------

    async def start(self) -> None:
        devices = [self._device(unit) for unit in self.units]
        if self.nonvolatile:  # what it powered up with is what its memory holds
            self._stored = {
                u: {k: self._start_values.get(k, 0) for k in (*self._owner, *self._extra)} for u in self.units
            }
        lst = self.listen
        common: dict[str, Any] = {
            "broadcast_enable": True,
            "trace_pdu": self._trace_pdu,
            "trace_connect": self._trace_connect,
        }
        if lst.scheme == "tcp":
            self._server = ModbusTcpServer(devices, framer=FramerType.SOCKET, address=(lst.host, lst.port), **common)
        elif lst.scheme == "tls":
            ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH, cafile=lst.options.get("ca"))
            ctx.load_cert_chain(lst.options["cert"], lst.options["key"])
            if "ca" in lst.options:  # Modbus/TCP Security: mutual authentication
                ctx.verify_mode = ssl.CERT_REQUIRED
            self._server = ModbusTlsServer(
                devices, framer=FramerType.TLS, sslctx=ctx, address=(lst.host, lst.port), **common
            )
        elif lst.scheme == "rtu+tcp":
            self._server = ModbusTcpServer(
                devices, framer=FramerType.RTU, address=(lst.host, lst.port), ignore_missing_devices=True, **common
            )
        else:
            framer = FramerType.RTU if lst.scheme == "rtu" else FramerType.ASCII
            self._server = ModbusSerialServer(
                devices, framer=framer, port=lst.path, baudrate=lst.baudrate, ignore_missing_devices=True, **common
            )
        self._core = self._server.context
        self._server.context = _Units(self._core, self)
        # this server's decoder (each connection's framer copies it) answers Function 43 / 14 itself
        decoder = self._server.decoder
        decoder.pdu_sub_table = {fc: dict(subs) for fc, subs in decoder.pdu_sub_table.items()}
        decoder.pdu_sub_table[0x2B][0x0E] = (_DeviceIdRequest, ReadDeviceInformationResponse)
        server = self._server
        server.callback_new_connection = lambda: _InOrderHandler(server, self.functions, self)
        if self.log_path:
            self._log_file = open(self.log_path, "a", encoding="utf-8")  # noqa: SIM115 - open for the server's life
        await self._server.serve_forever(background=True)
        if lst.scheme in ("tcp", "rtu+tcp", "tls"):
            port = lst.port
            sockets = getattr(self._server.transport, "sockets", None)
            if sockets:
                port = sockets[0].getsockname()[1]
            self.url = f"{lst.scheme}://{lst.host}:{port}"
        else:
            self.url = f"{lst.scheme}://{lst.path}"

    async def stop(self) -> None:
        if self._server is not None:
            await self._server.shutdown()
            self._server = None
        if self.state_path:
            self.dump_state(self.state_path)
        if self._log_file is not None:
            self._log_file.close()
            self._log_file = None

    async def __aenter__(self) -> Simulator:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    def set_identity(self, objects: Mapping[int, str]) -> None:
        """Other Function 43 objects from now on (the device was swapped for another model)."""
        self.quirks.identity = dict(objects)
        if self._server is not None:
            self._server.context.identity = self.identity_objects()

    def identity_objects(self) -> dict[int, str] | None:
        """Function 43 objects served: the quirk's, else those the profile's identity checks expect."""
        if self.quirks.identity is not None:
            return dict(self.quirks.identity) or None
        objects = {c.object_id: c.equals for c in self.profile.identity_objects}
        return objects or None

    # ---- registers from outside ------------------------------------------------------------

    def _block(self, unit: int, table: str = "holding") -> tuple[int, list[int]]:
        runtime = self._core.devices[unit]
        start, _count, registers, _flags = runtime.block[table[0]]  # c, d, h, i
        return start, registers

    def _get(self, unit: int, key: int) -> int:
        table, address = REGISTER_TYPES[key >> 16], key & 0xFFFF
        start, regs = self._block(unit, table)
        if table in BIT_TABLES:  # 16 coils to a register, bit 0 first; start counts registers
            bit = address - start * 16
            return regs[bit // 16] >> (bit % 16) & 1
        return regs[address - start]

    def _set(self, unit: int, key: int, value: int) -> None:
        table, address = REGISTER_TYPES[key >> 16], key & 0xFFFF
        start, regs = self._block(unit, table)
        if table in BIT_TABLES:
            bit = address - start * 16
            regs[bit // 16] = regs[bit // 16] & ~(1 << bit % 16) | (1 if value else 0) << bit % 16
        else:
            regs[address - start] = value

    def power_cycle(self) -> None:
        """Power off and on (``nonvolatile``): every register holds again what non-volatile memory holds, the
        values of the last commit (or of the start); what was written since, without a commit, is gone."""
        if not self.nonvolatile:
            raise ValueError(
                "a power cycle changes nothing without the RAM and non-volatile memory model "
                "(Simulator(..., nonvolatile=True); deployer simulate --nonvolatile)"
            )
        for u, image in self._stored.items():
            for k, v in image.items():
                self._set(u, k, v)
        self._busy_until = 0.0
        self.power_cycles += 1

    def stored(self, unit: int = 1, table: RegisterType = "holding") -> dict[int, int]:
        """What non-volatile memory holds for one table (``nonvolatile``), by wire address."""
        space = SPACE[table]
        return {k & 0xFFFF: v for k, v in sorted(self._stored.get(unit, {}).items()) if k >> 16 == space}

    def _store(self, unit: int) -> None:
        """The profile's commit: the parameters' values in RAM go to non-volatile memory."""
        image = self._stored.get(unit)
        if image is None:
            return
        for k, owners in self._owner.items():
            if any(p.writable for p in owners):
                image[k] = self._get(unit, k)

    def registers(self, unit: int = 1, table: RegisterType = "holding") -> dict[int, int]:
        """One table's declared registers (coils: 0/1) by wire address."""
        space = SPACE[table]
        keys = sorted(k for k in {*self._owner, *self._extra} if k >> 16 == space)
        return {k & 0xFFFF: self._get(unit, k) for k in keys}

    def read(self, name: str, unit: int = 1) -> tuple[int, ...]:
        p = self.profile.parameter(name)
        return tuple(self._get(unit, k) for k in range(p.key, p.key + p.count))

    def write(self, name: str, registers: Sequence[int], unit: int = 1) -> None:
        p = self.profile.parameter(name)
        if len(registers) != p.count:
            raise ValueError(f"{name} has {p.count} registers")
        if p.is_bit and any(v not in (0, 1) for v in registers):
            raise ValueError(f"{name} is a {p.register_type}: 0 or 1")
        for k, v in zip(range(p.key, p.key + p.count), registers, strict=True):
            self._set(unit, k, v)

    def set_register(self, address: int, value: int, unit: int = 1, table: RegisterType = "holding") -> None:
        """Set a declared register from outside (a fault code clears after a reset, a status word changes)."""
        key = SPACE[table] << 16 | address
        if key not in self._owner and key not in self._extra:
            raise ValueError(f"{table} register {address} is not declared in profile {self.profile.id}")
        self._set(unit, key, value)

    def dump_state(self, path: str) -> None:
        from ..state.durable import write_atomic

        state = {str(u): {str(a): v for a, v in self.registers(u).items()} for u in self.units}
        data: dict[str, Any] = {"profile": self.profile.id, "units": state}
        others = [t for t in REGISTER_TYPES[1:] if t in self._used]
        if others:  # coils, discrete inputs, input registers by table (addresses of each table)
            data["tables"] = {
                str(u): {t: {str(a): v for a, v in self.registers(u, t).items()} for t in others} for u in self.units
            }
        write_atomic(path, json.dumps(data, indent=1))

    # ---- the device ----------------------------------------------------------------------------

    def _device(self, unit: int) -> SimDevice:
        tables: dict[str, list[SimData]] = {t: [] for t in REGISTER_TYPES}
        done: set[int] = set()
        for p in self.profile.parameters:
            if p.key in done or p.is_bit:  # bit fields sharing a register: one block; coils below
                continue
            done.add(p.key)
            writable = any(q.writable for q in self._owner[p.key])
            tables[p.register_type].append(
                SimData(
                    address=p.address,
                    values=[self._start_values[a] for a in range(p.key, p.key + p.count)],
                    datatype=DataType.REGISTERS,
                    readonly=not writable,
                )
            )
        for a in self._extra:  # e.g. a health check's input register
            tables[REGISTER_TYPES[a >> 16]].append(
                SimData(address=a & 0xFFFF, values=[self._start_values.get(a, 0)], datatype=DataType.REGISTERS)
            )
        for t in ("holding", "input"):
            if self.gap_reads:  # read-only zeros in every gap between declared registers
                declared = sorted({a & 0xFFFF for a in (*self._owner, *self._extra) if a >> 16 == SPACE[t]})
                tables[t] += [
                    SimData(address=a + 1, values=[0] * (b - a - 1), datatype=DataType.REGISTERS, readonly=True)
                    for a, b in itertools.pairwise(declared)
                    if b - a > 1
                ]
            tables[t].sort(key=lambda b: b.address)
            if not tables[t]:  # pymodbus wants every table; check_table answers 01 for an unused one
                tables[t] = [SimData(address=0, values=[0], datatype=DataType.REGISTERS, readonly=True)]
        for t in BIT_TABLES:  # one run of bits from the first declared one to the last; check_table
            space = SPACE[t]  # refuses the undeclared ones in between
            keys = sorted(k for k in (*self._owner, *self._extra) if k >> 16 == space)  # a coil commit step too
            lo, hi = (keys[0], keys[-1]) if keys else (space << 16, space << 16)
            tables[t] = [
                SimData(
                    address=lo & 0xFFFF,
                    values=[bool(self._start_values.get(k, 0)) for k in range(lo, hi + 1)],
                    datatype=DataType.BITS,
                )
            ]

        async def action(
            fc: int, start: int, address: int, count: int, registers: list[int], values: list[int] | list[bool] | None
        ) -> ExcCodes | None:
            words = None if values is None else [int(v) for v in values]
            return await self._action(fc, start, address, count, registers, words, unit)

        return SimDevice(
            id=unit, simdata=(tables["coil"], tables["discrete"], tables["holding"], tables["input"]), action=action
        )

    def check_table(self, fc: int, address: int, count: int, *, write: bool) -> ExcCodes | None:
        """The checks pymodbus cannot make on bits, and unused tables (see _Units); None: go on."""
        table = _FC_TABLE.get(fc)
        if table is None:
            return None  # the action answers 01
        if table not in self._used:
            return ExcCodes.ILLEGAL_FUNCTION  # a drive without coils (or input registers) does not know the function
        if table not in BIT_TABLES:
            return None
        self._bit_count = count
        limits = self.profile.limits
        if self.strict_limits and count > (limits.write_coils if write else limits.read_coils):
            return ExcCodes.ILLEGAL_VALUE
        space = SPACE[table]
        # gap reads: undeclared bits between two declared ones read as 0 (the first and last must exist)
        gaps = (
            self.gap_reads
            and not write
            and (space << 16 | address) in self._owner
            and (space << 16 | (address + count - 1)) in self._owner
        )
        for a in range(address, address + count):
            owners = self._owner.get(space << 16 | a)
            if owners is None:
                if (space << 16 | a) in self._action_regs:  # a coil of an unlock/commit/lock step, a health bit
                    continue
                if not gaps:
                    return ExcCodes.ILLEGAL_ADDRESS
                continue
            if (write and not owners[0].writable) or (not write and not owners[0].readable and fc != 5):
                return ExcCodes.ILLEGAL_ADDRESS
        return None

    def _params_in(self, address: int, count: int) -> list[Parameter]:
        seen: dict[str, Parameter] = {}
        for a in range(address, address + count):
            for p in self._owner.get(a, ()):
                seen.setdefault(p.name, p)
        return sorted(seen.values(), key=lambda p: p.address)

    def unlocked(self, registers: Mapping[int, int]) -> bool:
        """The profile's unlock values are in place (a device without unlock is always unlocked)."""
        return all(registers.get(a) == v for a, v in self._unlock_regs.items())

    def guarded(self, registers: Mapping[int, int]) -> str | None:
        """Why parameter writes are refused now (a failing precondition, e.g. 'drive running'), or None."""
        for c in self.profile.preconditions:
            if not c.holds(registers.get(c.address, 0)):
                return c.what()
        return None

    async def _action(
        self,
        fc: int,
        start: int,
        address: int,
        count: int,
        registers: list[int],
        values: list[int] | None,
        unit: int = 1,
    ) -> ExcCodes | None:
        """The device's answer to one request (None: a normal answer), stores a write's values as it goes."""
        if fc not in _FC_TABLE or (fc == 16 and self.quirks.fc06_only):  # e.g. FC22/23: not implemented
            return ExcCodes.ILLEGAL_FUNCTION
        if _FC_TABLE[fc] in BIT_TABLES:
            count = self._bit_count  # pymodbus passes the registers the bits live in
        await self._line_time(fc, count, values)
        if fc == 4:
            return ExcCodes.ILLEGAL_VALUE if self.strict_limits and count > self.profile.limits.read_registers else None
        if fc in (1, 2) or (fc == 5 and values is None):
            return None  # checked by check_table
        if fc in (5, 15):
            return self._coil_write(address, count, unit, values or [])
        params = self._params_in(address, count)
        if values is None:  # a read (or pymodbus reading back an FC06 write)
            return self._register_read(fc, count, params)
        return self._register_write(fc, start, address, count, registers, values, params, unit)

    async def _line_time(self, fc: int, count: int, values: list[int] | None) -> None:
        """The answer's delay: the latency, and at a baud rate the time both frames take on the line."""
        f = self.faults
        delay = f.latency_ms / 1000
        if f.late_reads is not None:  # a device late now and then (a busy moment), else prompt
            if f.late_reads > 0 and values is None and fc in (1, 2, 3, 4):
                f.late_reads -= 1
            else:
                delay = 0.0
        if f.baud and not (values is None and fc in (5, 6)):  # not pymodbus reading back a single write
            chars = _frame_chars(fc, count, True) + _frame_chars(fc, count, False)
            delay += (chars + 7) * 11 / f.baud  # 8E1 = 11 bits a character; 3.5 characters of silence per frame
        if delay:
            await asyncio.sleep(delay)

    def _busy(self) -> bool:
        """Counts a write; busy for the first ``busy_first`` writes and while a declared wait runs."""
        self._writes += 1
        return self._writes <= self.faults.busy_first or time.monotonic() < self._busy_until

    def _refused_now(self, registers: Sequence[int], start: int, unit: int) -> bool:
        """Parameters locked (unlock values not in place) or a precondition failing (the drive running).
        ``registers`` from ``start``: the holding registers as the request being served sees them."""
        current = {
            a: registers[a - start]
            for a in (*self._unlock_regs, *(c.address for c in self.profile.preconditions))
            if 0 <= a - start < len(registers)
        }
        current.update((k, self._get(unit, k)) for k in self._unlock_regs if k >> 16)  # a coil unlock step
        return not self.unlocked(current) or bool(self.guarded(current))

    def _coil_write(self, address: int, count: int, unit: int, values: Sequence[int]) -> ExcCodes | None:
        if self._busy():
            return ExcCodes.DEVICE_BUSY
        keys = [SPACE["coil"] << 16 | a for a in range(address, address + count)]
        touches_parameters = any(k not in self._action_regs for k in keys)  # an unlock coil is taken when locked
        if touches_parameters and (self._unlock_regs or self.profile.preconditions):
            hstart, hregs = self._block(unit)
            if self._refused_now(hregs, hstart, unit):
                return ExcCodes.DEVICE_FAILURE
        if any(k in self.faults.fail_registers for k in keys):
            return ExcCodes.DEVICE_FAILURE
        written = dict(zip(keys, values, strict=False))
        for (k, words), wait in self._waits.items():
            if written.get(k) == words[0] and k >> 16:
                self._busy_until = time.monotonic() + wait / 1000
        if any(written.get(k) == words[0] for k, words in self._commits if k >> 16):
            self._store(unit)  # e.g. coil 65: store to EEPROM
            image = self._stored.get(unit, {})  # coils written in this very request (pymodbus stores them after)
            image.update((k, v) for k, v in written.items() if k in image and k in self._owner)
        return None

    def _register_read(self, fc: int, count: int, params: list[Parameter]) -> ExcCodes | None:
        if fc == 3:
            if self.strict_limits and count > self.profile.limits.read_registers:
                return ExcCodes.ILLEGAL_VALUE
            if any(not p.readable for p in params):
                return ExcCodes.ILLEGAL_ADDRESS
        return None

    def _write_refused(
        self,
        fc: int,
        start: int,
        address: int,
        count: int,
        registers: list[int],
        values: list[int],
        params: list[Parameter],
        unit: int,
    ) -> ExcCodes | None:
        """What refuses a register write as a whole, before any value is stored."""
        q, limits = self.quirks, self.profile.limits
        if self._busy():
            return ExcCodes.DEVICE_BUSY
        touches_parameters = any(a not in self._action_regs for a in range(address, address + count))
        if (
            touches_parameters
            and (self._unlock_regs or self.profile.preconditions)
            and self._refused_now(registers, start, unit)
        ):
            return ExcCodes.DEVICE_FAILURE  # parameters locked, or the drive is running
        if self.strict_limits and fc == 16 and count > limits.write_registers:
            return ExcCodes.ILLEGAL_VALUE
        if fc == 16 and q.max_write_registers and count > q.max_write_registers:
            return ExcCodes.ILLEGAL_VALUE  # the device's own buffer, whatever the profile says
        # FC06 devices take a 32-bit value word by word
        single_words = fc == 6 and (limits.write_function == 6 or q.fc06_only)
        if not single_words and any(p.address < address or p.end > address + count for p in params):
            return ExcCodes.ILLEGAL_VALUE  # the upper and lower word must come in one request
        if q.all_or_nothing:  # every value is checked before any is stored (Yaskawa: one bad value discards all)
            return self._refusal(params, address, count, values)
        return None

    def _register_write(
        self,
        fc: int,
        start: int,
        address: int,
        count: int,
        registers: list[int],
        values: list[int],
        params: list[Parameter],
        unit: int,
    ) -> ExcCodes | None:
        refused = self._write_refused(fc, start, address, count, registers, values, params, unit)
        if refused is not None:
            return refused
        f = self.faults
        for p in params:  # in address order, stopping at the first bad one: the partial write of real drives
            lo, hi = max(p.address, address), min(p.end, address + count)
            if any(a in f.fail_registers for a in range(lo, hi)):
                return ExcCodes.DEVICE_FAILURE
            new = list(values[lo - address : hi - address])
            if hi - lo == p.count and not self._in_range(p, new):
                return ExcCodes.ILLEGAL_VALUE
            registers[lo - start : hi - start] = new
        for a in range(address, address + count):  # registers of unlock/lock/commit writes only
            if not self._owner.get(a):
                registers[a - start] = values[a - address]
        self._after_write(start, address, count, registers, values, unit)
        if any(a in f.complain_registers for a in range(address, address + count)):
            return ExcCodes.DEVICE_FAILURE  # written all the same: a device that complains about what it did
        return None

    def _after_write(
        self, start: int, address: int, count: int, registers: list[int], values: list[int], unit: int
    ) -> None:
        """What a write sets off: fault rules (a drive that trips on a too-short acceleration time), the busy
        time of a declared wait (storing to EEPROM), and with ``nonvolatile`` the profile's commit storing RAM."""
        for rule in self.faults.rules:
            p = self.profile.parameter(rule.parameter)
            if rule.register - start in range(len(registers)) and rule.holds(
                p, registers[p.address - start : p.end - start]
            ):
                registers[rule.register - start] = rule.raw

        def written(a: int, words: tuple[int, ...]) -> bool:
            return (
                address <= a
                and a + len(words) <= address + count
                and tuple(values[a - address : a - address + len(words)]) == words
            )

        for (a, words), wait in self._waits.items():
            if written(a, words):  # a coil's key is beyond any register's address: never matches here
                self._busy_until = time.monotonic() + wait / 1000
        if any(written(a, words) for a, words in self._commits):
            self._store(unit)  # ``registers`` is the block itself: this request's values are in it already

    def _refusal(self, params: list[Parameter], address: int, count: int, values: list[int]) -> ExcCodes | None:
        """The answer the first bad value of a write gets, or None when every value is acceptable."""
        for p in params:
            lo, hi = max(p.address, address), min(p.end, address + count)
            if any(a in self.faults.fail_registers for a in range(lo, hi)):
                return ExcCodes.DEVICE_FAILURE
            if hi - lo == p.count and not self._in_range(p, list(values[lo - address : hi - address])):
                return ExcCodes.ILLEGAL_VALUE
        return None

    @staticmethod
    def _in_range(p: Parameter, words: list[int]) -> bool:
        if p.is_string:
            return True  # a device stores whatever bytes it is sent
        raw = p.decode(words)
        if isinstance(raw, float) and raw != raw:  # NaN
            return False
        bounds = p.raw_bounds()
        return bounds is None or bounds[0] <= raw <= bounds[1]

    # ---- request log, dropped answers, disconnects --------------------------------------------

    def _trace_connect(self, connected: bool) -> None:
        if connected:
            self._connected_at = time.monotonic()

    def _too_soon(self) -> bool:
        """A request inside the pause the device needs after a connect or after its last answer."""
        q, now = self.quirks, time.monotonic()
        return (
            now - self._connected_at < q.pause_after_connect_ms / 1000
            or now - self._answered_at < q.request_gap_ms / 1000
        )

    def _trace_pdu(self, sending: bool, pdu: Any) -> Any:
        fc = int(pdu.function_code) & 0x7F
        if sending:
            self._answered_at = time.monotonic()
            waiting = self._pending.get((pdu.dev_id, pdu.transaction_id, fc))
            entry = waiting.popleft() if waiting else None
            if entry is not None:
                if pdu.isError():
                    entry.result = f"exception {int(pdu.exception_code):02d}"
                self._write_log(entry)
            return pdu
        regs = list(getattr(pdu, "registers", None) or [])
        if fc in (5, 15):  # coils as 0/1 (pdu.bits is padded to whole bytes for FC15)
            regs = [1 if b else 0 for b in (pdu.bits or [])]
            if fc == 15 and pdu.count:
                regs = regs[: int(pdu.count)]
            elif fc == 5:
                regs = regs[:1]
        count = int(getattr(pdu, "count", 0) or len(regs) or 1)
        try:
            body = pdu.encode()
        except Exception:  # an unknown function: nothing to re-encode
            body = b""
        entry = LogEntry(
            time.time(),
            int(pdu.dev_id),
            fc,
            int(getattr(pdu, "address", 0) or 0),
            count,
            regs if fc in (5, 6, 15, 16) else None,
            bytes([pdu.dev_id, fc]).hex() + body.hex(),
        )
        self.log.append(entry)
        self._requests += 1
        self._window += 1
        f = self.faults
        if self._too_soon():  # not ready: the request is ignored (gateways, dongles, slow meters)
            entry.result = "too soon"
            self._write_log(entry)
            return None
        if f.drop_every and self._requests % f.drop_every == 0:
            entry.result = "dropped"
            self._write_log(entry)
            return None
        if fc in self.quirks.silent_functions:
            entry.result = "no answer"
            self._write_log(entry)
            return None
        if f.disconnect_after and self._window > f.disconnect_after:
            entry.result = "disconnected"
            self._window = 0
            self._write_log(entry)
            self._drop_connections()
            return None
        if pdu.dev_id == 0:
            entry.result = "broadcast"
            self._write_log(entry)
        elif pdu.dev_id not in self.units and self.listen.scheme not in ("tcp", "tls"):
            entry.result = "no answer"  # nobody on the bus has this address
            self._write_log(entry)
        else:
            self._pending.setdefault((pdu.dev_id, pdu.transaction_id, fc), deque()).append(entry)
        return pdu

    def _drop_connections(self) -> None:
        server = self._server
        for conn in list(getattr(server, "active_connections", {}).values()):
            loop = asyncio.get_running_loop()
            loop.call_soon(conn.close)

    def _write_log(self, entry: LogEntry) -> None:
        if self._log_file is not None:
            self._log_file.write(json.dumps(asdict(entry)) + "\n")
            self._log_file.flush()


class SimulatorThread:
    """A Simulator on its own event loop in a background thread (for code that calls asyncio.run)."""

    def __init__(self, profile: Profile, **kwargs: Any) -> None:
        self.sim = Simulator(profile, **kwargs)
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="deployer-simulator", daemon=True)

    def __enter__(self) -> Simulator:
        self._thread.start()
        asyncio.run_coroutine_threadsafe(self.sim.start(), self._loop).result(timeout=30)
        return self.sim

    def __exit__(self, *exc: object) -> None:
        try:
            asyncio.run_coroutine_threadsafe(self.sim.stop(), self._loop).result(timeout=30)
        finally:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=30)
            self._loop.close()


async def serve(sim: Simulator, *, on_ready: Any = None) -> None:
    """Run until SIGINT/SIGTERM; SIGUSR1 dumps the state file; SIGUSR2 power-cycles a ``nonvolatile`` device."""
    from ..portable import interrupt_signals, on_signals

    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    undo = [on_signals(loop, interrupt_signals(), lambda _sig: stop.set())]
    if sim.state_path and hasattr(signal, "SIGUSR1"):  # POSIX only; Windows dumps on exit alone
        path = sim.state_path
        undo.append(on_signals(loop, (signal.SIGUSR1,), lambda _sig: sim.dump_state(path)))
    if sim.nonvolatile and hasattr(signal, "SIGUSR2"):  # POSIX only; in Python: Simulator.power_cycle()

        def power_cycle(_sig: object) -> None:
            sim.power_cycle()
            print(
                f"power cycle {sim.power_cycles}: RAM holds what non-volatile memory holds", file=sys.stderr, flush=True
            )

        undo.append(on_signals(loop, (signal.SIGUSR2,), power_cycle))
    await sim.start()
    if on_ready:
        on_ready(sim)
    try:
        await stop.wait()
    finally:
        for u in undo:
            u()
        await sim.stop()
