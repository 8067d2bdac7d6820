"""The executor: the only code that talks to devices.

connect -> identity check -> read current values -> snapshot (durable) -> diff-aware plan ->
write requests in order (retries with backoff, partial-failure recovery) -> read back ->
commit actions -> DeviceResult. Everything it sends is recorded for the report.
"""

from __future__ import annotations

import asyncio
import hashlib
import itertools
import json
import operator
import os
import time
from collections import deque
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from ..errors import (
    Declined,
    DeviceGone,
    ExceptionResponse,
    IdentityMismatch,
    InputError,
    Locked,
    StalePlan,
    Unreachable,
    Untrusted,
    UsageError,
)
from ..planning.model import Plan, ReadRequest, Target
from ..planning.planfile import plan_to_json
from ..planning.planner import make_plan, plan_reads
from ..profile import Profile, profile_ref
from ..recipe.loader import Recipe
from ..report import DeviceResult, ParameterResult, show_registers
from ..state import journal, learned, lock
from ..state.durable import Line, disk_error, durable, queue
from ..state.snapshot import last_identity, snapshot_file, snapshot_values
from ..state.snapshot import written as snapshot_written
from ..transport import clients as tp
from .recovery import Learning, _recover, _remerge, chunks, single_writes
from .session import ApplyOptions, Session
from .steps import (
    _send_actions,
    check_firmware,
    check_identity,
    check_identity_objects,
    check_preconditions,
    commit_steps,
)
from .verify import PENDING, _attempted, _values, _verify


def _results(recipe: Recipe) -> dict[str, ParameterResult]:
    """A result per recipe parameter, in recipe order, each ``skipped`` until something happens to it."""
    shared = _shared(recipe)
    return dict(zip(shared.names, itertools.starmap(ParameterResult, shared.results), strict=True))


@dataclass(frozen=True)
class _Shared:
    """What every device applying one recipe shares, worked out once (a fleet has hundreds of them)."""

    reads: tuple[ReadRequest, ...]  # the blocks covering the readable parameters (snapshot, read-back)
    layout: tuple[tuple[str, int, int], ...]  # name, key (Parameter.key), registers of each recipe parameter
    names: tuple[str, ...]  # the recipe's parameters, in its order (the layout's, the results')
    results: tuple[tuple[Any, ...], ...]  # each ParameterResult's arguments, in its fields' order
    restart: tuple[str, ...]  # the parameters that take effect after a power cycle, in recipe order
    words: Callable[[Mapping[int, int]], tuple[int, ...]] | None  # every register of the layout (None: < 2)
    seen: dict[tuple[int, ...], dict[str, tuple[int, ...]]] = field(default_factory=dict, compare=False)

    def values(self, regs: Mapping[int, int]) -> dict[str, tuple[int, ...]]:
        """``_values(self.layout, regs)``, made once for all the devices whose registers read the same: their
        values are then the same objects too (the plan's key, the report's entries compare them at once)."""
        if self.words is None:
            return _values(self.layout, regs)
        try:
            words = self.words(regs)
        except KeyError:  # registers not read (write-only parameters; a read that failed): the long way
            return _values(self.layout, regs)
        hit = self.seen.get(words)
        if hit is None:
            if len(self.seen) >= _SHARED_KEPT:
                self.seen.clear()
            hit = self.seen[words] = _values(self.layout, regs)
        return dict(hit)  # the caller's own


_SHARED: dict[int, tuple[Recipe, _Shared]] = {}
_SHARED_KEPT = 64  # recipes remembered (a long-lived API user loads new ones)


def _shared(recipe: Recipe) -> _Shared:
    hit = _SHARED.get(id(recipe))
    if hit is None or hit[0] is not recipe:  # the recipe is kept in the entry, so its id is not reused
        while len(_SHARED) >= _SHARED_KEPT:
            del _SHARED[next(iter(_SHARED))]  # the oldest
        params = [d.parameter for d in recipe.desired]
        keys = [p.key + i for p in params for i in range(p.count)]
        hit = _SHARED[id(recipe)] = (recipe, _Shared(
            plan_reads(recipe.profile, [p.name for p in params if p.readable]),
            tuple((p.name, p.key, p.count) for p in params),
            tuple(p.name for p in params),
            tuple((d.name, d.parameter.address, d.parameter.count, d.text, d.registers, None, None, "skipped", None,
                   d.parameter.register_type, d.parameter) for d in recipe.desired),
            tuple(p.name for p in params if recipe.profile.parameter(p.name).restart),
            operator.itemgetter(*keys) if len(keys) > 1 else None))  # one key: itemgetter gives no tuple
    return hit[1]


