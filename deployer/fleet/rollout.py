"""The rollout over many devices: buses in parallel, batches, the failure budget."""

from __future__ import annotations

import asyncio
import math
import time
from collections import deque
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Protocol, TypeVar

from ..errors import Declined, RunInterrupted, StalePlan, TransportError, UsageError
from ..execute.device import DeviceInterrupted, Planners, apply_job, journal_line, parameter_results
from ..execute.job import Job
from ..execute.read import plan_device, read_current
from ..execute.session import ApplyOptions, raise_if_cancelled
from ..planning.model import Plan
from ..profile import Profile, profile_ref
from ..report import DeviceResult, Report
from ..state import journal
from ..transport import clients as tp
from ..window.held import Written
from ..window.rollout import Window
from .workers import Call, Pool, WorkerGone, ineligible

# ---- fleets ----------------------------------------------------------------------------------


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


async def on_buses(jobs: Sequence[_J], parallel: int, work: Callable[[_J], Awaitable[Awaitable[None] | None]]) -> None:
    """Run ``work`` for every job, at most ``parallel`` at once; jobs on one bus strictly one after the other.

    ``work`` may hand back what its job still waits for without needing its slot (a journal fsync):
    that is awaited after the slot is free, before the bus's next job.

    ``parallel`` workers take the buses in order (a bus whose device finished goes first again, its next
    device waiting for that device's wait): 10,000 devices are not 10,000 coroutines queued at a semaphore.
    """
    buses: dict[str, list[_J]] = {}
    for j in jobs:
        buses.setdefault(j.url.bus, []).append(j)
    todo: deque[tuple[list[_J], int, asyncio.Future[None] | None]] = deque((g, 0, None) for g in buses.values())
    waits: set[asyncio.Future[None]] = set()

    async def worker() -> None:
        while todo:
            group, i, before = todo.popleft()
            if before is not None:  # half-duplex bus: the next device starts when the last one is done
                await before
            after = await work(group[i])  # an error (a cancelled run) ends this worker: its bus stops
            wait = None if after is None else asyncio.ensure_future(after)
            if wait is not None:
                waits.add(wait)
                wait.add_done_callback(waits.discard)
            if i + 1 < len(group):
                todo.appendleft((group, i + 1, wait))

    try:
        # every worker ends before this does, also when the run is cancelled (Ctrl-C): gather would otherwise
        # raise at the first cancelled one while devices on others still say what they hold, or write on
        outcomes = await asyncio.gather(
            *(worker() for _ in range(min(max(1, parallel), len(buses)))), return_exceptions=True
        )
    finally:
        if waits:  # the devices done but for their journal line: said done before this returns
            await asyncio.gather(*waits, return_exceptions=True)
    for outcome in outcomes:
        if isinstance(outcome, BaseException):
            raise outcome


def skipped_result(job: Job, reason: str, batch: int | None = None, *, parameters: bool = True) -> DeviceResult:
    """A device a fleet run did not start: nothing was sent to it (``batch``: the one it would have run in;
    ``parameters``: False leaves out the recipe's parameters, for the report file's "not finished" lines)."""
    r = DeviceResult(
        job.name,
        tp.describe(job.url),
        job.unit,
        job.recipe.profile.id,
        status="skipped",
        error=reason,
        profile_ref=profile_ref(job.recipe.profile),
        recipe=job.recipe.path,
        batch=batch,
        profile_sha256=job.recipe.profile.digest,
    )
    if parameters:
        r.parameters = list(parameter_results(job.recipe).values())
    return r


# a device that ended in any other status spends the failure budget (unreachable ones too, as
# Ansible's max_fail_percentage counts unreachable hosts); skipped ones were never tried
SPENDS_NOTHING = ("ok", "sent", "skipped")


@dataclass
class Budget:
    """``--max-failures``: how many devices may end other than ok (failed, partial, unreachable ...; never
    skipped) before no new device starts."""

    limit: int | None
    failures: int = 0

    def count(self, r: DeviceResult) -> None:
        if r.status not in SPENDS_NOTHING:
            self.failures += 1

    def spent(self) -> str | None:
        """Why no new device may start, or None."""
        n = self.failures
        if self.limit is None or n < self.limit:
            return None
        return (
            f"not started: {n} device{'s' if n != 1 else ''} did not end ok (--max-failures {self.limit}: "
            "failed, partial, unreachable and rolled-back devices count)"
        )


