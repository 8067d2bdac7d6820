"""The executor: the only code that talks to devices.

connect -> identity check -> read current values -> snapshot (fsync) -> diff-aware plan ->
write requests in order (retries with backoff, partial-failure recovery) -> read back ->
commit actions -> DeviceResult. Everything it sends is recorded for the report.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import time
from collections import deque
from collections.abc import Awaitable, Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Literal, Protocol, TypeVar

from . import journal, lock
from . import transport as tp
from .diagnostics import UsageError
from .planner import Plan, ReadRequest, Target, WriteRequest, gap_free_reads, make_plan, plan_reads, plan_to_json
from .profile import Parameter, Profile, profile_ref
from .recipe import Recipe
from .report import DeviceResult, ParameterResult, Report, RequestRecord
from .snapshot import save_snapshot

Confirm = Callable[[Plan, DeviceResult], Awaitable[bool]]


class StalePlan(UsageError):
    """apply PLAN.json: the device no longer holds what the plan was made against."""


class Declined(UsageError):
    """The user answered no at the confirmation prompt."""


@dataclass(frozen=True)
class ApplyOptions:
    on_error: Literal["continue", "stop"] = "continue"
    write_all: bool = False
    allow_broadcast: bool = False
    state_dir: str = ".deployer"
    backoff: float = 0.05  # first retry delay in seconds; doubles per attempt
    expected: Plan | None = None  # apply PLAN.json: run exactly this plan
    confirm: Confirm | None = None
    run_id: str | None = None  # journal lines in STATE/audit.jsonl carry it (None: no journal)
    applied: str | None = None  # what is being applied (recipe or plan file), recorded in the snapshot
    lock_timeout: float = 0.0  # seconds to wait for a device another run holds (0: fail at once)
    lock_dir: str | None = None  # None: $DEPLOYER_LOCK_DIR or <tmp>/deployer-locks


class DeviceGone(tp.TransportError):
    """The device stopped answering and the retry budget is spent."""


class Session:
    """Requests to one unit over one transport, with our own retries, each one recorded.

    pymodbus's retries are off (a late answer to a first copy would hide a double write);
    here every attempt is counted and reported. Timeouts and exception 06 (busy) are
    retried with exponential backoff; FC03 and FC16 are idempotent, so a resend is safe.
    """

    def __init__(self, transport: tp.Transport, unit: int, *, retries: int, backoff: float,
                 records: list[RequestRecord]) -> None:
        self.transport = transport
        self.unit = unit
        self.retries = retries
        self.backoff = backoff
        self.records = records
        self.gap_reads = True  # False once the device refused a read across undeclared registers

    async def _call(self, record: RequestRecord, op: Callable[[], Awaitable[list[int] | None]]) -> list[int] | None:
        self.records.append(record)
        attempt = 0
        while True:
            attempt += 1
            record.attempts = attempt
            try:
                result = await op()
                record.result = "broadcast" if self.unit == 0 and record.function != 3 else "ok"
                record.exception_code = None
                return result
            except tp.ExceptionResponse as e:
                record.result, record.exception_code = "exception", e.code
                if e.code != 6 or attempt > self.retries:
                    raise
            except tp.NoResponse:
                record.result, record.exception_code = "no response", None
                if attempt > self.retries:
                    hint = tp.no_answer_hint(self.transport.url, self.unit)
                    raise DeviceGone(f"no answer after {attempt} attempt{'s' if attempt > 1 else ''}{hint}") from None
            except tp.ConnectionLost as e:
                record.result, record.exception_code = "connection lost", None
                if attempt > self.retries:
                    raise DeviceGone(f"connection lost ({e})") from None
                await asyncio.sleep(self.backoff * 2 ** (attempt - 1))
                with contextlib.suppress(tp.Unreachable):  # counts as an attempt; the next try reports
                    await self.transport.reconnect()
                continue
            await asyncio.sleep(self.backoff * 2 ** (attempt - 1))

    async def read(self, address: int, count: int) -> list[int]:
        rec = RequestRecord(3, address, count)
        out = await self._call(rec, lambda: self.transport.read_holding_registers(address, count, self.unit))
        assert out is not None
        return out

    async def write(self, req: WriteRequest) -> None:
        rec = RequestRecord(req.function, req.address, req.count)
        t, unit = self.transport, self.unit
        if req.function == 6:
            await self._call(rec, lambda: _none(t.write_register(req.address, req.registers[0], unit)))
        else:
            await self._call(rec, lambda: _none(t.write_registers(req.address, list(req.registers), unit)))

    async def read_blocks(self, reads: Iterable[ReadRequest], profile: Profile | None = None) -> dict[int, int]:
        """Registers of every block. With ``profile``: when the device refuses a read across
        undeclared registers (exception 02), the rest of the reads, that one included, and every
        later read of this session go in gap-free blocks (the refused request stays in the
        report, followed by the fallback reads)."""
        todo = list(reads)
        regs: dict[int, int] = {}
        i = 0
        while i < len(todo):
            if profile is not None and profile.limits.max_read_gap and not self.gap_reads:
                todo[i:] = gap_free_reads(profile, todo[i:])
                profile = None  # planned once: read on as planned
            r = todo[i]
            try:
                values = await self.read(r.address, r.count)
            except tp.ExceptionResponse as e:
                if (profile is None or not profile.limits.max_read_gap or e.code != 2
                        or gap_free_reads(profile, [r]) == (r,)):
                    raise  # not about a gap
                self.gap_reads = False
                continue
            regs.update(zip(range(r.address, r.address + r.count), values, strict=False))
            i += 1
        return regs


async def _none(aw: Awaitable[None]) -> None:
    await aw


def values_of(params: Iterable[Parameter], regs: Mapping[int, int]) -> dict[str, tuple[int, ...]]:
    """Parameter name -> registers, for every parameter whose registers were all read."""
    out = {}
    for p in params:
        words = [regs.get(a) for a in range(p.address, p.end)]
        if all(w is not None for w in words):
            out[p.name] = tuple(w for w in words if w is not None)
    return out


async def check_identity(session: Session, profile: Profile) -> str | None:
    """None if every identity register holds its expected value, else why not."""
    for chk in profile.identity:
        (value,) = await session.read(chk.address, 1)
        if value != chk.raw:
            what = f" ({chk.description})" if chk.description else ""
            return (f"identity check failed: register 0x{chk.address:04X}{what} holds 0x{value:04X}, expected "
                    f"0x{chk.raw:04X}: another kind of device answers here")
    return None


def _results(recipe: Recipe) -> dict[str, ParameterResult]:
    return {d.name: ParameterResult(d.name, d.parameter.address, d.parameter.count, d.text, d.registers)
            for d in recipe.desired}


def _text(p: Parameter, regs: Sequence[int] | None) -> str | None:
    if regs is None:
        return None
    try:
        return p.format_registers(tuple(regs))
    except Exception:  # a value the codec cannot show (e.g. NaN): show raw words
        return " ".join(f"{w:04X}h" for w in regs)


async def apply_device(recipe: Recipe, url: tp.DeviceURL, unit: int, *, name: str | None = None,
                       options: ApplyOptions | None = None) -> DeviceResult:
    """Apply ``recipe`` to one device and say exactly what it holds afterwards.

    The device's lock is held from before the first read until the read-back is done, so no
    other run on this machine can write it in between.
    """
    opts = options or ApplyOptions()
    prof = recipe.profile
    res = DeviceResult(name or recipe.name, tp.describe(url), unit, prof.id, profile_ref=profile_ref(prof))
    results = _results(recipe)
    res.parameters = list(results.values())
    if unit == 0 and not opts.allow_broadcast:
        raise UsageError("unit 0 is broadcast (no device answers, nothing can be verified); "
                         "pass --allow-broadcast to send it anyway")
    try:
        held = await lock.acquire(lock.device_key(url.bus, unit), timeout=opts.lock_timeout,
                                  command=lock.command_line(), directory=opts.lock_dir)
    except lock.Locked as e:
        res.status, res.error = "unreachable", f"{e}; nothing was sent"
        return res
    try:
        if held.stale:
            res.notices.append(held.stale)
        target = Target(tp.describe(url), unit, profile_ref(prof))
        transport = tp.open_transport(url)
        try:
            await transport.connect()
        except tp.Unreachable as e:
            res.status, res.error = "unreachable", str(e)
            return res
        session = Session(transport, unit, retries=url.retries, backoff=opts.backoff, records=res.requests)
        try:
            if unit == 0:
                await _broadcast(session, recipe, target, opts, res, results)
            else:
                await _apply(session, recipe, target, opts, res, results)
        finally:
            await transport.close()
        res.settle()
        if res.snapshot is not None and opts.run_id is not None:
            await asyncio.to_thread(journal.device_finished, opts.state_dir, opts.run_id, res)
        return res
    finally:
        held.release()


async def _broadcast(session: Session, recipe: Recipe, target: Target, opts: ApplyOptions, res: DeviceResult,
                     results: dict[str, ParameterResult]) -> None:
    """Unit 0: nobody answers, so nothing is read; every parameter is sent and unverified.

    The device ends ``sent`` when every request went out, ``failed`` when one could not be sent.
    """
    plan = opts.expected or make_plan(recipe, target, None, write_all=True)
    queue = deque(plan.writes)
    while queue:
        req = queue.popleft()
        try:
            await session.write(req)
        except DeviceGone as e:
            for n in req.parameters:
                results[n].status, results[n].error = "unverified", f"broadcast may not have gone out: {e}"
            for rest in queue:
                for n in rest.parameters:
                    results[n].status, results[n].error = "skipped", "not sent: an earlier broadcast request failed"
            res.status, res.error = "failed", f"broadcast request at 0x{req.address:04X} could not be sent: {e}"
            return
        for n in req.parameters:
            results[n].status, results[n].error = "unverified", "broadcast: no device answers"
    res.status = "sent"


async def _apply(session: Session, recipe: Recipe, target: Target, opts: ApplyOptions, res: DeviceResult,
                 results: dict[str, ParameterResult]) -> None:
    prof = recipe.profile
    params = [d.parameter for d in recipe.desired]
    # 1. before any write: identity and current values; a silent device here is "unreachable"
    try:
        why = await check_identity(session, prof)
        if why:
            res.status, res.error = "failed", f"{why}; nothing was written"
            return
        offline = make_plan(recipe, target, None)
        before = values_of(params, await session.read_blocks(offline.reads, prof))
    except DeviceGone as e:
        res.status, res.error = "unreachable", f"{e}; nothing was written"
        return
    except tp.ExceptionResponse as e:
        res.status, res.error = "failed", f"reading the current values answered {e}; nothing was written"
        return
    if not session.gap_reads:  # the refused read is in res.requests; say why the reads that follow differ
        res.notices.append("the device refused a read across undeclared registers (exception 02): "
                           "it is read in gap-free blocks (the profile's limits.max_read_gap is not for it)")
    for n, regs in before.items():
        results[n].before_raw, results[n].before = regs, _text(prof.parameter(n), regs)

    # 2. the plan: a saved one must still match the device, else a fresh diff-aware plan
    if opts.expected is not None:
        changed = [pp.name for pp in opts.expected.parameters
                   if pp.current_raw is not None and before.get(pp.name) != pp.current_raw]
        if changed:
            raise StalePlan(
                "the device changed since the plan was made (" + ", ".join(
                    f"{n}: now {_text(prof.parameter(n), before.get(n))}" for n in changed)
                + "); make a new plan")
        plan = opts.expected
    else:
        plan = make_plan(recipe, target, before, write_all=opts.write_all)
    for pp in plan.parameters:
        if pp.action == "unchanged":
            results[pp.name].status = "unchanged"
    if not plan.writes:
        _verify(results, prof, before, written=set())
        return
    if opts.confirm is not None and not await opts.confirm(plan, res):
        raise Declined("nothing was written (declined)")

    # 3. the snapshot is on disk before the first write, and the journal says this device is being written
    #    (in a thread: two fsyncs must not stall the other devices of a fleet)
    res.snapshot = await asyncio.to_thread(save_snapshot, opts.state_dir, res.name, recipe, before, res.url,
                                           res.unit, applied=opts.applied)
    if opts.run_id is not None:
        digest = hashlib.sha256(json.dumps(plan_to_json(plan), sort_keys=True).encode()).hexdigest()
        await asyncio.to_thread(journal.device_started, opts.state_dir, opts.run_id, name=res.name, url=res.url,
                                unit=res.unit, snapshot=res.snapshot, plan_digest=digest)

    # 4. writes, in plan order; recover from partial failures
    written, gone = await _write_all(session, prof, plan, opts, results)

    # 5. read back everything the plan reads, compare raw values (after a silence too: it may be back)
    try:
        after = values_of(params, await session.read_blocks(plan.reads, prof))
    except (DeviceGone, tp.ExceptionResponse) as e:
        for n in written:
            if results[n].error == PENDING:
                results[n].error = f"read-back failed: {e}"
        return
    _verify(results, prof, after, written)
    if gone:
        return

    # 6. commit (e.g. store to EEPROM) only when everything is verified
    if prof.commit and all(r.status in ("ok", "unchanged") for r in results.values()):
        for action in prof.commit:
            fn = prof.limits.write_function
            reqs = ([WriteRequest(6, action.address + i, (w,), ("(commit)",)) for i, w in enumerate(action.registers)]
                    if fn == 6 else [WriteRequest(16, action.address, action.registers, ("(commit)",))])
            try:
                for r in reqs:
                    await session.write(r)
            except (DeviceGone, tp.ExceptionResponse) as e:
                res.status, res.error = "partial", f"commit '{action.description or hex(action.address)}' failed: {e}"
                return


PENDING = "not read back yet"


def _attempted(results: dict[str, ParameterResult], names: Iterable[str], written: set[str],
               error: str = PENDING) -> None:
    """Mark parameters as sent: unverified until the read-back says ok or mismatch."""
    for n in names:
        written.add(n)
        results[n].status, results[n].error = "unverified", error


async def _write_all(session: Session, prof: Profile, plan: Plan, opts: ApplyOptions,
                     results: dict[str, ParameterResult]) -> tuple[set[str], bool]:
    """Send the plan's writes. Returns the names sent, and whether the device went away."""
    desired = {pp.name: pp.desired_raw for pp in plan.parameters}
    written: set[str] = set()
    queue = deque(plan.writes)
    stopped = False
    while queue:
        req = queue.popleft()
        if stopped:
            for n in req.parameters:
                if results[n].status != "failed":
                    results[n].status = "skipped"
            continue
        try:
            await session.write(req)
            _attempted(results, req.parameters, written)
        except tp.ExceptionResponse as e:
            follow_up = await _recover(session, prof, req, e, desired, results, written)
            if opts.on_error == "continue":
                if follow_up is not None:
                    queue.appendleft(follow_up)
            else:
                stopped = True
                if follow_up is not None:
                    for n in follow_up.parameters:
                        results[n].status = "skipped"
        except DeviceGone as e:
            # the request may or may not have been applied: the read-back (if any) decides
            _attempted(results, req.parameters, written, f"device stopped answering: {e}")
            for rest in queue:
                for n in rest.parameters:
                    results[n].status = "skipped"
            return written, True
    return written, False