def plan_digest(plan: Plan) -> str:
    """The journal's ``plan_sha256``: SHA-256 of the plan's saved-plan JSON with sorted keys."""
    return hashlib.sha256(json.dumps(plan_to_json(plan), sort_keys=True).encode()).hexdigest()


@dataclass(frozen=True)
class _Facts:
    """What a plan says of its parameters that an apply marks on their results and writes from."""

    unchanged: tuple[str, ...]  # not written: the device holds the value
    fields: tuple[tuple[str, tuple[int, ...]], ...]  # bit fields and the whole word planned for their register
    desired: dict[str, tuple[int, ...]]  # every parameter's registers as planned (copied before a write changes it)


def _facts(plan: Plan, prof: Profile) -> _Facts:
    return _Facts(tuple(pp.name for pp in plan.parameters if pp.action == "unchanged"),
                  tuple((pp.name, pp.desired_raw) for pp in plan.parameters if prof.parameter(pp.name).mask),
                  {pp.name: tuple(pp.desired_raw) for pp in plan.parameters})


@dataclass
class _Planned:
    """A plan the devices of one recipe holding the same values share, and what each of them needs of it."""

    plan: Plan  # planned for no device in particular (Target("", answers, ""))
    rest: bytes  # the plan's sorted-key JSON after its "device" (which sorts first)
    facts: _Facts
    snapshot: str | None = None  # the values part of their snapshots' text, once the first one was made

    def digest(self, device: Target) -> str:
        """``plan_digest`` of the plan for ``device``, without serialising it again: only its device differs."""
        head = json.dumps({"profile": device.profile, "unit": device.unit, "url": device.url}).encode()
        h = hashlib.sha256(b'{"device": ' + head + b", ")
        h.update(self.rest)
        return h.hexdigest()

    def snapshot_values(self, prof: Profile, before: Mapping[str, tuple[int, ...]]) -> str:
        """``snapshot_values(prof, before)``: the devices sharing this plan hold the same values (they are its key)."""
        if self.snapshot is None:
            self.snapshot = snapshot_values(prof, before)
        return self.snapshot


_PLANS: dict[tuple[int, bool, bool, tuple[tuple[int, ...] | None, ...]], tuple[Recipe, _Planned]] = {}


def _planned(recipe: Recipe, target: Target, before: dict[str, tuple[int, ...]], write_all: bool,
             shared: _Shared) -> tuple[Plan, _Planned]:
    """``make_plan`` for this device, planned once for all the devices of ``recipe`` that hold the same values
    (the plan depends on the recipe, its profile with any learned limits, and what the device holds; the
    device itself is only named in it, and whether it answers: unit 0 does not); and the shared entry."""
    current = tuple(map(before.get, shared.names))
    answers = target.unit != 0  # the plan's wire summary counts the answers (none to a broadcast)
    key = (id(recipe), write_all, answers, current)
    hit = _PLANS.get(key)
    if hit is None or hit[0] is not recipe:  # the recipe is kept in the entry, so its id is not reused
        while len(_PLANS) >= _SHARED_KEPT:
            del _PLANS[next(iter(_PLANS))]
        plan = make_plan(recipe, Target("", int(answers), ""), before, write_all=write_all, reads=shared.reads)
        doc = plan_to_json(plan)
        del doc["device"]
        hit = _PLANS[key] = (recipe, _Planned(plan, json.dumps(doc, sort_keys=True)[1:].encode(),
                                              _facts(plan, recipe.profile)))
    return replace(hit[1].plan, device=target), hit[1]