def batch_numbers(jobs: Sequence[Job], batches: Sequence[int] | None) -> dict[str, int]:
    """Device name -> its batch (1 = the first) for these batch sizes; {} without batches."""
    if batches is None:
        return {}
    out: dict[str, int] = {}
    pos = 0
    for number, size in enumerate(batches, 1):
        for j in jobs[pos : pos + size]:
            out[j.name] = number
        pos += size
    return out


async def apply_many(
    jobs: Sequence[Job],
    *,
    parallel: int = 8,
    options: ApplyOptions | None = None,
    recipe_name: str | None = None,
    on_done: Callable[[DeviceResult], None] | None = None,
    on_start: Callable[[Job], None] | None = None,
    batches: Sequence[int] | None = None,
    max_failures: int | None = None,
    rollback_on_failure: bool = False,
    between_batches: Callable[[int, Report], Awaitable[str | None]] | None = None,
    on_confirm_wait: Callable[[str, float], None] | None = None,
    on_changed: Callable[[DeviceResult], None] | None = None,
    on_soak: Callable[[int, list[str]], None] | None = None,
    keep_results: bool = True,
    pool: Pool | None = None,
    report_lines: bool = True,
) -> Report:
    """Apply to many devices: in parallel, except that devices on one bus go one at a time.

    ``batches`` (sizes, in job order; ``batch_plan`` orders a mixed line) stage the rollout: each batch
    finishes before the next starts; any device of the first (canary) batch that did not end ok, or a later
    batch in which no device ended ok, ends the rollout.
    ``max_failures``: once that many devices did not end ok (failed, partial, unreachable, rolled back;
    never skipped), no new device starts. Devices never started are in the report as ``skipped`` with
    the reason. With ``batches``, every device's result carries its batch number.

    A safe change (``options.soak``, ``options.confirm_within``; see ``deployer.window``): each batch is
    written, then soaked together; a device failing its health checks is rolled back and counts against
    ``max_failures``, and any such failure in the first (canary) batch ends the rollout. The profile's
    commit is sent after the soak passed, or once the run is confirmed; not confirmed in time, every
    written device is rolled back. ``rollback_on_failure``: when the rollout stops, every device written
    is rolled back. ``between_batches(number, report so far)`` runs before batches 2, 3 ... (a pause, a
    question) and may end the rollout by returning the reason. ``on_changed`` is told of a device whose
    result changed after ``on_done`` (rolled back, committed); ``on_soak(batch number, device names)`` when a
    soak starts. ``keep_results`` False: a device that ended ok is kept as its ``DeviceResult.small()`` once
    ``on_done`` had it (which wrote its report line), unless a soak, a confirmation or ``rollback_on_failure``
    may still change it: 10,000 devices x 100 parameters held 34 KB of result objects per device.
    ``pool``: worker processes launched for this run (``fleet.workers.Pool.launch``; a plain run only: UsageError
    otherwise) run the devices, this process keeping the rollout; the caller closes it. ``report_lines``: whether
    ``on_done`` writes each device's report line (``report.device_json``), which the workers then encode.
    """
    opts = options or ApplyOptions()
    window = Window(opts, recipe_name, on_changed=on_changed, on_soak=on_soak, on_confirm_wait=on_confirm_wait)
    if window.held:  # a device keeps its lock from its first write until its window ends
        opts = replace(opts, keep_lock=window.keep)
    rollout = _Rollout(
        jobs,
        opts,
        recipe_name,
        batch_numbers(jobs, batches),
        Budget(max_failures),
        window,
        on_done=on_done,
        on_start=on_start,
    )
    rollout.small_ok = (
        not keep_results and opts.soak is None and opts.confirm_within is None and not rollback_on_failure
    )
    if pool is not None:
        why = ineligible(opts, rollback_on_failure=rollback_on_failure)
        if why is not None:
            window.close()
            raise UsageError(f"worker processes cannot run this fleet: {why} (run it with --workers 0)")
        rollout.started -= pool.seconds  # launching the workers is part of the phase, though it came first
        try:
            await pool.setup(
                opts,
                lines=report_lines and on_done is not None,
                small_ok=rollout.small_ok,
                files=min(parallel, len(jobs)) + 64,
            )
        except BaseException:
            window.close()
            raise
        rollout.pool = pool
    try:
        await rollout.batches(list(batches) if batches else [len(jobs)], parallel, between_batches)
        await window.end(rollout.written(jobs), rollout.stop, rollback_on_failure=rollback_on_failure)
    except asyncio.CancelledError:
        window.interrupted(rollout.written(jobs))
        raise RunInterrupted(rollout.interrupted()) from None
    finally:
        window.close()
    return rollout.report()


