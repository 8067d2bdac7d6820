"""One device's apply: its lock, its connection, its plan executed, its snapshot on disk before the first write.

    lock -> connect (``connect.py``) -> the plan's checks (identity, current values ...) -> the plan
    (``apply RECIPE``: made now against what they read; ``apply PLAN.json``: the saved one, refused when the
    device changed since) -> confirm -> snapshot (durable) -> the rest of the plan (``executor.py``) -> result

The plan is made between the checks and the changes in one session, so the device sees exactly the plan's
steps; the executor never plans. ``Planners`` holds what the devices of one run share (one planner per
recipe and set of limits the devices taught; one plan per set of values held).
"""

from __future__ import annotations

import asyncio
import copy
import hashlib
import itertools
import json
import operator
import os
import time
from collections.abc import Awaitable, Mapping
from dataclasses import dataclass, replace
from typing import Any

from ..errors import Declined, InputError, Locked, StalePlan, Unreachable, UsageError
from ..planning.model import WRITE_FUNCTIONS, Pacing, Plan, Target
from ..planning.planfile import plan_to_json
from ..planning.steps import Planner, pacing_for
from ..profile import Profile, profile_ref
from ..recipe.loader import Recipe
from ..report import DeviceResult, ParameterResult, show_registers
from ..state import journal, learned, lock
from ..state.durable import Line, disk_error, durable, queue
from ..state.snapshot import last_identity, snapshot_file, snapshot_values
from ..state.snapshot import written as snapshot_written
from ..transport import clients as tp
from ..transport.urls import identification
from .connect import connected
from .executor import Execution
from .job import Job
from .session import ApplyOptions, Session
from .verify import PENDING, _values


def plan_digest(plan: Plan) -> str:
    """The journal's ``plan_sha256``: SHA-256 of the plan's JSON, canonical (sorted keys, no spaces, UTF-8)."""
    return hashlib.sha256(canonical(plan_to_json(plan))).hexdigest()


def canonical(doc: Any) -> bytes:
    return json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode()


@dataclass
class _Entry:
    """A plan the devices of one recipe holding the same values share, and what each of them needs of it."""

    plan: Plan  # planned for no device in particular
    rest: bytes  # the plan's canonical JSON after its "device" (which sorts first)
    facts: tuple[tuple[str, ...], tuple[tuple[str, tuple[int, ...]], ...]]  # ``plan_facts``
    snapshot: str | None = None  # the values part of their snapshots' text, once the first one was made

    def snapshot_values(self, prof: Profile, before: dict[str, tuple[int, ...]]) -> str:
        """``snapshot_values(prof, before)``: the devices sharing this plan hold the same values (they are its key)."""
        if self.snapshot is None:
            self.snapshot = snapshot_values(prof, before)
        return self.snapshot

    def digest(self, device: Target) -> str:
        """``plan_digest`` of the plan for ``device``, without serialising it again: only its device differs."""
        head = canonical({"profile": device.profile, "unit": device.unit, "url": device.url})
        h = hashlib.sha256(b'{"device":' + head + b",")
        h.update(self.rest)
        return h.hexdigest()


def plan_facts(plan: Plan, prof: Profile) -> tuple[tuple[str, ...], tuple[tuple[str, tuple[int, ...]], ...]]:
    """The parameters the plan leaves unchanged, and the bit fields it writes with the word planned for each."""
    return (
        tuple(pp.name for pp in plan.parameters if pp.action == "unchanged"),
        tuple(
            (pp.name, pp.desired_raw)
            for pp in plan.parameters
            if pp.action != "unchanged" and prof.parameter(pp.name).mask
        ),
    )


def planned_results(results: dict[str, ParameterResult], plan: Plan, entry: _Entry | None, prof: Profile) -> None:
    """What the plan does with each parameter, in its result: ``unchanged`` said; a bit field's register goes
    whole, so its result wants the word planned. Asked of the shared entry once for all its devices."""
    unchanged, fields = entry.facts if entry is not None else plan_facts(plan, prof)
    for n in unchanged:
        results[n].status = "unchanged"
    for n, raw in fields:
        results[n].desired_raw = raw