async def apply_device(recipe: Recipe, url: tp.DeviceURL, unit: int, *, name: str | None = None,
                       options: ApplyOptions | None = None) -> DeviceResult:
    """Apply ``recipe`` to one device and say exactly what it holds afterwards.

    The device's lock is held from before the first read until the read-back is done, so no
    other run on this machine can write it in between. With a journal (``options.run_id``) it
    returns once the ``device-finished`` line is on disk.
    """
    res, finishing = await _apply_device(recipe, url, unit, name=name, options=options)
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


async def _apply_device(recipe: Recipe, url: tp.DeviceURL, unit: int, *, name: str | None,
                        options: ApplyOptions | None, batch: int | None = None,
                        ) -> tuple[DeviceResult, Awaitable[object] | None]:
    """``apply_device``, handing back the wait for its ``device-finished`` line instead of waiting:
    a fleet frees the device's slot (and lock) for the next device while that fsync happens.
    ``batch``: a staged fleet's batch number, for the report and the journal."""
    opts = options or ApplyOptions()
    prof = recipe.profile
    res = DeviceResult(name or recipe.name, tp.describe(url), unit, prof.id, profile_ref=profile_ref(prof),
                       recipe=recipe.path, batch=batch, profile_sha256=prof.digest)
    if recipe.snapshot is not None and recipe.path is not None:
        res.restored = os.path.abspath(recipe.path)
    results = _results(recipe)
    res.parameters = list(results.values())
    if unit == 0 and not opts.allow_broadcast:
        raise UsageError("unit 0 is broadcast (no device answers, nothing can be verified); to send it anyway, "
                         "allow broadcast (--allow-broadcast; ApplyOptions(allow_broadcast=True) in Python)")
    if unit == 0 and (prof.preconditions or any(d.parameter.mask for d in recipe.desired)):
        raise UsageError("a broadcast cannot read: bit fields (which keep the register's other bits) and "
                         f"preconditions of profile {prof.id} need a device that answers")
    try:
        return await _locked(recipe, url, unit, opts, res, results)
    except asyncio.CancelledError:
        interrupted(res, results)
        raise DeviceInterrupted(res) from None


class DeviceInterrupted(asyncio.CancelledError):
    """The device's apply was cancelled (the run interrupted): ``result`` says what it holds as far as known."""

    def __init__(self, result: DeviceResult) -> None:
        super().__init__(result.name)
        self.result = result


def interrupted(res: DeviceResult, results: dict[str, ParameterResult]) -> None:
    """What an interrupted device's report says: every write that went out is unverified, the one that was
    out when the run stopped may have been applied, the rest was not sent."""
    out = [(r.address, r.address + r.count) for r in res.requests if r.result == "interrupted" and r.function != 3]
    for p in results.values():
        if any(a < p.address + p.count and p.address < b for a, b in out):
            p.status, p.error = "unverified", "the run was interrupted while its write request was out: " \
                                              "it may have been applied"
        elif p.status == "unverified" and p.error == PENDING:
            p.error = "written; not read back: the run was interrupted"
        elif p.status == "skipped" and p.error is None:
            p.error = "not written: the run was interrupted"
    res.status = "interrupted"
    if res.snapshot is None:
        res.error = "the run was interrupted before the first write to this device; nothing was written"
    else:
        res.error = ("the run was interrupted while writing this device: some parameters may hold new values; "
                     f"restore with: deployer rollback {res.snapshot}")