async def _recover(session: Session, prof: Profile, req: WriteRequest, exc: tp.ExceptionResponse,
                   desired: Mapping[str, tuple[int, ...]], results: dict[str, ParameterResult],
                   written: set[str]) -> WriteRequest | None:
    """After an exception: read the request's registers back to see which took.

    Devices write in address order and stop at the bad value, so the first parameter that
    does not hold its desired value is the rejected one; the ones after it were not written
    and go into a follow-up request. Write-only parameters cannot be read: they count as
    taken when a later parameter took.
    """
    params = sorted({prof.parameter(n) for n in req.parameters}, key=lambda p: p.address)
    error = f"exception {exc.code:02d} ({tp.ExceptionResponse.NAMES.get(exc.code, 'unknown')})"
    try:
        now = values_of(params, await session.read_blocks(plan_reads(prof, [p.name for p in params if p.readable]),
                                                           prof))
    except (DeviceGone, tp.ExceptionResponse) as e:  # cannot tell what took: say so, send nothing more of it
        _attempted(results, req.parameters, written, f"{error}; reading back failed: {e}")
        return None
    rejected: Parameter | None = None
    unknown: list[str] = []  # write-only parameters seen so far
    for p in params:
        if not p.readable:
            unknown.append(p.name)
            continue
        if now.get(p.name) == desired[p.name]:
            _attempted(results, [*unknown, p.name], written)
            unknown = []
            continue
        rejected = p
        break
    _attempted(results, unknown, written, f"write-only, next to a rejected value ({error})")
    if rejected is None:  # everything took although the device complained: the read-back decides
        return None
    results[rejected.name].status, results[rejected.name].error = "failed", error
    rest = [p for p in params if p.address > rejected.address]
    if not rest or req.function == 6:  # an FC06 request carries one register: nothing after it
        return None
    regs = tuple(w for p in rest for w in desired[p.name])
    return replace(req, address=rest[0].address, registers=regs, parameters=tuple(p.name for p in rest))


