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
from typing import Literal, Protocol, TypeVar, cast

from . import codec, journal, lock
from . import transport as tp
from .diagnostics import UsageError
from .durable import Line, durable, queue
from .planner import (
    Plan,
    ReadRequest,
    Target,
    WriteRequest,
    gap_free_reads,
    make_plan,
    merge_fields,
    plan_reads,
    plan_to_json,
)
from .profile import Parameter, Profile, WriteAction, profile_ref
from .recipe import Recipe
from .report import DeviceResult, ParameterResult, Report, RequestRecord, show_registers
from .snapshot import snapshot_file

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
    return _values(((p.name, p.address, p.count) for p in params), regs)


def _values(layout: Iterable[tuple[str, int, int]], regs: Mapping[int, int]) -> dict[str, tuple[int, ...]]:
    out: dict[str, tuple[int, ...]] = {}
    get = regs.get
    for name, a, n in layout:
        if n == 1:  # most parameters: no generator per value (a fleet does this 200 times per device)
            w = get(a)
            if w is not None:
                out[name] = (w,)
            continue
        words = tuple(get(a + i) for i in range(n))
        if None not in words:
            out[name] = cast(tuple[int, ...], words)  # no None left
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


async def check_preconditions(session: Session, profile: Profile) -> str | None:
    """None if every precondition holds (e.g. 'drive stopped'), else which one does not."""
    for c in profile.preconditions:
        (word,) = await session.read(c.address, 1)
        if not c.holds(word):
            return f"precondition failed: {c.what()} is {codec.extract_field(word, c.mask)}, expected {c.equals}"
    return None


async def _send_actions(session: Session, prof: Profile, actions: Iterable[WriteAction]) -> None:
    """The profile's own writes (unlock, commit, lock), each followed by its wait."""
    for action in actions:
        reqs = ([WriteRequest(6, action.address + i, (w,), ()) for i, w in enumerate(action.registers)]
                if prof.limits.write_function == 6 else [WriteRequest(16, action.address, action.registers, ())])
        for r in reqs:
            await session.write(r)
        if action.wait_ms:
            await asyncio.sleep(action.wait_ms / 1000)


def _results(recipe: Recipe) -> dict[str, ParameterResult]:
    return {name: ParameterResult(name, a, n, text, regs, parameter=p) for name, a, n, text, regs, p
            in _shared(recipe).results}


@dataclass(frozen=True)
class _Shared:
    """What every device applying one recipe shares, worked out once (a fleet has hundreds of them)."""

    reads: tuple[ReadRequest, ...]  # the blocks covering the readable parameters (snapshot, read-back)
    layout: tuple[tuple[str, int, int], ...]  # name, address, registers of each recipe parameter
    results: tuple[tuple[str, int, int, str, tuple[int, ...], Parameter], ...]  # a ParameterResult's fields


_SHARED: dict[int, tuple[Recipe, _Shared]] = {}
_SHARED_KEPT = 64  # recipes remembered (a long-lived API user loads new ones)


def _shared(recipe: Recipe) -> _Shared:
    hit = _SHARED.get(id(recipe))
    if hit is None or hit[0] is not recipe:  # the recipe is kept in the entry, so its id is not reused
        while len(_SHARED) >= _SHARED_KEPT:
            del _SHARED[next(iter(_SHARED))]  # the oldest
        params = [d.parameter for d in recipe.desired]
        hit = _SHARED[id(recipe)] = (recipe, _Shared(
            plan_reads(recipe.profile, [p.name for p in params if p.readable]),
            tuple((p.name, p.address, p.count) for p in params),
            tuple((d.name, d.parameter.address, d.parameter.count, d.text, d.registers, d.parameter)
                  for d in recipe.desired)))
    return hit[1]


async def apply_device(recipe: Recipe, url: tp.DeviceURL, unit: int, *, name: str | None = None,
                       options: ApplyOptions | None = None) -> DeviceResult:
    """Apply ``recipe`` to one device and say exactly what it holds afterwards.

    The device's lock is held from before the first read until the read-back is done, so no
    other run on this machine can write it in between. With a journal (``options.run_id``) it
    returns once the ``device-finished`` line is on disk.
    """
    res, finishing = await _apply_device(recipe, url, unit, name=name, options=options)
    if finishing is not None:
        await finishing
    return res