class Shared:
    """What the devices of one recipe share in a run: its planner, the layout of its values (name, key,
    registers), its results' starting point, and the plans of devices holding the same values."""

    def __init__(self, planner: Planner) -> None:
        recipe = planner.recipe
        self.planner = planner
        self.recipe = recipe
        params = [d.parameter for d in recipe.desired]
        self.layout = tuple((p.name, p.key, p.count) for p in params)
        self.names = tuple(p.name for p in params)
        self.restart = tuple(p.name for p in params if p.restart)
        self._plans: dict[tuple[Any, ...], _Entry] = {}
        # each ParameterResult's arguments, in its fields' order (a fleet makes 100 per device)
        self._results = tuple(
            (
                d.name,
                d.parameter.address,
                d.parameter.count,
                d.text,
                d.registers,
                None,
                None,
                "skipped",
                None,
                d.parameter.register_type,
                d.parameter,
            )
            for d in recipe.desired
        )
        keys = [p.key + i for p in params for i in range(p.count)]
        self._words = operator.itemgetter(*keys) if len(keys) > 1 else None  # one key: itemgetter gives no tuple
        self._seen: dict[tuple[int, ...], dict[str, tuple[int, ...]]] = {}

    def results(self) -> dict[str, ParameterResult]:
        """A result per recipe parameter, in recipe order, each ``skipped`` until something happens to it."""
        return dict(zip(self.names, itertools.starmap(ParameterResult, self._results), strict=True))

    def values(self, regs: Mapping[int, int]) -> dict[str, tuple[int, ...]]:
        """The recipe's parameters' registers from the words read (``verify._values``), made once for all the
        devices whose registers read the same: their values are then the same objects too (the plan's key
        compares them at once)."""
        if self._words is None:
            return _values(self.layout, regs)
        try:
            words = self._words(regs)
        except KeyError:  # registers not read (write-only parameters; a read that failed): the long way
            return _values(self.layout, regs)
        hit = self._seen.get(words)
        if hit is None:
            if len(self._seen) >= 64:
                self._seen.clear()
            hit = self._seen[words] = _values(self.layout, regs)
        return dict(hit)  # the caller's own

    def plan(self, target: Target, before: dict[str, tuple[int, ...]] | None, commit_owed: bool) -> tuple[Plan, _Entry]:
        """The device's plan (``Planner.plan``) and the entry the devices holding the same values share."""
        key = (target.unit != 0, commit_owed, None if before is None else tuple(map(before.get, self.names)))
        hit = self._plans.get(key)
        if hit is None:
            if len(self._plans) >= 64:
                self._plans.clear()
            plan = self.planner.plan(Target("", target.unit, ""), before, commit_owed=commit_owed)
            doc = plan_to_json(plan)
            del doc["device"]
            hit = self._plans[key] = _Entry(plan, canonical(doc)[1:], plan_facts(plan, self.recipe.profile))
            _ = plan.writes, plan.checks, plan._desired, plan._read_back  # made once: each device's copy has them
        plan = copy.copy(hit.plan)  # keeps what the executor derived from the plan once (``Plan._desired``)
        object.__setattr__(plan, "device", target)
        return plan, hit


def parameter_results(recipe: Recipe) -> dict[str, ParameterResult]:
    """A result per recipe parameter, in recipe order, each ``skipped`` until something happens to it."""
    return {
        d.name: ParameterResult(
            d.name,
            d.parameter.address,
            d.parameter.count,
            d.text,
            d.registers,
            register_type=d.parameter.register_type,
            parameter=d.parameter,
        )
        for d in recipe.desired
    }