async def _locked(recipe: Recipe, url: tp.DeviceURL, unit: int, opts: ApplyOptions, res: DeviceResult,
                  results: dict[str, ParameterResult]) -> tuple[DeviceResult, Awaitable[object] | None]:
    prof = recipe.profile
    try:
        held = [] if opts.lock_held else await lock.acquire_device(
            url.lock_keys, unit, timeout=opts.lock_timeout, command=lock.command_line(), directory=opts.lock_dir,
            run=opts.run_id)
    except Locked as e:
        res.status, res.error = "unreachable", f"{e}; nothing was sent"
        return res, None
    try:
        res.notices.extend(h.stale for h in held if h.stale)
        target = Target(tp.describe(url), unit, profile_ref(prof))
        transport = tp.open_transport(url)
        transport.set_pacing(*tp.pacing(url, prof.limits.pause_after_connect, prof.limits.pause_between_requests))
        try:
            await transport.connect()
        except Unreachable as e:
            res.status, res.error = "unreachable", str(e)
            return res, None
        session = Session(transport, unit, retries=url.retries, backoff=opts.backoff, records=res.requests)
        try:
            if unit == 0:
                await _broadcast(session, recipe, target, opts, res, results)
            else:
                await _apply(session, recipe, target, opts, res, results, learned.device_id(url, unit))
        finally:
            await transport.close()
        if (doubt := session.trust.notice()) is not None:
            res.notices.append(doubt)
        res.settle()
        if opts.keep_lock is not None and held and opts.keep_lock(res, held):
            held = []  # its window holds them now, until the commit or the rollback
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
                 results: dict[str, ParameterResult], key: str) -> None:
    # 1. before any write: identity and current values; a silent device here is "unreachable"
    found = await _read_before(session, recipe, opts, res, key)
    if found is None:
        return
    recipe, shared, before = found
    prof = recipe.profile
    for n, regs in before.items():
        results[n].before_raw = regs

    # 2. the plan: a saved one must still match the device, else a fresh diff-aware plan
    plan, planned = _the_plan(recipe, target, opts, before, shared)
    facts = planned.facts if planned is not None else _facts(plan, prof)
    for n in facts.unchanged:
        results[n].status = "unchanged"
    for n, raw in facts.fields:  # a field's register goes whole: report the word planned
        results[n].desired_raw = raw
    if not plan.writes:
        _verify(results, prof, before, written=set())
        # a retry of a device whose commit failed: the values were verified (and soaked, confirmed) by that run,
        # and nothing is left to write: its commit is owed, sent now
        if opts.commit_owed and prof.commit and not opts.hold_commit and all(
                r.status in ("ok", "unchanged") for r in results.values()):
            await _commit(session, prof, res, around=True)
        return
    # guards (e.g. "drive stopped") only matter when something is to be written
    try:
        why = await check_preconditions(session, prof)
    except (DeviceGone, ExceptionResponse) as e:
        why = f"reading the preconditions failed: {e}"
    if why:
        res.status, res.error = "failed", f"{why}; nothing was written"
        return
    if opts.confirm is not None and not await opts.confirm(plan, res):
        raise Declined("nothing was written (declined)")

    # 3. the snapshot is on disk before the first write, and the journal says this device is being written
    if not await _save_snapshot(recipe, opts, res, before, plan, planned):
        return
    if opts.on_writing is not None:
        opts.on_writing(res)

    # 4. unlock, writes in plan order (recovering from partial failures), read-back, commit, lock
    await _write_phase(session, recipe, plan, opts, res, results, key, dict(facts.desired))


async def _read_before(session: Session, recipe: Recipe, opts: ApplyOptions, res: DeviceResult, key: str
                       ) -> tuple[Recipe, _Shared, dict[str, tuple[int, ...]]] | None:
    """Identity, firmware and current values, and the limits the device taught (the recipe over them);
    None when nothing may be written (the device's status says why)."""
    prof = recipe.profile
    try:
        try:
            await check_identity(session, prof)
        except IdentityMismatch as e:
            res.status, res.error = "failed", f"{e}; nothing was written"
            return None
        shared = _shared(recipe)
        before = shared.values(await session.read_blocks(shared.reads, prof))
        # after a register answered: a device silent on Function 43 is not taken for an absent one
        res.identity = await session.identify()
        why = check_identity_objects(prof, res.identity)
        if why is None:  # the revision found against the profile's and each named parameter's
            why = await check_firmware(session, prof, res.identity, shared.names)
        if why:
            res.status, res.error = "failed", f"{why}; nothing was written"
            return None
        _identity_notice(opts, res)
        recipe = _taught_limits(recipe, opts, res, key)
    except Untrusted as e:  # it answers, but what it answered cannot be told from another request's answer
        res.status, res.error = "failed", f"{e}; nothing was written"
        return None
    except DeviceGone as e:
        res.status, res.error = "unreachable", f"{e}; nothing was written"
        return None
    except ExceptionResponse as e:
        res.status, res.error = "failed", f"reading the current values answered {e}; nothing was written"
        return None
    if not session.gap_reads:  # the refused read is in res.requests; say why the reads that follow differ
        res.notices.append("the device refused a read across undeclared registers (exception 02): "
                           "it is read in gap-free blocks (the profile's limits.max_read_gap is not for it)")
    return recipe, shared, before