async def _apply_device(recipe: Recipe, url: tp.DeviceURL, unit: int, *, name: str | None,
                        options: ApplyOptions | None) -> tuple[DeviceResult, Awaitable[object] | None]:
    """``apply_device``, handing back the wait for its ``device-finished`` line instead of waiting:
    a fleet frees the device's slot (and lock) for the next device while that fsync happens."""
    opts = options or ApplyOptions()
    prof = recipe.profile
    res = DeviceResult(name or recipe.name, tp.describe(url), unit, prof.id, profile_ref=profile_ref(prof))
    results = _results(recipe)
    res.parameters = list(results.values())
    if unit == 0 and not opts.allow_broadcast:
        raise UsageError("unit 0 is broadcast (no device answers, nothing can be verified); "
                         "pass --allow-broadcast to send it anyway")
    if unit == 0 and (prof.preconditions or any(d.parameter.mask for d in recipe.desired)):
        raise UsageError("a broadcast cannot read: bit fields (which keep the register's other bits) and "
                         f"preconditions of profile {prof.id} need a device that answers")
    try:
        held = await lock.acquire_device(url.bus, unit, timeout=opts.lock_timeout, command=lock.command_line(),
                                         directory=opts.lock_dir)
    except lock.Locked as e:
        res.status, res.error = "unreachable", f"{e}; nothing was sent"
        return res, None
    try:
        res.notices.extend(h.stale for h in held if h.stale)
        target = Target(tp.describe(url), unit, profile_ref(prof))
        transport = tp.open_transport(url)
        try:
            await transport.connect()
        except tp.Unreachable as e:
            res.status, res.error = "unreachable", str(e)
            return res, None
        session = Session(transport, unit, retries=url.retries, backoff=opts.backoff, records=res.requests)
        try:
            if unit == 0:
                await _broadcast(session, recipe, target, opts, res, results)
            else:
                await _apply(session, recipe, target, opts, res, results)
        finally:
            await transport.close()
        res.settle()
        if res.snapshot is not None and opts.run_id is not None:  # queued now, after the read-back
            return res, queue(Line(journal.path_of(opts.state_dir), journal.device_finished(opts.run_id, res)))
        return res, None
    finally:
        for h in reversed(held):
            h.release()


async def _broadcast(session: Session, recipe: Recipe, target: Target, opts: ApplyOptions, res: DeviceResult,
                     results: dict[str, ParameterResult]) -> None:
    """Unit 0: nobody answers, so nothing is read; every parameter is sent and unverified.

    The device ends ``sent`` when every request went out, ``failed`` when one could not be sent.
    """
    plan = opts.expected or make_plan(recipe, target, None, write_all=True)
    pending = deque(plan.writes)
    while pending:
        req = pending.popleft()
        try:
            await session.write(req)
        except DeviceGone as e:
            for n in req.parameters:
                results[n].status, results[n].error = "unverified", f"broadcast may not have gone out: {e}"
            for rest in pending:
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
    shared = _shared(recipe)
    # 1. before any write: identity and current values; a silent device here is "unreachable"
    try:
        why = await check_identity(session, prof)
        if why:
            res.status, res.error = "failed", f"{why}; nothing was written"
            return
        before = _values(shared.layout, await session.read_blocks(shared.reads, prof))
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
        results[n].before_raw = regs

    # 2. the plan: a saved one must still match the device, else a fresh diff-aware plan
    if opts.expected is not None:
        changed = [pp.name for pp in opts.expected.parameters
                   if pp.current_raw is not None and not prof.parameter(pp.name).same_value(before.get(pp.name),
                                                                                            pp.current_raw)]
        if changed:
            raise StalePlan(
                "the device changed since the plan was made (" + ", ".join(
                    f"{n}: now {show_registers(prof.parameter(n), before.get(n))}" for n in changed)
                + "); make a new plan")
        plan = opts.expected
    else:
        plan = make_plan(recipe, target, before, write_all=opts.write_all, reads=shared.reads)
    for pp in plan.parameters:
        if pp.action == "unchanged":
            results[pp.name].status = "unchanged"
    for pp in plan.parameters:  # a field's register goes whole: report the word planned
        if prof.parameter(pp.name).mask:
            results[pp.name].desired_raw = pp.desired_raw
    if not plan.writes:
        _verify(results, prof, before, written=set())
        return
    # guards (e.g. "drive stopped") only matter when something is to be written
    try:
        why = await check_preconditions(session, prof)
    except (DeviceGone, tp.ExceptionResponse) as e:
        why = f"reading the preconditions failed: {e}"
    if why:
        res.status, res.error = "failed", f"{why}; nothing was written"
        return
    if opts.confirm is not None and not await opts.confirm(plan, res):
        raise Declined("nothing was written (declined)")

    # 3. the snapshot is on disk before the first write, and the journal says this device is being written:
    #    both made durable by the group-commit thread, sharing fsyncs with the other devices of a fleet
    snap = snapshot_file(opts.state_dir, res.name, recipe, before, res.url, res.unit, applied=opts.applied)
    if opts.run_id is not None:
        digest = hashlib.sha256(json.dumps(plan_to_json(plan), sort_keys=True).encode()).hexdigest()
        snap.journal = journal.path_of(opts.state_dir)
        snap.line = journal.device_started(opts.run_id, name=res.name, url=res.url, unit=res.unit, plan_digest=digest)
    res.snapshot = await durable(snap)

    # 4. unlock, writes in plan order (recovering from partial failures), read-back, commit, lock
    if prof.unlock:
        try:
            await _send_actions(session, prof, prof.unlock)
        except (DeviceGone, tp.ExceptionResponse) as e:
            res.status, res.error = "failed", f"unlock failed: {e}; no parameter was written"
            return
    try:
        await _write_verify_commit(session, prof, recipe, plan, opts, res, results)
    finally:
        if prof.unlock and prof.lock:
            try:
                await _send_actions(session, prof, prof.lock)
            except (DeviceGone, tp.ExceptionResponse) as e:
                res.status = "partial"
                res.error = f"{res.error + '; ' if res.error else ''}lock failed: {e}; the device may be left unlocked"
    res.notices.extend(f"{n} takes effect after a power cycle" for n, r in results.items()
                       if r.status == "ok" and prof.parameter(n).restart)