class Planners:
    """The planners of one run (or one worker process of it), shared by its devices: one per recipe, set of
    limits the devices taught, and pacing."""

    def __init__(self) -> None:
        self._by: dict[tuple[Any, ...], tuple[Recipe, Shared]] = {}
        self._taught: dict[tuple[Any, ...], tuple[Recipe, Recipe, UsageError | None]] = {}

    def over_limits(self, recipe: Recipe, taught: learned.Entry) -> Recipe:
        """``recipe`` with its profile over the limits a device taught (``learned.with_limits``); ``recipe`` itself
        when they change nothing. One recipe for all the devices that taught the same limits: their plans are
        shared as other devices' are. Raises UsageError when no plan can carry the recipe over them (a string longer
        than the writes the device takes), naming where the limit came from: not the profile."""
        key = (id(recipe), tuple(sorted(taught.limits.items())))
        hit = self._taught.get(key)
        if hit is None or hit[0] is not recipe:  # the recipe is kept in the entry, so its id is not reused
            prof = learned.with_limits(recipe.profile, taught)  # from the limits alone
            over = recipe if prof is recipe.profile else replace(recipe, profile=prof)
            # planned once for all the devices that taught these limits; said with the date each one taught them
            hit = self._taught[key] = (recipe, over, None if over is recipe else learned.refusal(recipe, over))
        if hit[2] is not None:
            raise learned.taught(hit[2], taught)
        return hit[1]

    def shared(
        self,
        recipe: Recipe,
        *,
        write_all: bool,
        commit: bool,
        pacing: Pacing,
        device_id: bool | None = None,
        window: bool = False,
    ) -> Shared:
        """``device_id``: whether the device is asked Function 43 (None: as the recipe's profile says); ``window``:
        a safe change's plans (the health checks read before the change)."""
        ask = recipe.profile.limits.device_identification if device_id is None else device_id
        key = (id(recipe), write_all, commit, pacing, ask, window)
        hit = self._by.get(key)
        if hit is None or hit[0] is not recipe:  # the recipe is kept in the entry, so its id is not reused
            hit = self._by[key] = (
                recipe,
                Shared(
                    Planner(recipe, write_all=write_all, commit=commit, pacing=pacing, device_id=ask, window=window)
                ),
            )
        return hit[1]


async def apply_device(
    recipe: Recipe,
    url: tp.DeviceURL,
    unit: int,
    *,
    name: str | None = None,
    options: ApplyOptions | None = None,
    plan: Plan | None = None,
) -> DeviceResult:
    """Apply ``recipe`` to one device and say exactly what it holds afterwards; ``plan``: a saved plan of it,
    executed unchanged (refused when the device changed since it was made).

    The device's lock is held from before the first read until the read-back is done, so no
    other run on this machine can write it in between. With a journal (``options.run_id``) it
    returns once the ``device-finished`` line is on disk.
    """
    job = Job(name or recipe.name, recipe, url, unit, plan=plan)
    res, finishing = await apply_job(job, options or ApplyOptions())
    if finishing is not None:
        await journal_line(res, finishing)
    return res


async def journal_line(res: DeviceResult, finishing: Awaitable[object]) -> None:
    """Wait for the device's device-finished line; a state directory that cannot take it is said (``unrecorded``,
    the run exits 4): the device's outcome stands (the report says it), only the journal misses the line."""
    try:
        await finishing
    except OSError as e:
        res.unrecorded.append(f"the journal's device-finished line could not be written: {disk_error(e)}")


def new_result(job: Job, batch: int | None = None) -> DeviceResult:
    prof = job.recipe.profile
    res = DeviceResult(
        job.name,
        tp.describe(job.url),
        job.unit,
        prof.id,
        profile_ref=profile_ref(prof),
        recipe=job.recipe.path,
        batch=batch,
        profile_sha256=prof.digest,
    )
    if job.recipe.snapshot is not None and job.recipe.path is not None:
        res.restored = os.path.abspath(job.recipe.path)
    return res