def _verify(results: dict[str, ParameterResult], prof: Profile, after: Mapping[str, tuple[int, ...]],
            written: set[str]) -> None:
    """Statuses from the read-back: what was sent must read back equal; the rest is reported as is."""
    for n, r in results.items():
        p = prof.parameter(n)
        got = after.get(n)
        if got is not None:
            r.after_raw, r.after = got, _text(p, got)
        if r.status in ("failed", "skipped"):
            continue
        if got is None:  # not read back: sent ones stay unverified, with the reason
            if n in written and r.error == PENDING:
                r.error = "write-only: cannot be read back"
            continue
        if got == r.desired_raw:
            r.status, r.error = ("ok" if n in written else "unchanged"), None
            continue
        reads_back = f"reads back {_text(p, got)} ({' '.join(f'{w:04X}h' for w in got)})"
        if r.error and r.error.startswith("device stopped answering"):
            r.error = f"{r.error}; {reads_back}"  # no answer and not applied: unverified, not "accepted"
        else:
            r.status, r.error = "mismatch", reads_back


# ---- reading without writing: plan --device, diff, pull ----------------------------------


async def read_current(profile: Profile, names: Sequence[str], url: tp.DeviceURL, unit: int,
                       records: list[RequestRecord] | None = None, *, backoff: float = 0.05,
                       ) -> dict[str, tuple[int, ...]]:
    """Current registers of the named readable parameters. Raises tp.Unreachable / UsageError."""
    if unit == 0:
        raise UsageError("unit 0 is broadcast: nothing can be read from it")
    transport = tp.open_transport(url)
    await transport.connect()
    session = Session(transport, unit, retries=url.retries, backoff=backoff,
                      records=records if records is not None else [])
    try:
        why = await check_identity(session, profile)
        if why:
            raise tp.Unreachable(why)
        params = [profile.parameter(n) for n in names]
        reads = plan_reads(profile, [p.name for p in params if p.readable])
        return values_of(params, await session.read_blocks(reads, profile))
    except DeviceGone as e:
        raise tp.Unreachable(f"{tp.describe(url)} unit {unit}: {e}") from None
    except tp.ExceptionResponse as e:
        raise tp.Unreachable(f"{tp.describe(url)} unit {unit}: reading answered {e}") from None
    finally:
        await transport.close()