class _Rollout:
    """One ``apply_many``: the devices' results so far, the failure budget, and why it stopped (if it did)."""

    def __init__(
        self,
        jobs: Sequence[Job],
        opts: ApplyOptions,
        recipe_name: str | None,
        batch_of: dict[str, int],
        budget: Budget,
        window: Window,
        *,
        on_done: Callable[[DeviceResult], None] | None,
        on_start: Callable[[Job], None] | None,
    ) -> None:
        self.jobs = jobs
        self.opts = opts
        self.recipe_name = recipe_name
        self.batch_of = batch_of
        self.budget = budget
        self.window = window
        self.on_done = on_done
        self.on_start = on_start
        self.done: dict[str, DeviceResult] = {}
        self.small_ok = False  # keep a device that ended ok as its small result once on_done had it
        self.stop: str | None = None
        self.started = time.monotonic()
        self.pool: Pool | None = None  # worker processes running the devices (None: this process does)
        self.planners = Planners()  # the devices of one recipe share its planner and their plans
        self.journal_seen: dict[str, dict[str, dict[str, object]]] = {}  # ``started_by``: per worker gone

    async def batches(
        self, sizes: Sequence[int], parallel: int, between: Callable[[int, Report], Awaitable[str | None]] | None
    ) -> None:
        jobs = self.jobs
        pos = 0
        for number, size in enumerate(sizes, 1):
            batch = jobs[pos : pos + size]
            if number > 1 and self.stop is None and between is not None:
                self.stop = await between(number, self.report())
            pos += size
            await on_buses(batch, parallel, self.one)
            unhealthy = await self.window.after_batch(number, self.written(batch), self.report())
            self.budget.failures += len(unhealthy)
            # the same rule after every batch, the last one too: --rollback-on-failure undoes a rollout whose
            # last batch failed as it undoes one that stopped in the middle
            self.stop = self.stop or self.why_stop(number, batch, unhealthy)

    def why_stop(self, number: int, batch: Sequence[Job], unhealthy: Sequence[str]) -> str | None:
        """Why the rollout ends after batch ``number``: a canary that failed its health checks, a batch without
        an ok device, the failure budget spent; None to go on."""
        if number == 1 and unhealthy and len(batch) < len(self.jobs):
            return f"not started: the canary batch 1 failed its health checks ({', '.join(unhealthy)} rolled back)"
        if number == 1:
            return canary_failed(batch, self.done) or self.budget.spent()
        return batch_failed(number, batch, self.done) or self.budget.spent()

    async def one(self, j: Job) -> Awaitable[None] | None:
        raise_if_cancelled()  # interrupted while this device waited for its turn: it never starts
        self.stop = self.stop or self.budget.spent()  # checked when the device's turn comes, not when it was queued
        batch = self.batch_of.get(j.name)
        if self.stop is not None:
            self.done[j.name] = skipped_result(j, self.stop, batch)
            return None
        if self.on_start:
            self.on_start(j)
        if self.pool is not None:
            return await self.remote(self.pool, j, batch)
        t = time.monotonic()
        finishing: Awaitable[object] | None = None
        try:
            r, finishing = await apply_job(j, self.opts, batch=batch, planners=self.planners)
        except DeviceInterrupted as e:
            e.result.seconds = time.monotonic() - t
            self.done[j.name] = e.result
            raise
        except (Declined, StalePlan) as e:
            if len(self.jobs) == 1:
                raise
            # in a fleet, a "no" or a stale plan (deployer.apply of a FleetPlan) is that device's: the others were
            # asked, or are checked against their own plans, on their own; nothing was written to this one
            why = "declined at the confirmation prompt" if isinstance(e, Declined) else str(e)
            # the device as it was found (its values read), where it was read before the refusal
            r = e.result if e.result is not None else skipped_result(j, f"not written: {why}", batch)
        except UsageError as e:
            r = DeviceResult(
                j.name,
                tp.describe(j.url),
                j.unit,
                j.recipe.profile.id,
                status="failed",
                error=str(e),
                profile_ref=profile_ref(j.recipe.profile),
                recipe=j.recipe.path,
                batch=batch,
                profile_sha256=j.recipe.profile.digest,
            )
            r.parameters = list(parameter_results(j.recipe).values())
        r.seconds = time.monotonic() - t
        self.done[j.name] = r
        self.budget.count(r)
        return self.finished(r, finishing)

    async def finished(self, r: DeviceResult, finishing: Awaitable[object] | None) -> None:
        if finishing is not None:  # outside the device's slot: the next device is already connecting
            await journal_line(r, finishing)
        if self.on_done:  # the device is done (report file, progress) once its journal line is on disk
            self.on_done(r)
        if self.small_ok and r.status == "ok":
            self.done[r.name] = r.small()

    async def remote(self, pool: Pool, j: Job, batch: int | None) -> Awaitable[None] | None:
        """``one`` for a device a worker process runs: the same outcome, said by the worker."""
        call = pool.run(j, batch)
        try:
            kind, *said = await asyncio.shield(call.done)
        except asyncio.CancelledError:  # the run was interrupted: the device says what it holds, as in one()
            pool.cancel(call)
            try:
                kind, *said = await call.done
            except WorkerGone as e:
                kind, said = "gone", [str(e)]
            if kind == "interrupted":
                self.done[j.name] = said[0]
                raise DeviceInterrupted(said[0]) from None
            if kind == "gone":
                self.done[j.name] = self.lost(j, batch, call, said[0])
                raise
        except WorkerGone as e:
            kind, said = "gone", [str(e)]
        if kind == "interrupted":  # the worker stopped it without being asked: its process is going away
            kind, said = "gone", ["its worker process is ending"]
        if kind == "gone":
            r = self.lost(j, batch, call, said[0])
            self.stop = self.stop or "not started: a worker process ended unexpectedly"
        elif kind == "failed":  # the UsageError of one(), or an error in deployer: the device failed, said so
            r = DeviceResult(
                j.name,
                tp.describe(j.url),
                j.unit,
                j.recipe.profile.id,
                status="failed",
                error=said[0],
                profile_ref=profile_ref(j.recipe.profile),
                recipe=j.recipe.path,
                batch=batch,
                profile_sha256=j.recipe.profile.digest,
            )
            r.parameters = list(parameter_results(j.recipe).values())
            r.seconds = time.monotonic() - call.started
        else:
            self.budget.failures += said[0] not in SPENDS_NOTHING
            return self.recorded(j, call)
        self.done[j.name] = r
        self.budget.count(r)
        return self.finished(r, None)

    async def recorded(self, j: Job, call: Call) -> None:
        """A worker's device once its journal line is on disk: its result and report line, reported done."""
        try:
            r, line = await call.recorded
        except WorkerGone as e:
            r, line = self.lost(j, self.batch_of.get(j.name), call, str(e)), None
        r.report_line = line
        self.done[j.name] = r
        if self.on_done:
            self.on_done(r)
        r.report_line = None  # the report file has it: 17 KB a device, not kept for the rest of the run

    def lost(self, j: Job, batch: int | None, call: Call, why: str) -> DeviceResult:
        """A device whose worker process went away while it ran: what is known (its snapshot, if its writes had
        started), said as an interrupted device."""
        r = call.writing or self.started_by(j, batch, why) or skipped_result(j, "", batch, parameters=False)
        r = replace(
            r,
            status="interrupted",
            seconds=time.monotonic() - call.started,
            error=(
                f"{why}; some parameters may hold new values: restore with: deployer rollback {r.snapshot}"
                if r.snapshot
                else f"{why} before its first write; nothing was written"
            ),
        )
        if not r.parameters:
            r.parameters = list(parameter_results(j.recipe).values())
        return r

    def started_by(self, j: Job, batch: int | None, why: str) -> DeviceResult | None:
        """A lost device whose "writing" message never reached this process (the worker died with it unsent, its
        first write already out): the journal's ``device-started`` line, on disk before that write, names its
        snapshot. The journal is read once per worker that went away (``why`` names it)."""
        run = self.opts.run_id
        if run is None:
            return None
        started = self.journal_seen.get(why)
        if started is None:
            try:
                records = journal.records(self.opts.state_dir, run)
            except OSError:
                records = []
            started = self.journal_seen[why] = {
                str(rec.get("name")): rec for rec in records if rec.get("event") == "device-started"
            }
        rec = started.get(j.name, {})
        snapshot, digest = rec.get("snapshot"), rec.get("snapshot_sha256")
        if not isinstance(snapshot, str):
            return None
        r = skipped_result(j, "", batch, parameters=False)
        r.snapshot, r.snapshot_sha256 = snapshot, digest if isinstance(digest, str) else None
        return r

    def written(self, batch: Sequence[Job]) -> list[Written]:
        return [self.window.device(j, self.done[j.name]) for j in batch if j.name in self.done]

    def report(self) -> Report:
        """Every device that ran so far, in job order."""
        return Report(
            self.recipe_name,
            [self.done[j.name] for j in self.jobs if j.name in self.done],
            time.monotonic() - self.started,
        )

    def interrupted(self) -> Report:
        """Every device in flight has said what it holds (gather waits for them); the rest never started."""
        return Report(
            self.recipe_name,
            [
                self.done.get(j.name)
                or skipped_result(j, "not started: the run was interrupted", self.batch_of.get(j.name))
                for j in self.jobs
            ],
            time.monotonic() - self.started,
        )


