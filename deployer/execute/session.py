"""One device's connection for a run: retries, the request log, options of an apply."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Awaitable, Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Literal

from ..errors import (
    BadAnswer,
    ConnectionLost,
    DeviceGone,
    ExceptionResponse,
    NoResponse,
    Unreachable,
)
from ..planning.model import Plan, ReadRequest, WriteRequest
from ..planning.planner import gap_free_reads, read_key
from ..profile import Profile, object_name
from ..report import DeviceResult, RequestRecord
from ..state.lock import DeviceLock
from ..transport import clients as tp
from .trust import CONFIRMATIONS, Trust

Confirm = Callable[[Plan, DeviceResult], Awaitable[bool]]


@dataclass(frozen=True)
class ApplyOptions:
    on_error: Literal["continue", "stop"] = "continue"
    write_all: bool = False
    allow_broadcast: bool = False
    state_dir: str = ".deployer"
    backoff: float = 0.05  # first retry delay in seconds; doubles per attempt
    confirm: Confirm | None = None
    run_id: str | None = None  # journal lines in STATE/audit.jsonl carry it (None: no journal)
    applied: str | None = None  # what is being applied (recipe or plan file), recorded in the snapshot
    lock_timeout: float = 0.0  # seconds to wait for a device another run holds (0: fail at once)
    lock_dir: str | None = None  # None: lock.lock_dir() ($DEPLOYER_LOCK_DIR or a fixed folder)
    # called when a device's snapshot and device-started line are on disk, right before its first write
    on_writing: Callable[[DeviceResult], None] | None = None
    # a safe change (deployer.window): watch the health checks this long after the write, every health_interval
    soak: float | None = None  # seconds
    health_interval: float = 1.0
    confirm_within: float | None = None  # seconds to wait for `deployer confirm` before rolling back
    # a soak or confirmation writes a device whose health checks fail already (deployer.window.before)
    allow_unhealthy: bool = False
    command: str | None = None  # what started the run (the command line, or the caller), for the report
    hold_commit: bool = False  # do not send the profile's commit after the read-back (a rollback never commits)
    # the safe-change window (deployer.window) keeps a written device's lock until its commit or rollback:
    # asked after the read-back, True when it took the locks over (they are not released here then)
    keep_lock: Callable[[DeviceResult, list[DeviceLock]], bool] | None = None
    commit_owed: bool = False  # a retry of a device whose commit failed: sent even when nothing is left to write
    restoring: bool = False  # a window's own rollback: it goes on without a snapshot of its own (a full disk)
    lock_held: bool = False  # the caller holds the device's lock already (a window's own rollback): not taken again

    @property
    def window(self) -> bool:
        """A safe change: judged by the profile's health checks (before the change too)."""
        return self.soak is not None or self.confirm_within is not None

    @property
    def holds_commit(self) -> bool:
        """The commit waits: for the soak, the confirmation, or for ever (a rollback)."""
        return self.hold_commit or self.soak is not None or self.confirm_within is not None


def raise_if_cancelled() -> None:
    """Stop here when the task was cancelled (the run interrupted), even where the CancelledError itself got
    lost: Python 3.11's ``asyncio.wait_for`` (in pymodbus) swallows a cancellation that arrives together
    with the answer, and the device would go on writing after Ctrl-C."""
    task = asyncio.current_task()
    if task is not None and task.cancelling():
        raise asyncio.CancelledError