# ---- fleets ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Job:
    name: str
    recipe: Recipe
    url: tp.DeviceURL
    unit: int


@dataclass(frozen=True)
class ReadJob:
    """Read some parameters of one fleet device (plan, diff, pull)."""

    name: str
    profile: Profile
    names: tuple[str, ...]
    url: tp.DeviceURL
    unit: int


class _HasBus(Protocol):
    @property
    def url(self) -> tp.DeviceURL: ...


_J = TypeVar("_J", bound=_HasBus)


async def on_buses(jobs: Sequence[_J], parallel: int, work: Callable[[_J], Awaitable[None]]) -> None:
    """Run ``work`` for every job, at most ``parallel`` at once; jobs on one bus strictly one after the other."""
    buses: dict[str, list[_J]] = {}
    for j in jobs:
        buses.setdefault(j.url.bus, []).append(j)
    gate = asyncio.Semaphore(max(1, parallel))

    async def run_bus(group: list[_J]) -> None:
        for j in group:  # half-duplex bus: the next device starts when the last one is done
            async with gate:
                await work(j)

    await asyncio.gather(*(run_bus(g) for g in buses.values()))


def skipped_result(job: Job, reason: str) -> DeviceResult:
    """A device a fleet run did not start: nothing was sent to it."""
    r = DeviceResult(job.name, tp.describe(job.url), job.unit, job.recipe.profile.id, status="skipped", error=reason,
                     profile_ref=profile_ref(job.recipe.profile))
    r.parameters = list(_results(job.recipe).values())
    return r