def canary_failed(batch: Sequence[Job], done: Mapping[str, DeviceResult]) -> str | None:
    """The canary rule: any device of batch 1 that ran and did not end ok ends the rollout."""
    bad = [done[j.name] for j in batch if j.name in done and done[j.name].status not in SPENDS_NOTHING]
    if not bad:
        return None
    said = ", ".join(f"{r.name} {r.status}" for r in bad[:5]) + (f" and {len(bad) - 5} more" if len(bad) > 5 else "")
    return f"not started: the canary batch 1 did not end ok ({said})"


def batch_failed(number: int, batch: Sequence[Job], done: Mapping[str, DeviceResult]) -> str | None:
    """Ansible's ``serial`` rule: a batch in which no device that ran ended ok ends the rollout."""
    ran = [done[j.name] for j in batch if done[j.name].status != "skipped"]
    if not ran or any(r.status == "ok" for r in ran):
        return None
    which = (
        f"the canary {ran[0].name}"
        if len(batch) == 1
        else f"its only device that ran, {ran[0].name},"
        if len(ran) == 1
        else f"all {len(ran)} devices that ran"
    )
    return f"not started: batch {number} failed ({which} did not end ok)"


async def read_many(
    jobs: Sequence[ReadJob],
    *,
    parallel: int = 8,
    on_done: Callable[[str, str | None], None] | None = None,
) -> dict[str, dict[str, tuple[int, ...]] | TransportError | UsageError]:
    """Current values of many devices (diff, pull): per device its registers or why not."""
    return await _each(jobs, parallel, lambda j: read_current(j.profile, j.names, j.url, j.unit), on_done)


