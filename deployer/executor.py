"""The executor: the only code that talks to devices.

connect -> identity check -> read current values -> snapshot (fsync) -> diff-aware plan ->
write requests in order (retries with backoff, partial-failure recovery) -> read back ->
commit actions -> DeviceResult. Everything it sends is recorded for the report.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from collections import deque
from collections.abc import Awaitable, Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Literal

from . import transport as tp
from .diagnostics import UsageError
from .planner import Plan, ReadRequest, Target, WriteRequest, make_plan, plan_reads
from .profile import Parameter, Profile
from .recipe import DeviceSpec, Recipe, recipe_text
from .report import DeviceResult, ParameterResult, Report, RequestRecord

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
                record.result = "no response"
                if attempt > self.retries:
                    hint = tp.no_answer_hint(self.transport.url, self.unit)
                    raise DeviceGone(f"no answer after {attempt} attempt{'s' if attempt > 1 else ''}{hint}") from None
            except tp.ConnectionLost as e:
                record.result = "connection lost"
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

    async def read_blocks(self, reads: Iterable[ReadRequest]) -> dict[int, int]:
        regs: dict[int, int] = {}
        for r in reads:
            for i, v in enumerate(await self.read(r.address, r.count)):
                regs[r.address + i] = v
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


def save_snapshot(state_dir: str, name: str, recipe: Recipe, values: Mapping[str, tuple[int, ...]],
                  url: str, unit: int) -> str:
    """Write the values the device held as a recipe, fsync'ed before any write happens."""
    directory = os.path.join(state_dir, "snapshots")
    os.makedirs(directory, exist_ok=True)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
    path = os.path.join(directory, f"{safe}-{stamp}.yaml")
    n = 1
    while os.path.exists(path):
        n += 1
        path = os.path.join(directory, f"{safe}-{stamp}-{n}.yaml")
    prof = recipe.profile
    text = recipe_text(
        recipe.profile_ref or prof.id,
        {prof.parameter(k): v for k, v in values.items()},
        name=f"snapshot-{safe}-{stamp}",
        device=DeviceSpec(url, unit),
        comment=f"Snapshot: what {url} unit {unit} held before applying recipe '{recipe.name}'.\n"
                f"Restore with: deployer rollback {path}",
    )
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        os.write(fd, text.encode())
        os.fsync(fd)
    finally:
        os.close(fd)
    dfd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(dfd)  # the directory entry too, or a crash can lose the file
    finally:
        os.close(dfd)
    return path


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
    """Apply ``recipe`` to one device and say exactly what it holds afterwards."""
    opts = options or ApplyOptions()
    prof = recipe.profile
    res = DeviceResult(name or recipe.name, tp.describe(url), unit, prof.id)
    results = _results(recipe)
    res.parameters = list(results.values())
    if unit == 0 and not opts.allow_broadcast:
        raise UsageError("unit 0 is broadcast (no device answers, nothing can be verified); "
                         "pass --allow-broadcast to send it anyway")
    target = Target(tp.describe(url), unit, recipe.profile_ref or prof.id)
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
    return res


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
        before = values_of(params, await session.read_blocks(offline.reads))
    except DeviceGone as e:
        res.status, res.error = "unreachable", f"{e}; nothing was written"
        return
    except tp.ExceptionResponse as e:
        res.status, res.error = "failed", f"reading the current values answered {e}; nothing was written"
        return
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

    # 3. the snapshot is on disk before the first write
    res.snapshot = save_snapshot(opts.state_dir, res.name, recipe, before, res.url, res.unit)

    # 4. writes, in plan order; recover from partial failures
    written, gone = await _write_all(session, prof, plan, opts, results)

    # 5. read back everything the plan reads, compare raw values (after a silence too: it may be back)
    try:
        after = values_of(params, await session.read_blocks(plan.reads))
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
        now = values_of(params, await session.read_blocks(plan_reads(prof, [p.name for p in params if p.readable])))
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
        return values_of(params, await session.read_blocks(reads))
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


async def apply_many(jobs: Sequence[Job], *, parallel: int = 8, options: ApplyOptions | None = None,
                     recipe_name: str | None = None,
                     on_done: Callable[[DeviceResult], None] | None = None) -> Report:
    """Apply to many devices: in parallel, except that devices on one bus go one at a time."""
    started = time.monotonic()
    buses: dict[str, list[Job]] = {}
    for j in jobs:
        buses.setdefault(j.url.bus, []).append(j)
    gate = asyncio.Semaphore(max(1, parallel))
    done: dict[str, DeviceResult] = {}

    async def run_bus(group: list[Job]) -> None:
        for j in group:  # half-duplex bus: strictly one device after the other
            async with gate:
                try:
                    r = await apply_device(j.recipe, j.url, j.unit, name=j.name, options=options)
                except (StalePlan, Declined):
                    raise
                except UsageError as e:
                    r = DeviceResult(j.name, tp.describe(j.url), j.unit, j.recipe.profile.id, status="failed",
                                     error=str(e))
                    r.parameters = list(_results(j.recipe).values())
                done[j.name] = r
                if on_done:
                    on_done(r)

    await asyncio.gather(*(run_bus(g) for g in buses.values()))
    return Report(recipe_name, [done[j.name] for j in jobs if j.name in done], time.monotonic() - started)