class Session:
    """Requests to one unit over one transport, with our own retries, each one recorded.

    pymodbus's retries are off (a late answer to a first copy would hide a double write);
    here every attempt is counted and reported. Timeouts and exception 06 (busy) are
    retried with exponential backoff; FC03 and FC16 are idempotent, so a resend is safe.

    ``trust`` (deployer.execute.trust) says which answers it believes: once a serial line went out of
    step, every value read is confirmed by a read after the line fell silent (that read is a request of
    its own, in ``records``), or ``Untrusted`` is raised.
    """

    def __init__(
        self, transport: tp.Transport, unit: int, *, retries: int, backoff: float, records: list[RequestRecord]
    ) -> None:
        self.transport = transport
        self.unit = unit
        self.retries = retries
        self.backoff = backoff
        self.records = records
        self.gap_reads = True  # False once the device refused a read across undeclared registers
        self.trust = Trust(transport)
        # what the executor is doing, stamped on every request it logs: the plan's step, and a deviation from it
        self.step: int | None = None
        self.deviation: str | None = None

    def _log(self, record: RequestRecord) -> None:
        record.step, record.deviation = self.step, self.deviation
        self.records.append(record)

    @contextlib.contextmanager
    def deviating(self, kind: str) -> Iterator[None]:
        """Requests sent inside are a deviation of ``kind`` from the current step (what only the device decided)."""
        was, self.deviation = self.deviation, kind
        try:
            yield
        finally:
            self.deviation = was

    async def _call(self, record: RequestRecord, op: Callable[[], Awaitable[list[int] | None]]) -> list[int] | None:
        self._log(record)
        attempt = 0
        while True:
            raise_if_cancelled()
            attempt += 1
            record.attempts = attempt
            try:
                result = await op()
                self.trust.after()
                record.result = "broadcast" if self.unit == 0 and record.function not in (1, 2, 3, 4) else "ok"
                record.exception_code = None
                return result
            except ExceptionResponse as e:
                self.trust.after()
                record.result, record.exception_code = "exception", e.code
                if e.code != 6 or attempt > self.retries:
                    raise
            except NoResponse as e:
                self.trust.after(e)
                record.result, record.exception_code = "no response", None
                if attempt > self.retries:
                    tries = f"{attempt} attempt{'s' if attempt > 1 else ''}"
                    if isinstance(e, BadAnswer):  # something answered, wrongly: say what, not "no answer"
                        raise DeviceGone(f"{e} (after {tries})") from None
                    hint = tp.no_answer_hint(self.transport.url, self.unit)
                    raise DeviceGone(f"no answer after {tries}{hint}") from None
            except asyncio.CancelledError:  # the run was interrupted while this request was out
                record.result, record.exception_code = "interrupted", None
                raise
            except ConnectionLost as e:
                self.trust.after(e)
                record.result, record.exception_code = "connection lost", None
                if attempt > self.retries:
                    raise DeviceGone(f"connection lost ({e})") from None
                await asyncio.sleep(self.backoff * 2 ** (attempt - 1))
                with contextlib.suppress(Unreachable):  # counts as an attempt; the next try reports
                    await self.transport.reconnect()
                continue
            await asyncio.sleep(self.backoff * 2 ** (attempt - 1))

    async def identify(self) -> dict[str, str] | None:
        """Device Identification (Function 43 / 14, basic objects: vendor, product code, revision) as
        texts by object name, or None for a device without it. One attempt, never an error: devices
        answer 01, or nothing, or drop the connection for a function they lack (it is opened again)."""
        rec = RequestRecord(43, 0, 1)
        self._log(rec)
        try:
            objects = await self.transport.read_device_identification(self.unit)
            self.trust.after()
        except ExceptionResponse as e:
            self.trust.after()
            rec.result, rec.exception_code = "exception", e.code
            return None
        except BadAnswer as e:  # something else came on the line: out of step
            self.trust.after(e)
            rec.result = "no response"
            return None
        except NoResponse:  # many devices keep silent on a function they lack: its answer, if ever, is no read's
            self.trust.overlook()
            rec.result = "no response"
            return None
        except ConnectionLost as e:
            self.trust.after(e)
            rec.result = "connection lost"
            with contextlib.suppress(Unreachable):
                await self.transport.reconnect()
            return None
        return {object_name(i): v.decode("latin-1").strip(" \x00") for i, v in sorted(objects.items())}

    async def read(self, address: int, count: int, function: int = 3) -> list[int]:
        """Registers (FC03, FC04) or bits as 0/1 (FC01, FC02) from ``address``; confirmed while in doubt
        (``trust``), else Untrusted."""
        t, unit = self.transport, self.unit
        op = lambda: t.read(function, address, count, unit)  # noqa: E731
        out = await self._call(RequestRecord(function, address, count), op)
        assert out is not None
        if not self.trust.doubting:
            return out
        seen = [out]
        for _ in range(CONFIRMATIONS):  # the line went out of step: a value is one two reads agree on
            with t.in_sync():
                again = await self._call(RequestRecord(function, address, count), op)
            self.trust.rereads += 1
            assert again is not None
            if t.answered_in_sync and again == seen[-1]:
                return again
            seen.append(again)
        raise self.trust.refusal(function, address, count, seen)

    async def write(self, req: WriteRequest) -> None:
        rec = RequestRecord(req.function, req.address, req.count)
        t, unit = self.transport, self.unit
        if req.function == 6:
            await self._call(rec, lambda: _none(t.write_register(req.address, req.registers[0], unit)))
        elif req.function == 5:
            await self._call(rec, lambda: _none(t.write_coil(req.address, bool(req.registers[0]), unit)))
        elif req.function == 15:
            await self._call(rec, lambda: _none(t.write_coils(req.address, [bool(b) for b in req.registers], unit)))
        else:
            await self._call(rec, lambda: _none(t.write_registers(req.address, list(req.registers), unit)))

    async def read_blocks(
        self, reads: Iterable[ReadRequest], profile: Profile | None = None, *, steps: Sequence[int] | None = None
    ) -> dict[int, int]:
        """Registers of every block, by key (Parameter.key; a holding register's key is its address).

        With ``profile``: when the device refuses a read across undeclared registers (exception 02), the rest of
        the reads, that one included, and every later read of this session go in gap-free blocks (the refused
        request stays in the report, followed by the fallback reads: a ``gap-free`` deviation). ``steps``: the
        plan step each block executes, stamped on its request (the gap-free blocks: on the first step they
        stand in for)."""
        todo = list(reads)
        numbers = list(steps) if steps is not None else None
        regs: dict[int, int] = {}
        gap_free = False  # the blocks from here on replace the planned ones (a deviation)
        i = 0
        while i < len(todo):
            if profile is not None and profile.limits.max_read_gap and not self.gap_reads:
                replaced = todo[i:]
                todo[i:] = gap_free_reads(profile, replaced)
                profile = None  # planned once: read on as planned
                gap_free = todo[i:] != replaced
                if numbers is not None:  # each new block stands in for the planned one holding its first register
                    planned = list(zip(replaced, numbers[i:], strict=True))
                    numbers[i:] = [
                        next(
                            (n for p, n in planned if read_key(p) <= read_key(r) < read_key(p) + p.count), planned[0][1]
                        )
                        for r in todo[i:]
                    ]
            r = todo[i]
            if numbers is not None:
                self.step = numbers[i]
            try:
                if gap_free:
                    with self.deviating("gap-free"):
                        values = await self.read(r.address, r.count, r.function)
                else:
                    values = await self.read(r.address, r.count, r.function)
            except ExceptionResponse as e:
                if (
                    profile is None
                    or not profile.limits.max_read_gap
                    or e.code != 2
                    or gap_free_reads(profile, [r]) == (r,)
                ):
                    raise  # not about a gap
                self.gap_reads = False
                continue
            key = read_key(r)
            regs.update(zip(range(key, key + r.count), values, strict=False))
            i += 1
        return regs


async def _none(aw: Awaitable[None]) -> None:
    await aw
