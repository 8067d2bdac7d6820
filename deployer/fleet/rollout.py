"""The rollout over many devices: buses in parallel, batches, the failure budget."""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import time
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar

from ..errors import RunInterrupted, UsageError
from ..execute.device import DeviceInterrupted, _apply_device, _results, journal_line
from ..execute.read import read_current
from ..execute.session import ApplyOptions, Declined, StalePlan, raise_if_cancelled
from ..execute.soak import Written, await_confirmation, needs_soak, pending_path, roll_back, send_commit, soak
from ..profile import Profile, profile_ref
from ..recipe.loader import Recipe
from ..report import DeviceResult, Report
from ..transport import clients as tp

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

    # every bus ends before this does, also when the run is cancelled (Ctrl-C): gather would otherwise raise at
    # the first cancelled bus while devices on others still say what they hold, or write on
    for outcome in await asyncio.gather(*(run_bus(g) for g in buses.values()), return_exceptions=True):
        if isinstance(outcome, BaseException):
            raise outcome


def skipped_result(job: Job, reason: str, batch: int | None = None) -> DeviceResult:
    """A device a fleet run did not start: nothing was sent to it (``batch``: the one it would have run in)."""
    r = DeviceResult(job.name, tp.describe(job.url), job.unit, job.recipe.profile.id, status="skipped", error=reason,
                     profile_ref=profile_ref(job.recipe.profile), recipe=job.recipe.path, batch=batch,
                     profile_sha256=job.recipe.profile.digest)
    r.parameters = list(_results(job.recipe).values())
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
        return (f"not started: {n} device{'s' if n != 1 else ''} did not end ok (--max-failures {self.limit}: "
                "failed, partial, unreachable and rolled-back devices count)")


def batch_numbers(jobs: Sequence[Job], batches: Sequence[int] | None) -> dict[str, int]:
    """Device name -> its batch (1 = the first) for these batch sizes; {} without batches."""
    if batches is None:
        return {}
    out: dict[str, int] = {}
    pos = 0
    for number, size in enumerate(batches, 1):
        for j in jobs[pos:pos + size]:
            out[j.name] = number
        pos += size
    return out