async def _write_verify_commit(session: Session, prof: Profile, recipe: Recipe, plan: Plan, opts: ApplyOptions,
                               res: DeviceResult, results: dict[str, ParameterResult]) -> None:
    written, gone = await _write_all(session, prof, plan, opts, results)

    # read back everything the plan reads, compare raw values (after a silence too: it may be back)
    try:
        after = _values(_shared(recipe).layout, await session.read_blocks(plan.reads, prof))
    except (DeviceGone, tp.ExceptionResponse) as e:
        for n in written:
            if results[n].error == PENDING:
                results[n].error = f"read-back failed: {e}"
        return
    _verify(results, prof, after, written)
    if gone:
        return

    # commit (e.g. store to EEPROM) only when everything is verified
    if prof.commit and all(r.status in ("ok", "unchanged") for r in results.values()):
        for action in prof.commit:
            try:
                await _send_actions(session, prof, [action])
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
    desired = {pp.name: tuple(pp.desired_raw) for pp in plan.parameters}
    written: set[str] = set()
    pending = deque(plan.writes)
    stopped = False
    while pending:
        req = pending.popleft()
        if stopped:
            for n in req.parameters:
                if results[n].status != "failed":
                    results[n].status = "skipped"
            continue
        try:
            req = await _remerge(session, prof, req, desired, results)
        except (DeviceGone, tp.ExceptionResponse) as e:  # nothing of this request was sent
            for n in req.parameters:
                results[n].status, results[n].error = "failed", f"reading the register to keep its other bits: {e}"
            stopped = opts.on_error == "stop"
            continue
        try:
            await session.write(req)
            _attempted(results, req.parameters, written)
            wait = prof.wait_after(req.stage)
            if wait and (not pending or pending[0].stage != req.stage):
                await asyncio.sleep(wait / 1000)
        except tp.ExceptionResponse as e:
            follow_up = await _recover(session, prof, req, e, desired, results, written)
            if opts.on_error == "continue":
                if follow_up is not None:
                    pending.appendleft(follow_up)
            else:
                stopped = True
                if follow_up is not None:
                    for n in follow_up.parameters:
                        results[n].status = "skipped"
        except DeviceGone as e:
            # the request may or may not have been applied: the read-back (if any) decides
            _attempted(results, req.parameters, written, f"device stopped answering: {e}")
            for rest in pending:
                for n in rest.parameters:
                    results[n].status = "skipped"
            return written, True
    return written, False


async def _remerge(session: Session, prof: Profile, req: WriteRequest, desired: dict[str, tuple[int, ...]],
                   results: dict[str, ParameterResult]) -> WriteRequest:
    """Bit fields: read their registers right before the write and merge the new bits into what the
    device holds now (another field may have changed since the snapshot: keep it, never guess)."""
    fields = [p for p in (prof.parameter(n) for n in req.parameters) if p.mask and p.readable]
    if not fields:
        return req
    fresh = await session.read_blocks(plan_reads(prof, [f.name for f in fields]))
    regs = list(req.registers)
    for a in sorted({f.address for f in fields}):
        mates = [prof.parameter(n) for n in req.parameters if prof.parameter(n).address == a]
        word = merge_fields(mates, [desired[m.name][0] for m in mates], fresh[a])
        regs[a - req.address] = word
        for m in mates:
            desired[m.name] = results[m.name].desired_raw = (word,)
    return replace(req, registers=tuple(regs))


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
        if p.same_value(now.get(p.name), desired[p.name]):
            _attempted(results, [*unknown, p.name], written)
            unknown = []
            continue
        rejected = p
        break
    _attempted(results, unknown, written, f"write-only, next to a rejected value ({error})")
    if rejected is None:  # everything took although the device complained: the read-back decides
        return None
    results[rejected.name].status, results[rejected.name].error = "failed", error
    for p in params:  # bit fields of the rejected register went with it
        if p.mask and p.address == rejected.address and p is not rejected:
            results[p.name].status, results[p.name].error = "failed", f"{error} (register of {rejected.name})"
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
            r.after_raw = got
        if r.status in ("failed", "skipped"):
            continue
        if got is None:  # not read back: sent ones stay unverified, with the reason
            if n in written and r.error == PENDING:
                r.error = "write-only: cannot be read back"
            continue
        if p.same_value(got, r.desired_raw):
            r.status, r.error = ("ok" if n in written else "unchanged"), None
            continue
        reads_back = f"reads back {show_registers(p, got)} ({' '.join(f'{w:04X}h' for w in got)})"
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