async def apply_job(
    job: Job, opts: ApplyOptions, *, batch: int | None = None, planners: Planners | None = None
) -> tuple[DeviceResult, Awaitable[object] | None]:
    """``apply_device`` for a run's job, handing back the wait for its ``device-finished`` line instead of
    waiting: a fleet frees the device's slot (and lock) for the next device while that fsync happens.
    ``batch``: a staged fleet's batch number, for the report and the journal; ``planners``: the run's."""
    recipe, unit = job.recipe, job.unit
    res = new_result(job, batch)
    if unit == 0 and not opts.allow_broadcast:
        raise UsageError(
            "unit 0 is broadcast (no device answers, nothing can be verified); to send it anyway, "
            "allow broadcast (--allow-broadcast; ApplyOptions(allow_broadcast=True) in Python)"
        )
    if unit == 0 and (recipe.profile.preconditions or any(d.parameter.mask for d in recipe.desired)):
        raise UsageError(
            "a broadcast cannot read: bit fields (which keep the register's other bits) and "
            f"preconditions of profile {recipe.profile.id} need a device that answers"
        )
    if job.commit_owed or job.hold_commit:
        opts = replace(opts, commit_owed=job.commit_owed, hold_commit=opts.hold_commit or job.hold_commit)
    device = _Device(job, opts, res, planners or Planners())
    try:
        return await device.locked()
    except asyncio.CancelledError:
        interrupted(res, device.results)
        raise DeviceInterrupted(res) from None


class DeviceInterrupted(asyncio.CancelledError):
    """The device's apply was cancelled (the run interrupted): ``result`` says what it holds as far as known."""

    def __init__(self, result: DeviceResult) -> None:
        super().__init__(result.name)
        self.result = result


def interrupted(res: DeviceResult, results: dict[str, ParameterResult]) -> None:
    """What an interrupted device's report says: every write that went out is unverified, the one that was
    out when the run stopped may have been applied, the rest was not sent."""
    out = [
        (r.address, r.address + r.count)
        for r in res.requests
        if r.result == "interrupted" and r.function in WRITE_FUNCTIONS
    ]
    for p in results.values():
        if any(a < p.address + p.count and p.address < b for a, b in out):
            p.status, p.error = (
                "unverified",
                "the run was interrupted while its write request was out: it may have been applied",
            )
        elif p.status == "unverified" and p.error == PENDING:
            p.error = "written; not read back: the run was interrupted"
        elif p.status == "skipped" and p.error is None:
            p.error = "not written: the run was interrupted"
    res.status = "interrupted"
    if res.snapshot is None:
        res.error = "the run was interrupted before the first write to this device; nothing was written"
    else:
        res.error = (
            "the run was interrupted while writing this device: some parameters may hold new values; "
            f"restore with: deployer rollback {res.snapshot}"
        )