async def apply_many(jobs: Sequence[Job], *, parallel: int = 8, options: ApplyOptions | None = None,
                     recipe_name: str | None = None,
                     on_done: Callable[[DeviceResult], None] | None = None,
                     on_start: Callable[[Job], None] | None = None,
                     batches: Sequence[int] | None = None, max_failures: int | None = None,
                     rollback_on_failure: bool = False,
                     between_batches: Callable[[int, Report], Awaitable[str | None]] | None = None,
                     on_confirm_wait: Callable[[str, float], None] | None = None,
                     on_changed: Callable[[DeviceResult], None] | None = None,
                     on_soak: Callable[[int, list[str]], None] | None = None) -> Report:
    """Apply to many devices: in parallel, except that devices on one bus go one at a time.

    ``batches`` (sizes, in job order) stage the rollout: each batch finishes before the next
    starts, and a batch in which no device ended ok ends the rollout (Ansible's ``serial``).
    ``max_failures``: once that many devices did not end ok (failed, partial, unreachable, rolled back;
    never skipped), no new device starts. Devices never started are in the report as ``skipped`` with
    the reason. With ``batches``, every device's result carries its batch number.

    A safe change (``options.soak``, ``options.confirm_within``; see ``execute.soak``): each batch is
    written, then soaked together; a device failing its health checks is rolled back and counts against
    ``max_failures``, and any such failure in the first (canary) batch ends the rollout. The profile's
    commit is sent after the soak passed, or once the run is confirmed; not confirmed in time, every
    written device is rolled back. ``rollback_on_failure``: when the rollout stops, every device written
    is rolled back. ``between_batches(number, report so far)`` runs before batches 2, 3 ... (a pause, a
    question) and may end the rollout by returning the reason. ``on_changed`` is told of a device whose
    result changed after ``on_done`` (rolled back, committed); ``on_soak(batch number, device names)`` when a
    soak starts.
    """
    started = time.monotonic()
    done: dict[str, DeviceResult] = {}
    budget = Budget(max_failures)
    stop: str | None = None
    batch_of = batch_numbers(jobs, batches)

    async def one(j: Job) -> Awaitable[None] | None:
        nonlocal stop
        raise_if_cancelled()  # interrupted while this device waited for its turn: it never starts
        stop = stop or budget.spent()  # checked when the device's turn comes, not when it was queued
        batch = batch_of.get(j.name)
        if stop is not None:
            done[j.name] = skipped_result(j, stop, batch)
            return None
        if on_start:
            on_start(j)
        t = time.monotonic()
        finishing: Awaitable[object] | None = None
        try:
            r, finishing = await _apply_device(j.recipe, j.url, j.unit, name=j.name, options=options, batch=batch)
        except DeviceInterrupted as e:
            e.result.seconds = time.monotonic() - t
            done[j.name] = e.result
            raise
        except Declined:
            if len(jobs) == 1:
                raise
            # in a fleet, a "no" is about that device: the others were asked (or are being written) on their own
            r = skipped_result(j, "not written: declined at the confirmation prompt", batch)
        except StalePlan:
            raise
        except UsageError as e:
            r = DeviceResult(j.name, tp.describe(j.url), j.unit, j.recipe.profile.id, status="failed", error=str(e),
                             profile_ref=profile_ref(j.recipe.profile), recipe=j.recipe.path, batch=batch,
                             profile_sha256=j.recipe.profile.digest)
            r.parameters = list(_results(j.recipe).values())
        r.seconds = time.monotonic() - t
        done[j.name] = r
        budget.count(r)
        return finished(r, finishing)

    async def finished(r: DeviceResult, finishing: Awaitable[object] | None) -> None:
        if finishing is not None:  # outside the device's slot: the next device is already connecting
            await journal_line(r, finishing)
        if on_done:  # the device is done (report file, progress) once its journal line is on disk
            on_done(r)

    opts = options or ApplyOptions()

    def written(batch: Sequence[Job]) -> list[Written]:
        return [Written(j.name, j.recipe, j.url, j.unit, done[j.name]) for j in batch if j.name in done]

    def changed(devices: Sequence[Written]) -> None:
        if on_changed is not None:
            for w in devices:
                if w.result.snapshot is not None:
                    on_changed(w.result)

    def so_far() -> Report:
        return Report(recipe_name, [done[j.name] for j in jobs if j.name in done], time.monotonic() - started)

    try:
        sizes = list(batches) if batches else [len(jobs)]
        pos = 0
        for number, size in enumerate(sizes, 1):
            batch = jobs[pos:pos + size]
            if number > 1 and stop is None and between_batches is not None:
                stop = await between_batches(number, so_far())
            pos += size
            await on_buses(batch, parallel, one)
            if opts.soak is not None:
                unhealthy: list[str] = []
                pending = _write_pending(opts, so_far())
                soaking = [w.name for w in written(batch) if needs_soak(w.result)]
                if on_soak is not None and soaking:
                    on_soak(number, soaking)
                passed = await soak(written(batch), opts, on_failed=unhealthy_into(unhealthy), report=pending)
                budget.failures += len(unhealthy)
                if opts.confirm_within is None:  # the soak passed: the change is kept
                    await asyncio.gather(*(send_commit(w, opts) for w in passed))
                changed(written(batch))
                if number == 1 and unhealthy and stop is None and pos < len(jobs):
                    stop = (f"not started: the canary batch 1 failed its health checks "
                            f"({', '.join(unhealthy)} rolled back)")
            if stop is None and pos < len(jobs):
                stop = batch_failed(number, batch, done)
            if stop is None and pos < len(jobs):
                stop = budget.spent()
        if stop is not None and rollback_on_failure:
            reason = f"rolled back: the rollout stopped ({stop.removeprefix('not started: ')})"
            await asyncio.gather(*(roll_back(w, reason, opts) for w in written(jobs)
                                   if w.result.snapshot is not None
                                   and w.result.status not in ("rolled-back", "skipped", "unreachable")))
        if opts.confirm_within is not None:
            await _confirm_or_roll_back(written(jobs), opts, recipe_name, on_confirm_wait)
        for w in written(jobs):  # a commit never sent to a device that ended other than ok
            if w.result.commit == "held" and w.result.status != "ok":
                w.result.commit = "not sent"
        if rollback_on_failure or opts.confirm_within is not None:
            changed(written(jobs))
    except asyncio.CancelledError:
        # every device in flight has said what it holds (gather waits for them); the rest never started
        report = Report(recipe_name, [done.get(j.name) or skipped_result(j, "not started: the run was interrupted",
                                                                         batch_of.get(j.name))
                                      for j in jobs], time.monotonic() - started)
        raise RunInterrupted(report) from None
    finally:
        if opts.run_id is not None and (opts.soak is not None or opts.confirm_within is not None):
            with contextlib.suppress(FileNotFoundError):  # the run ended (or was interrupted and rolled back)
                os.remove(pending_path(opts.state_dir, opts.run_id))
    return Report(recipe_name, [done[j.name] for j in jobs], time.monotonic() - started)