def _identity_notice(opts: ApplyOptions, res: DeviceResult) -> None:
    """The same name answering with other Function 43 objects than at its last snapshot: a replaced device."""
    if res.identity is not None:
        last = last_identity(opts.state_dir, res.name)
        if last is not None and last[1] != res.identity:
            res.notices.append(f"the device's identity changed since its last snapshot "
                               f"({os.path.basename(last[0])}: {_identity_text(last[1])}; now "
                               f"{_identity_text(res.identity)}): it may have been replaced")


def _taught_limits(recipe: Recipe, opts: ApplyOptions, res: DeviceResult, key: str) -> Recipe:
    """``recipe`` over the limits this device taught an earlier run (not for a saved plan, nor when its
    identity changed since)."""
    prof = recipe.profile
    try:  # the run checked the file before it started: damaged since, it is not used (and said)
        taught = learned.lookup(opts.state_dir, profile_ref(prof), key) if opts.expected is None else None
    except InputError as e:
        taught = None
        res.notices.append(f"what devices taught is not used: {e}")
    if taught is None:
        return recipe
    if taught.identity is not None and res.identity is not None and taught.identity != res.identity:
        res.notices.append("the device's identity changed since it taught "
                           f"{taught.describe_limits()} ({_identity_text(taught.identity)}, now "
                           f"{_identity_text(res.identity)}): not used")
    elif (over := _over_limits(recipe, taught)) is not recipe:
        res.notices.append(learned.note(taught))
        return over
    return recipe


_TAUGHT: dict[tuple[int, tuple[tuple[str, int], ...]], tuple[Recipe, Recipe]] = {}


def _over_limits(recipe: Recipe, taught: learned.Entry) -> Recipe:
    """``recipe`` with its profile over the limits a device taught (``learned.with_limits``); ``recipe`` itself
    when they change nothing. One recipe for all the devices that taught the same limits: their plans are
    shared as other devices' are (``_shared``, ``_planned`` know a recipe by its identity)."""
    key = (id(recipe), tuple(sorted(taught.limits.items())))
    hit = _TAUGHT.get(key)
    if hit is None or hit[0] is not recipe:  # the recipe is kept in the entry, so its id is not reused
        while len(_TAUGHT) >= _SHARED_KEPT:
            del _TAUGHT[next(iter(_TAUGHT))]
        prof = learned.with_limits(recipe.profile, taught)  # from the limits alone
        hit = _TAUGHT[key] = (recipe, recipe if prof is recipe.profile else replace(recipe, profile=prof))
    return hit[1]


def _the_plan(recipe: Recipe, target: Target, opts: ApplyOptions, before: dict[str, tuple[int, ...]],
              shared: _Shared) -> tuple[Plan, _Planned | None]:
    """The saved plan (refused when the device changed since it was made), else a fresh diff-aware one;
    and the planner's result it came from (None for a saved plan)."""
    prof = recipe.profile
    if opts.expected is not None:
        changed = [pp.name for pp in opts.expected.parameters
                   if pp.current_raw is not None and not prof.parameter(pp.name).same_value(before.get(pp.name),
                                                                                            pp.current_raw)]
        if changed:
            raise StalePlan(
                "the device changed since the plan was made (" + ", ".join(
                    f"{n}: now {show_registers(prof.parameter(n), before.get(n))}" for n in changed)
                + "); make a new plan")
        return opts.expected, None
    return _planned(recipe, target, before, opts.write_all, shared)