async def on_buses(jobs: Sequence[_J], parallel: int, work: Callable[[_J], Awaitable[Awaitable[None] | None]]
                   ) -> None:
    """Run ``work`` for every job, at most ``parallel`` at once; jobs on one bus strictly one after the other.

    ``work`` may hand back what its job still waits for without needing its slot (a journal fsync):
    that is awaited after the slot is free, before the bus's next job.
    """
    buses: dict[str, list[_J]] = {}
    for j in jobs:
        buses.setdefault(j.url.bus, []).append(j)
    gate = asyncio.Semaphore(max(1, parallel))

    async def run_bus(group: list[_J]) -> None:
        for j in group:  # half-duplex bus: the next device starts when the last one is done
            async with gate:
                after = await work(j)
            if after is not None:
                await after

    await asyncio.gather(*(run_bus(g) for g in buses.values()))


def skipped_result(job: Job, reason: str) -> DeviceResult:
    """A device a fleet run did not start: nothing was sent to it."""
    r = DeviceResult(job.name, tp.describe(job.url), job.unit, job.recipe.profile.id, status="skipped", error=reason,
                     profile_ref=profile_ref(job.recipe.profile))
    r.parameters = list(_results(job.recipe).values())
    return r


@dataclass
class Budget:
    """``--max-failures``: how many devices may end failed or partial before no new device starts."""

    limit: int | None
    failures: int = 0

    def spent(self) -> str | None:
        """Why no new device may start, or None."""
        n = self.failures
        if self.limit is None or n < self.limit:
            return None
        return f"not started: {n} device{'s' if n != 1 else ''} ended failed or partial (--max-failures {self.limit})"


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
    budget = Budget(max_failures)
    stop: str | None = None

    async def one(j: Job) -> Awaitable[None] | None:
        nonlocal stop
        stop = stop or budget.spent()  # checked when the device's turn comes, not when it was queued
        if stop is not None:
            done[j.name] = skipped_result(j, stop)
            return None
        if on_start:
            on_start(j)
        t = time.monotonic()
        finishing: Awaitable[object] | None = None
        try:
            r, finishing = await _apply_device(j.recipe, j.url, j.unit, name=j.name, options=options)
        except Declined:
            if len(jobs) == 1:
                raise
            # in a fleet, a "no" is about that device: the others were asked (or are being written) on their own
            r = skipped_result(j, "not written: declined at the confirmation prompt")
        except StalePlan:
            raise
        except UsageError as e:
            r = DeviceResult(j.name, tp.describe(j.url), j.unit, j.recipe.profile.id, status="failed", error=str(e),
                             profile_ref=profile_ref(j.recipe.profile))
            r.parameters = list(_results(j.recipe).values())
        r.seconds = time.monotonic() - t
        done[j.name] = r
        if r.status in ("failed", "partial"):
            budget.failures += 1
        return finished(r, finishing)

    async def finished(r: DeviceResult, finishing: Awaitable[object] | None) -> None:
        if finishing is not None:  # outside the device's slot: the next device is already connecting
            await finishing
        if on_done:  # the device is done (report file, progress) once its journal line is on disk
            on_done(r)

    sizes = list(batches) if batches else [len(jobs)]
    pos = 0
    for number, size in enumerate(sizes, 1):
        batch = jobs[pos:pos + size]
        pos += size
        await on_buses(batch, parallel, one)
        if stop is None and pos < len(jobs):
            stop = batch_failed(number, batch, done)
    return Report(recipe_name, [done[j.name] for j in jobs], time.monotonic() - started)


def batch_failed(number: int, batch: Sequence[Job], done: Mapping[str, DeviceResult]) -> str | None:
    """Ansible's ``serial`` rule: a batch in which no device that ran ended ok ends the rollout."""
    ran = [done[j.name] for j in batch if done[j.name].status != "skipped"]
    if not ran or any(r.status == "ok" for r in ran):
        return None
    which = f"the canary {ran[0].name}" if len(batch) == 1 else f"all {len(ran)} devices"
    return f"not started: batch {number} failed ({which} did not end ok)"


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