async def plan_many(
    jobs: Sequence[Job],
    *,
    parallel: int = 8,
    write_all: bool = False,
    state_dir: str | None = ".deployer",
    on_done: Callable[[str, str | None], None] | None = None,
    window: bool = False,
) -> dict[str, Plan | TransportError | UsageError]:
    """Each device's plan against what it holds now (fleet plan, check mode): its checks run, nothing written;
    per device its plan or why not. The devices of one recipe share its planner."""
    planners = Planners()
    return await _each(
        jobs,
        parallel,
        lambda j: plan_device(
            j.recipe, j.url, j.unit, write_all=write_all, state_dir=state_dir, planners=planners, window=window
        ),
        on_done,
    )


class _Named(_HasBus, Protocol):
    @property
    def name(self) -> str: ...


_T = TypeVar("_T")
_N = TypeVar("_N", bound=_Named)


async def _each(
    jobs: Sequence[_N],
    parallel: int,
    read: Callable[[_N], Awaitable[_T]],
    on_done: Callable[[str, str | None], None] | None,
) -> dict[str, _T | TransportError | UsageError]:
    """``read`` of every device (one at a time per bus, ``parallel`` at once): its result, or why there is none."""
    out: dict[str, _T | TransportError | UsageError] = {}

    async def one(j: _N) -> None:
        name = j.name
        try:
            out[name] = await read(j)
        except (TransportError, UsageError) as e:
            out[name] = e
        if on_done:
            res = out[name]
            on_done(name, str(res) if isinstance(res, Exception) else None)

    await on_buses(jobs, parallel, one)
    return {j.name: out[j.name] for j in jobs}