async def _save_snapshot(recipe: Recipe, opts: ApplyOptions, res: DeviceResult, before: dict[str, tuple[int, ...]],
                         plan: Plan, planned: _Planned | None) -> bool:
    """The snapshot on disk and the journal's device-started line, both made durable by the group-commit
    thread (sharing fsyncs with the other devices of a fleet); False (and nothing written) when it cannot be."""
    applied = opts.applied or (os.path.abspath(recipe.path) if recipe.path else None)  # a fleet: the device's own
    snap = snapshot_file(opts.state_dir, res.name, recipe, before, res.url, res.unit, applied=applied,
                         identity=res.identity,
                         values_text=None if planned is None else planned.snapshot_values(recipe.profile, before))
    if opts.run_id is not None:
        digest = planned.digest(plan.device) if planned is not None else plan_digest(plan)
        snap.journal = journal.path_of(opts.state_dir)
        snap.line = journal.device_started(opts.run_id, name=res.name, url=res.url, unit=res.unit, plan_digest=digest,
                                           batch=res.batch, restoring=res.restored)
    try:
        res.snapshot = await durable(snap)
        res.snapshot_sha256 = snap.digest
        if res.snapshot is not None:
            snapshot_written(res.snapshot)
    except OSError as e:
        if not opts.restoring:  # no snapshot, no write: nothing could be undone
            res.status, res.error = "failed", (f"cannot save the snapshot in {opts.state_dir}: {disk_error(e)}; "
                                               "nothing was written")
            return False
        # a window's rollback restores values the run verified: a full disk must not stop it
        res.unrecorded.append(f"the snapshot of what it held before the rollback could not be saved in "
                              f"{opts.state_dir}: {disk_error(e)}")
    return True


async def _write_phase(session: Session, recipe: Recipe, plan: Plan, opts: ApplyOptions, res: DeviceResult,
                       results: dict[str, ParameterResult], key: str, desired: dict[str, tuple[int, ...]]) -> None:
    """Unlock, the writes in plan order (recovering from partial failures), read-back, commit, lock; what the
    device taught is remembered. ``desired``: each planned parameter's registers (bit fields: merged anew)."""
    prof = recipe.profile
    if prof.unlock:
        try:
            await _send_actions(session, prof, prof.unlock)
        except (DeviceGone, ExceptionResponse) as e:
            res.status, res.error = "failed", f"unlock failed: {e}; no parameter was written"
            return
    try:
        await _write_verify_commit(session, prof, recipe, plan, opts, res, results, desired)
        res.seen = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())  # the read-back: what "as left" shows
        if res.learned:
            try:
                learned.remember(opts.state_dir, learned.Entry(
                    profile_ref(prof), key, dict(res.learned),
                    next((n for n in res.notices if "; set limits." in n), ""), learned.now(), res.identity,
                    res.url, res.unit))
            except InputError as e:  # damaged since the run started: said, not overwritten
                res.notices.append(f"what the device taught is not remembered: {e}")
            except UsageError as e:  # a full disk: the device's outcome stands, only the lesson is lost
                res.unrecorded.append(f"what the device taught is not remembered: {e}")
    finally:
        if prof.unlock and prof.lock:
            try:
                await _send_actions(session, prof, prof.lock)
            except (DeviceGone, ExceptionResponse) as e:
                res.status = "failed"  # its parameters say what they hold; the device is not left as it should be
                res.error = f"{res.error + '; ' if res.error else ''}lock failed: {e}; the device may be left unlocked"
    res.notices.extend([f"{n} takes effect after a power cycle" for n in _shared(recipe).restart
                        if results[n].status == "ok"])


def _identity_text(identity: dict[str, str]) -> str:
    return ", ".join(f"{k} {v!r}" for k, v in identity.items()) or "none"