class _Device:
    """One device's apply in progress."""

    def __init__(
        self, job: Job, opts: ApplyOptions, res: DeviceResult, planners: Planners, *, window: bool | None = None
    ) -> None:
        self.job = job
        self.window = opts.window if window is None else window  # a safe change's plan (plan --soak: no run)
        self.opts = opts
        self.res = res
        self.planners = planners
        self.recipe = job.recipe  # over the limits the device taught, once they are in force
        self.taught: learned.Entry | None = None  # what the device taught an earlier run, in force
        self.entry: _Entry | None = None  # the shared plan this device runs (None: a saved plan)
        self.pacing = pacing_for(job.url, job.recipe.profile)
        if job.plan is not None:  # a saved plan's pauses are part of it, though its URL keeps no options
            p = job.plan.pacing
            self.pacing = Pacing(
                max(self.pacing.after_connect, p.after_connect), max(self.pacing.between_requests, p.between_requests)
            )
        self.shared = self._shared(job.recipe)
        self.results = self.shared.results()
        res.parameters = list(self.results.values())

    def _shared(self, recipe: Recipe) -> Shared:
        """The run's planner for ``recipe``, asking Function 43 unless the URL or the (taught) profile says not."""
        ask = identification(self.job.url)
        return self.planners.shared(
            recipe,
            write_all=self.opts.write_all,
            commit=not self.opts.hold_commit,
            pacing=self.pacing,
            window=self.window,
            device_id=recipe.profile.limits.device_identification if ask is None else ask,
        )

    async def locked(self) -> tuple[DeviceResult, Awaitable[object] | None]:
        job, opts, res = self.job, self.opts, self.res
        try:
            held = (
                []
                if opts.lock_held
                else await lock.acquire_device(
                    job.url.lock_keys,
                    job.unit,
                    timeout=opts.lock_timeout,
                    command=lock.command_line(),
                    directory=opts.lock_dir,
                    run=opts.run_id,
                )
            )
        except Locked as e:
            res.status, res.error = "unreachable", f"{e}; nothing was sent"
            return res, None
        try:
            res.notices.extend(h.stale for h in held if h.stale)
            if job.plan is None and job.unit != 0:
                self.over_taught()
            entered = False
            try:
                async with connected(
                    job.url,
                    job.unit,
                    self.recipe.profile,
                    records=res.requests,
                    backoff=opts.backoff,
                    notices=res.notices,
                    pacing=self.pacing,  # what the plan says (no limit a device teaches is a pause)
                ) as session:
                    entered = True
                    if job.unit == 0:
                        await self._broadcast(session)
                    else:
                        await self._apply(session)
            except Unreachable as e:
                if entered:
                    raise
                res.status, res.error = "unreachable", str(e)
                return res, None
            res.settle()
            if opts.keep_lock is not None and held and opts.keep_lock(res, held):
                held = []  # its window holds them now, until the commit or the rollback
            if res.snapshot is not None and opts.run_id is not None:  # queued now, after the read-back
                return res, queue(Line(journal.path_of(opts.state_dir), journal.device_finished(opts.run_id, res)))
            return res, None
        finally:
            for h in reversed(held):
                h.release()

    def over_taught(self) -> None:
        """Plan over the limits this device taught an earlier run (``learned``): its checks too (a device that
        never answered Function 43 is not asked it again)."""
        res = self.res
        try:  # the run checked the file before it started: damaged since, it is not used (and said)
            taught = learned.lookup(
                self.opts.state_dir,
                profile_ref(self.job.recipe.profile),
                learned.device_id(self.job.url, self.job.unit),
            )
        except InputError as e:
            res.notices.append(f"what devices taught is not used: {e}")
            return
        if taught is None:
            return
        over = self.planners.over_limits(self.job.recipe, taught)
        if over is not self.job.recipe:
            self.taught, self.recipe, self.shared = taught, over, self._shared(over)

    def keep_taught(self, ex: Execution) -> None:
        """After the checks: what the device taught stays in force unless its identity changed since (another
        device answers there now); either is said."""
        taught, res = self.taught, self.res
        if taught is None:
            return
        if taught.identity is not None and res.identity is not None and taught.identity != res.identity:
            res.notices.append(
                "the device's identity changed since it taught "
                f"{taught.describe_limits()} ({_identity_text(taught.identity)}, now "
                f"{_identity_text(res.identity)}): not used"
            )
            self.taught, self.recipe, self.shared = None, self.job.recipe, self._shared(self.job.recipe)
            ex.recipe, ex.prof = self.recipe, self.recipe.profile
            return
        res.notices.append(learned.note(taught))

    async def _broadcast(self, session: Session) -> None:
        """Unit 0: nobody answers, so nothing is read; every parameter is sent and unverified.

        The device ends ``sent`` when every request went out, ``failed`` when one could not be sent."""
        from ..errors import DeviceGone

        res, results = self.res, self.results
        plan = self.job.plan or self.shared.plan(Target(res.url, 0, profile_ref(self.recipe.profile)), None, False)[0]
        steps = [s for s in plan.steps if s.kind == "write"]
        for i, step in enumerate(steps):
            session.step = plan.steps.index(step) + 1
            try:
                await session.write(step.write())
            except DeviceGone as e:
                for n in step.parameters:
                    results[n].status, results[n].error = "unverified", f"broadcast may not have gone out: {e}"
                for rest in steps[i + 1 :]:
                    for n in rest.parameters:
                        results[n].status, results[n].error = "skipped", "not sent: an earlier broadcast request failed"
                res.status, res.error = "failed", f"broadcast request at 0x{step.address:04X} could not be sent: {e}"
                return
            for n in step.parameters:
                results[n].status, results[n].error = "unverified", "broadcast: no device answers"
        res.status = "sent"

    async def _apply(self, session: Session) -> None:
        job, opts, res, results = self.job, self.opts, self.res, self.results
        prof = self.recipe.profile
        ex = Execution(session, self.recipe, res, results, opts, self.shared.values)
        target = Target(res.url, job.unit, profile_ref(prof))
        saved = job.plan
        # 1. the checks: identity, what the device holds (the snapshot), its identification and firmware
        if not await ex.checks(saved.steps[: saved.checks] if saved is not None else self.shared.planner.checks):
            return
        before = ex.before
        for n, regs in before.items():
            results[n].before_raw = regs
        self._identity_notice()
        if ex.silent_identification:
            self._silent(ex)
        # 2. the plan: the saved one must still match the device (the stale-plan rule), else made now against it
        if saved is not None:
            try:
                _stale(saved, prof, before)
            except StalePlan as e:
                _refused(res, e, str(e))
                raise
            plan = saved
        else:
            self.keep_taught(ex)
            prof = self.recipe.profile
            plan, self.entry = self.shared.plan(target, before, opts.commit_owed)
        planned_results(results, plan, self.entry, prof)

        async def before_write() -> bool:
            if opts.confirm is not None and not await opts.confirm(plan, res):
                raise Declined("nothing was written (declined)")
            # 3. the snapshot is on disk before the first write, and the journal says this device is being written
            if not await self._save_snapshot(plan, before):
                return False
            if opts.on_writing is not None:
                opts.on_writing(res)
            return True

        # 4. the rest of the plan: preconditions, unlock, writes, read-back, commit, lock
        try:
            await ex.changes(plan, before_write)
        except Declined as e:
            _refused(res, e, "declined at the confirmation prompt")
            raise
        if any(s.kind == "write" for s in plan.steps) and res.snapshot is not None:
            res.seen = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())  # the read-back: what "as left" shows
        self._remember()
        res.notices.extend(
            [f"{n} takes effect after a power cycle" for n in self.shared.restart if results[n].status == "ok"]
        )

    def _identity_notice(self) -> None:
        """The same name answering with other Function 43 objects than at its last snapshot: a replaced device."""
        res = self.res
        if res.identity is not None:
            last = last_identity(self.opts.state_dir, res.name)
            if last is not None and last[1] != res.identity:
                res.notices.append(
                    f"the device's identity changed since its last snapshot "
                    f"({os.path.basename(last[0])}: {_identity_text(last[1])}; now "
                    f"{_identity_text(res.identity)}): it may have been replaced"
                )

    def _silent(self, ex: Execution) -> None:
        """The device answered its reads but not Function 43: learned, so that it costs one timeout once."""
        prof = self.job.recipe.profile
        self.res.learned["device_identification"] = 0
        self.res.notices.append(
            f"the device did not answer Function 43 (device identification) within {self.job.url.timeout:g} s: it is "
            f"not asked again ('deployer learned forget' asks again); set limits.device_identification: false in "
            f"profile {prof.id} if its devices have none"
        )

    def _remember(self) -> None:
        res, opts = self.res, self.opts
        if not res.learned:
            return
        prof = self.recipe.profile
        try:
            learned.remember(
                opts.state_dir,
                learned.Entry(
                    profile_ref(prof),
                    learned.device_id(self.job.url, self.job.unit),
                    dict(res.learned),
                    next((n for n in res.notices if "; set limits." in n), ""),
                    learned.now(),
                    res.identity,
                    res.url,
                    res.unit,
                ),
            )
        except InputError as e:  # damaged since the run started: said, not overwritten
            res.notices.append(f"what the device taught is not remembered: {e}")
        except UsageError as e:  # a full disk: the device's outcome stands, only the lesson is lost
            res.unrecorded.append(f"what the device taught is not remembered: {e}")

    async def _save_snapshot(self, plan: Plan, before: dict[str, tuple[int, ...]]) -> bool:
        """The snapshot on disk and the journal's device-started line, both made durable by the group-commit
        thread (sharing fsyncs with the other devices of a fleet); False (and nothing written) when it cannot be."""
        opts, res, recipe = self.opts, self.res, self.recipe
        applied = opts.applied or (os.path.abspath(recipe.path) if recipe.path else None)  # a fleet: its own
        entry = self.entry
        values = None if entry is None else entry.snapshot_values(recipe.profile, before)
        snap = snapshot_file(
            opts.state_dir,
            res.name,
            recipe,
            before,
            tp.recorded(self.job.url, res.url),  # with its timeout and pauses: a rollback talks to it as this run did
            res.unit,
            applied=applied,
            identity=res.identity,
            values_text=values,
        )
        if opts.run_id is not None:
            digest = entry.digest(plan.device) if entry is not None else plan_digest(plan)
            snap.journal = journal.path_of(opts.state_dir)
            snap.line = journal.device_started(
                opts.run_id,
                name=res.name,
                url=res.url,
                unit=res.unit,
                plan_digest=digest,
                batch=res.batch,
                restoring=res.restored,
            )
        try:
            res.snapshot = await durable(snap)
            res.snapshot_sha256 = snap.digest
            if res.snapshot is not None:
                snapshot_written(res.snapshot)
        except OSError as e:
            if not opts.restoring:  # no snapshot, no write: nothing could be undone
                res.status, res.error = (
                    "failed",
                    (f"cannot save the snapshot in {opts.state_dir}: {disk_error(e)}; nothing was written"),
                )
                return False
            # a window's rollback restores values the run verified: a full disk must not stop it
            res.unrecorded.append(
                f"the snapshot of what it held before the rollback could not be saved in "
                f"{opts.state_dir}: {disk_error(e)}"
            )
        return True