# ---- staged rollouts ---------------------------------------------------------------------------


def _count(word: str, total: int, what: str) -> int:
    """``N`` or ``P%`` of ``total`` (a percentage rounds down, but never to zero)."""
    w = word.strip()
    try:
        if w.endswith("%"):
            pct = float(w[:-1])
            if not 0 < pct <= 100:
                raise ValueError
            return max(1, math.floor(total * pct / 100))
        n = int(w)
        if n < 1:
            raise ValueError
        return n
    except ValueError:
        raise UsageError(f"{what}: '{word}' is not a positive count or a percentage (e.g. 1, 10%, 100%)") from None


def batch_sizes(spec: str | None, total: int) -> list[int]:
    """``--batch 1,10%,100%``: Ansible's ``serial``; the last size repeats until every device had its turn."""
    if not spec:
        return [total] if total else []
    sizes = [_count(w, total, "--batch") for w in spec.split(",")]
    out: list[int] = []
    left = total
    i = 0
    while left > 0:
        n = min(sizes[min(i, len(sizes) - 1)], left)
        out.append(n)
        left -= n
        i += 1
    return out


def _per_kind(word: str, total: int) -> int:
    """``N`` devices, or ``P%`` of ``total`` rounded to the nearest (never to zero), of one kind."""
    w = word.strip()
    if w.endswith("%"):
        return max(1, math.floor(total * float(w[:-1]) / 100 + 0.5))
    return int(w)


def kind_of(job: Job, by: str) -> str:
    """What ``--batch-by`` groups a device by: its profile, or the first group the inventory lists for it."""
    if by == "group":
        return job.group or ""
    return profile_ref(job.recipe.profile)


def batch_plan(jobs: Sequence[Job], spec: str | None, by: str = "profile") -> tuple[list[Job], list[int]]:
    """``--batch 1,25%,100%`` over a mixed line: each batch takes that many devices (or that share) of every
    kind (profile, or group with ``by="group"``), so the canary batch has one device of each profile.

    Returns the jobs in batch order (in their own order inside a batch) and the batch sizes; the last word
    repeats until every device had its turn.
    """
    if not spec:
        return list(jobs), ([len(jobs)] if jobs else [])
    batch_sizes(spec, len(jobs))  # the words are checked once, with their messages
    words = spec.split(",")
    kinds: dict[str, list[Job]] = {}
    for j in jobs:
        kinds.setdefault(kind_of(j, by), []).append(j)
    totals = {k: len(v) for k, v in kinds.items()}
    taken = dict.fromkeys(kinds, 0)
    order: list[Job] = []
    sizes: list[int] = []
    position = {j.name: n for n, j in enumerate(jobs)}
    i = 0
    while len(order) < len(jobs):
        word = words[min(i, len(words) - 1)]
        batch = []
        for k, group in kinds.items():
            n = min(_per_kind(word, totals[k]), totals[k] - taken[k])
            batch += group[taken[k] : taken[k] + n]
            taken[k] += n
        order += sorted(batch, key=lambda j: position[j.name])
        sizes.append(len(batch))
        i += 1
    return order, sizes


def failure_budget(spec: str | None, total: int) -> int | None:
    """``--max-failures N|P%``: after this many devices did not end ok (failed, partial, unreachable; never
    skipped) no new device starts."""
    return None if spec is None else _count(spec, total, "--max-failures")