async def _write_verify_commit(session: Session, prof: Profile, recipe: Recipe, plan: Plan, opts: ApplyOptions,
                               res: DeviceResult, results: dict[str, ParameterResult],
                               desired: dict[str, tuple[int, ...]]) -> None:
    learning = Learning()
    try:
        written, unanswered = await _write_all(session, prof, plan, opts, results, learning, res.notices, desired)
    finally:
        res.learned = learning.limits(results)
        res.notices.extend(learning.notices(results, prof.id))

    # read back everything the plan reads, compare raw values (after a silence too: it may be back)
    try:
        after = _shared(recipe).values(await session.read_blocks(plan.reads, prof))
    except (DeviceGone, ExceptionResponse) as e:
        for n in written:
            if results[n].error == PENDING:
                results[n].error = f"read-back failed: {e}"
        return
    _verify(results, prof, after, written, unanswered or ())
    if unanswered is not None:
        return

    # commit (e.g. store to EEPROM) only when everything is verified; a soak or a confirmation holds it back
    if not prof.commit:
        return
    if not all(r.status in ("ok", "unchanged") for r in results.values()):
        res.commit = "not sent"
        return
    if opts.holds_commit:
        res.commit = "held"
        return
    await _commit(session, prof, res, around=False)


async def _commit(session: Session, prof: Profile, res: DeviceResult, *, around: bool) -> None:
    """The profile's commit steps now (``around``: with its unlock and lock steps; else the apply's writes are
    between them): a step that fails makes the device ``failed``, its parameters stay ``ok`` (verified, in RAM)."""
    failed = await commit_steps(session, prof, around=around)
    if failed is None:
        res.commit = "sent"
        return
    why, commit_failed = failed
    res.status, res.commit = "failed", "failed" if commit_failed else "sent"
    res.error = f"{res.error}; {why}" if res.error else why


async def _write_all(session: Session, prof: Profile, plan: Plan, opts: ApplyOptions,
                     results: dict[str, ParameterResult], learning: Learning,
                     notices: list[str] | None = None,
                     desired: dict[str, tuple[int, ...]] | None = None) -> tuple[set[str], set[str] | None]:
    """Send the plan's writes. Returns the names sent, and, when the device went away, the names of the
    request it did not answer (None while it answers).

    A request the device refuses whole is split and sent again (recovery.py); once a refusal is
    known to be for length alone, or Function 16 answered 01, the later requests go in the form the
    device takes (``learning``).
    """
    if desired is None:
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
        if req.function == 16 and learning.fc06:
            pending.extendleft(reversed(single_writes(prof, req)))
            continue
        cap = learning.update_cap(results, written) if req.function == 16 else 0
        if cap and req.count > cap:
            pieces = chunks(prof, req, cap)
            if len(pieces) > 1:
                pending.extendleft(reversed(pieces))
                continue
        try:
            req = await _remerge(session, prof, req, desired, results)
        except (DeviceGone, ExceptionResponse) as e:  # nothing of this request was sent
            for n in req.parameters:
                results[n].status, results[n].error = "failed", f"reading the register to keep its other bits: {e}"
            stopped = opts.on_error == "stop"
            continue
        try:
            await session.write(req)
            learning.took(req)
            _attempted(results, req.parameters, written)
            wait = prof.wait_after(req.stage)
            if wait and (not pending or pending[0].stage != req.stage):
                await asyncio.sleep(wait / 1000)
        except ExceptionResponse as e:
            if e.code == 1 and req.function == 16 and not learning.fc06:  # no Function 16: nothing was written
                learning.fc06 = True
                pending.extendleft(reversed(single_writes(prof, req)))
                continue
            rec = await _recover(session, prof, req, e, desired, results, written, notices)
            if rec.took_all:  # the device complained, but the values are there: go on as after a plain answer
                continue
            if rec.halves is not None:  # refused whole: the halves find the culprit (under --on-error stop too)
                learning.refused.append((req.count, req.parameters))
                pending.extendleft(reversed(rec.halves))
                continue
            if opts.on_error == "continue":
                if rec.follow_up is not None:
                    pending.appendleft(rec.follow_up)
            else:
                stopped = True
                if rec.follow_up is not None:
                    for n in rec.follow_up.parameters:
                        results[n].status = "skipped"
        except DeviceGone as e:
            # the request may or may not have been applied: the read-back (if any) decides
            _attempted(results, req.parameters, written, f"device stopped answering: {e}")
            for rest in pending:
                for n in rest.parameters:
                    results[n].status = "skipped"
            return written, set(req.parameters)
    return written, None