async def apply_many(jobs: Sequence[Job], *, parallel: int = 8, options: ApplyOptions | None = None,
                     recipe_name: str | None = None,
                     on_done: Callable[[DeviceResult], None] | None = None,
                     on_start: Callable[[Job], None] | None = None,
                     batches: Sequence[int] | None = None, max_failures: int | None = None) -> Report:
    """Apply to many devices: in parallel, except that devices on one bus go one at a time.

    ``batches`` (sizes, in job order) stage the rollout: each batch finishes before the next
    starts, and a batch in which no device ended ok ends the rollout (Ansible's ``serial``).
    ``max_failures``: once that many devices ended failed or partial, no new device starts.
    Devices never started are in the report as ``skipped`` with the reason.
    """
    started = time.monotonic()
    done: dict[str, DeviceResult] = {}
    failures = 0
    stop: str | None = None

    async def one(j: Job) -> None:
        nonlocal failures, stop
        if stop is not None:  # checked when the device's turn comes, not when it was queued
            done[j.name] = skipped_result(j, stop)
            return
        if on_start:
            on_start(j)
        t = time.monotonic()
        try:
            r = await apply_device(j.recipe, j.url, j.unit, name=j.name, options=options)
        except (StalePlan, Declined):
            raise
        except UsageError as e:
            r = DeviceResult(j.name, tp.describe(j.url), j.unit, j.recipe.profile.id, status="failed", error=str(e),
                             profile_ref=profile_ref(j.recipe.profile))
            r.parameters = list(_results(j.recipe).values())
        r.seconds = time.monotonic() - t
        done[j.name] = r
        if r.status in ("failed", "partial"):
            failures += 1
            if max_failures is not None and failures >= max_failures and stop is None:
                stop = (f"not started: {failures} device{'s' if failures != 1 else ''} ended failed or partial "
                        f"(--max-failures {max_failures})")
        if on_done:
            on_done(r)

    sizes = list(batches) if batches else [len(jobs)]
    pos = 0
    for number, size in enumerate(sizes, 1):
        batch = jobs[pos:pos + size]
        pos += size
        await on_buses(batch, parallel, one)
        ran = [done[j.name] for j in batch if done[j.name].status != "skipped"]
        if stop is None and pos < len(jobs) and ran and all(r.status != "ok" for r in ran):
            which = f"the canary {ran[0].name}" if len(batch) == 1 else f"all {len(ran)} devices"
            stop = f"not started: batch {number} failed ({which} did not end ok)"
    return Report(recipe_name, [done[j.name] for j in jobs], time.monotonic() - started)


async def read_many(jobs: Sequence[ReadJob], *, parallel: int = 8,
                    on_done: Callable[[str, str | None], None] | None = None,
                    ) -> dict[str, dict[str, tuple[int, ...]] | tp.TransportError | UsageError]:
    """Current values of many devices (fleet plan, diff, pull): per device its registers or why not."""
    out: dict[str, dict[str, tuple[int, ...]] | tp.TransportError | UsageError] = {}

    async def one(j: ReadJob) -> None:
        try:
            out[j.name] = await read_current(j.profile, j.names, j.url, j.unit)
        except (tp.TransportError, UsageError) as e:
            out[j.name] = e
        if on_done:
            res = out[j.name]
            on_done(j.name, str(res) if isinstance(res, Exception) else None)

    await on_buses(jobs, parallel, one)
    return {j.name: out[j.name] for j in jobs}