def unhealthy_into(names: list[str]) -> Callable[[Written], None]:
    def note(w: Written) -> None:
        names.append(w.name)
    return note


async def _confirm_or_roll_back(devices: Sequence[Written], opts: ApplyOptions, recipe_name: str | None,
                                on_wait: Callable[[str, float], None] | None) -> None:
    """``confirm_within``: wait for ``deployer confirm``; then send the held commits, else roll every device back.

    While it waits, a report of the run lies in STATE/pending/ (``deployer status`` points a rollback at it
    should this process die)."""
    assert opts.confirm_within is not None and opts.run_id is not None
    waiting = [w for w in devices if needs_soak(w.result)]
    if not waiting:
        return
    _write_pending(opts, Report(recipe_name, [w.result for w in devices]))
    run = opts.run_id
    try:
        confirmed = await await_confirmation(run, opts.confirm_within, opts,
                                             on_wait=None if on_wait is None else lambda t: on_wait(run, t))
    except asyncio.CancelledError:  # Ctrl-C while waiting: the answer is no, at once
        rolling = asyncio.ensure_future(asyncio.gather(*(roll_back(w, "interrupted while waiting for the "
                                                                      "confirmation", opts) for w in waiting)))
        await asyncio.shield(rolling)
        raise
    if confirmed:
        await asyncio.gather(*(send_commit(w, opts) for w in waiting))
    else:
        from ..load.durations import format_duration

        why = f"not confirmed within {format_duration(opts.confirm_within)}"
        await asyncio.gather(*(roll_back(w, why, opts) for w in waiting))


def _write_pending(opts: ApplyOptions, report: Report) -> str | None:
    """While devices hold uncommitted values (a soak, a confirmation wait), the run's report so far lies in
    STATE/pending/RUN.json: ``deployer status`` points a rollback at it should this process die."""
    from ..report import write_json

    if opts.run_id is None:
        return None
    path = pending_path(opts.state_dir, opts.run_id)
    write_json(report.to_json(), path)
    return path


def batch_failed(number: int, batch: Sequence[Job], done: Mapping[str, DeviceResult]) -> str | None:
    """Ansible's ``serial`` rule: a batch in which no device that ran ended ok ends the rollout."""
    ran = [done[j.name] for j in batch if done[j.name].status != "skipped"]
    if not ran or any(r.status == "ok" for r in ran):
        return None
    which = (f"the canary {ran[0].name}" if len(batch) == 1 else f"its only device that ran, {ran[0].name}," if
             len(ran) == 1 else f"all {len(ran)} devices that ran")
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


def failure_budget(spec: str | None, total: int) -> int | None:
    """``--max-failures N|P%``: after this many devices did not end ok (failed, partial, unreachable; never
    skipped) no new device starts."""
    return None if spec is None else _count(spec, total, "--max-failures")