def _refused(res: DeviceResult, e: StalePlan | Declined, why: str) -> None:
    """``e`` made to carry the device as it was found: skipped, its values read, nothing written (the report of a
    run refused before its first write says what each parameter holds)."""
    res.status, res.error = "skipped", f"not written: {why}"
    e.result = res


def _stale(plan: Plan, prof: Profile, before: dict[str, tuple[int, ...]]) -> None:
    """Raise StalePlan, naming each value, when the device no longer holds what ``plan`` was made against."""
    changed = [
        pp.name
        for pp in plan.parameters
        if pp.current_raw is not None and not prof.parameter(pp.name).same_value(before.get(pp.name), pp.current_raw)
    ]
    if not changed:
        return
    if all(prof.parameter(pp.name).same_value(before.get(pp.name), pp.desired_raw) for pp in plan.parameters):
        # the usual cause: the plan ran already (a second apply of the same file); said, so nobody hunts a culprit
        raise StalePlan(
            "the device changed since the plan was made: it now holds every value the plan writes (did the plan "
            "run already?); a new plan shows what is left to do, if anything"
        )
    raise StalePlan(
        "the device changed since the plan was made ("
        + ", ".join(f"{n}: now {show_registers(prof.parameter(n), before.get(n))}" for n in changed)
        + "); make a new plan"
    )


def _identity_text(identity: dict[str, str]) -> str:
    return ", ".join(f"{k} {v!r}" for k, v in identity.items()) or "none"
