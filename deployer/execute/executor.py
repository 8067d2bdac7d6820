"""The executor: the only code that sends a plan's steps to a device, and exactly those steps, in order.

``Execution`` runs a plan on one device's session. ``checks`` runs the steps that lead every plan (identity,
snapshot reads, device identification, firmware) and says what the device holds; ``changes`` runs the rest
(preconditions, unlock, writes, read-back, commit, lock). Between the two a caller may plan (``apply RECIPE``:
the plan is made against what the checks read, in the same session, so the device sees exactly the plan) or
check a saved plan against it (``apply PLAN.json``: the stale-plan rule).

Every request is logged with the step it executes. What only the device can decide is done as a named
deviation from the step it stands in for (``Session.deviating``): a request refused whole is split and sent
again (``split``), Function 16 refused with 01 goes as Function 06 (``function-06``), the registers of a
refused request are read to see what took (``recovery-read``), the values after a rejected one go in a new
request (``follow-up``), a read refused across undeclared registers goes in gap-free blocks (``gap-free``),
a part of a split bit-field write reads its register again (``read-modify-write``); a retry is an attempt
more of the same request (``attempts``). Nothing else may differ from the plan.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Awaitable, Callable, Mapping, Sequence

from ..errors import DeviceGone, ExceptionResponse, Untrusted
from ..planning.model import Plan, Step, WriteRequest
from ..planning.steps import secret_words
from ..profile import Profile, object_name
from ..profile.firmware import matches
from ..recipe.loader import Recipe
from ..report import DeviceResult, ParameterResult
from .recovery import Learning, _recover, _remerge, chunks, single_writes
from .session import ApplyOptions, Session
from .verify import PENDING, _attempted, _verify

# what stops a device's changes: the device's result says why; its parameters say what it holds
BeforeWrite = Callable[[], Awaitable[bool]]

# the kinds of deviation, for the report's readers (docs/reference/report.md)
DEVIATIONS = (
    "split",
    "function-06",
    "recovery-read",
    "follow-up",
    "gap-free",
    "read-modify-write",
    "more-objects",
    "confirm-read",
)


class Execution:
    """One device's plan being executed: the session, the results it fills in, and what the checks read."""

    def __init__(
        self,
        session: Session,
        recipe: Recipe,
        res: DeviceResult,
        results: dict[str, ParameterResult],
        options: ApplyOptions,
        values: Callable[[Mapping[int, int]], dict[str, tuple[int, ...]]],
    ) -> None:
        self.session = session
        self.recipe = recipe
        self.prof: Profile = recipe.profile
        self.res = res
        self.results = results
        self.opts = options
        self.values = values  # the recipe's parameters' registers from the words read (``Shared.values``)
        self.before: dict[str, tuple[int, ...]] = {}
        self.learning = Learning()
        self.written: set[str] = set()
        self.unanswered: set[str] | None = None  # a write the device did not answer: its parameters
        self.stopped = False  # --on-error stop after a refused request
        self.revision: str | None = None  # the firmware revision read by a firmware step
        self.verified = False  # the read-back is done (or could not be)
        self.unlocked = False  # an unlock step went out: the lock steps go too
        self.merge_failed: str | None = None  # why the read before the coming bit-field write failed
        self.silent_identification = False  # the device-id step got no answer (the reads did)

    # ---- the checks ------------------------------------------------------------------------------------

    async def checks(self, steps: Sequence[Step]) -> bool:
        """The steps that lead every plan (``Plan.checks`` of them); False when nothing may be written (the
        device's result says why). ``self.before`` holds what the snapshot steps read."""
        res = self.res
        regs: dict[int, int] = {}
        snapshot = [n for n, s in enumerate(steps, 1) if s.kind == "snapshot"]
        try:
            for n, step in enumerate(steps, 1):
                self.session.step = n
                if step.kind == "identity":
                    why = await self._identity(step)
                    if why:
                        res.status, res.error = "failed", f"{why}; nothing was written"
                        return False
                elif step.kind == "snapshot":  # all of them at once: a refused gap re-plans the rest together
                    if n == snapshot[0]:
                        regs.update(
                            await self.session.read_blocks(
                                [steps[k - 1].read() for k in snapshot], self.prof, steps=snapshot
                            )
                        )
                elif step.kind == "device-id":
                    res.identity = await self.session.identify()
                    self.silent_identification = self.session.records[-1].result == "no response"
                else:  # firmware
                    words = await self.session.read(step.address, step.count, step.function)
                    assert self.prof.firmware is not None
                    self.revision = self.prof.firmware.revision_of(words)
        except Untrusted as e:  # it answers, but what it answered cannot be told from another request's answer
            res.status, res.error = "failed", f"{e}; nothing was written"
            return False
        except DeviceGone as e:
            res.status, res.error = "unreachable", f"{e}; nothing was written"
            return False
        except ExceptionResponse as e:
            res.status, res.error = "failed", f"reading the current values answered {e}; nothing was written"
            return False
        self.before = self.values(regs)
        asked = any(s.kind == "device-id" for s in steps)
        why = self._objects(asked) or self._firmware(asked)
        if why:
            res.status, res.error = "failed", f"{why}; nothing was written"
            return False
        if not self.session.gap_reads:  # the refused read is in res.requests; say why the reads that follow differ
            res.notices.append(
                "the device refused a read across undeclared registers (exception 02): "
                "it is read in gap-free blocks (the profile's limits.max_read_gap is not for it)"
            )
        return True

    async def _identity(self, step: Step) -> str | None:
        (value,) = await self.session.read(step.address, 1, step.function)
        assert step.expect is not None
        if step.expect.holds(value):
            return None
        what = f" ({step.note})" if step.note else ""
        table = "input register" if step.function == 4 else "register"
        return (
            f"identity check failed: {table} 0x{step.address:04X}{what} holds 0x{value:04X}, expected "
            f"0x{step.expect.equals:04X}: another kind of device answers here"
        )

    def _objects(self, asked: bool) -> str | None:
        """Why the device's Function 43 objects are not what the profile's identity checks expect, if they are not."""
        identity = self.res.identity
        for chk in self.prof.identity_objects:
            name = object_name(chk.object_id)
            what = f" ({chk.description})" if chk.description else ""
            if identity is None:
                how = (
                    "the device does not answer Function 43 (device identification)"
                    if asked
                    else "Function 43 (device identification) is not asked of this device"
                )
                return f"identity check failed: {how}; {name}{what} should be {chk.equals!r}"
            if identity.get(name) != chk.equals:
                have = repr(identity[name]) if name in identity else "missing"
                return (
                    f"identity check failed: {name}{what} is {have}, expected {chk.equals!r}: another kind of "
                    f"device answers here"
                )
        return None

    def _firmware(self, asked: bool) -> str | None:
        """Why the firmware revision is not one the profile and the recipe's parameters apply to, if it is not."""
        src, prof = self.prof.firmware, self.prof
        if src is None:
            return None
        gated = [d.parameter for d in self.recipe.desired if d.parameter.firmware is not None]
        if src.applies is None and not gated:
            return None
        revision = self.revision
        if src.address is None:
            name = object_name(src.object_id or 0)
            identity = self.res.identity
            revision = None if identity is None else identity.get(name)
            if revision is None:
                why = (
                    "its Function 43 answer has no " + name
                    if identity is not None
                    else "the device does not answer Function 43 (device identification)"
                    if asked
                    else "Function 43 (device identification) is not asked of this device"
                )
                return (
                    f"firmware revision unknown: {why}; profile {prof.id} needs it (set firmware.register where "
                    "the device reports it)"
                )
        assert revision is not None
        if src.applies is not None and not matches(src.applies, revision):
            return f"firmware {revision!r} ({src.describe()}) is not one profile {prof.id} applies to ({src.applies})"
        wrong = [p for p in gated if p.firmware is not None and not matches(p.firmware, revision)]
        if wrong:
            said = ", ".join(f"{p.name} needs {p.firmware}" for p in wrong[:5]) + (
                f" and {len(wrong) - 5} more" if len(wrong) > 5 else ""
            )
            return f"firmware {revision!r} ({src.describe()}): {said}"
        return None

    # ---- the changes -----------------------------------------------------------------------------------

    async def changes(self, plan: Plan, before_write: BeforeWrite | None = None) -> None:
        """The steps after the checks, in order. ``before_write``: awaited when the preconditions held, before the
        first step of a plan that writes a recipe parameter (the snapshot on disk); False stops the device there,
        nothing written."""
        steps = plan.steps
        writes = bool(plan.writes)
        if not writes:
            _verify(self.results, self.prof, self.before, written=set())
        desired = dict(plan._desired)
        merged: dict[int, int] = {}  # a bit field's register as read right before its write
        ready = before_write is None or not writes
        unhealthy: list[tuple[int, str]] = []  # the health checks failing before the change: index, why
        try:
            for n in range(plan.checks + 1, len(steps) + 1):
                step = steps[n - 1]
                self.session.step = n
                if step.kind == "precondition":
                    if not await self._precondition(step):
                        return
                    continue
                if step.kind == "health":
                    if not await self._health(step, unhealthy):
                        return
                    continue
                if unhealthy and not self._judge(unhealthy):
                    return
                unhealthy = []
                if not ready:
                    if before_write is not None and not await before_write():
                        return
                    ready = True
                if step.kind == "unlock":
                    if not await self._unlock(step, writes):
                        return
                elif step.kind == "read-modify-write":
                    if not self.stopped and self.unanswered is None and self.merge_failed is None:
                        merged.update(await self._merge_read(step))
                elif step.kind == "write":
                    await self._write(step, desired, merged)
                    merged.clear()
                    self.merge_failed = None
                elif step.kind == "verify":
                    await self._read_back(plan)
                elif step.kind == "commit":
                    await self._read_back(plan)
                    if not await self._commit(step, writes):
                        return
                else:  # lock: comes in the finally below
                    break
            await self._read_back(plan)
        finally:
            await self._lock(plan)

    async def _precondition(self, step: Step) -> bool:
        res = self.res
        try:
            (word,) = await self.session.read(step.address, 1, step.function)
        except (DeviceGone, ExceptionResponse) as e:
            res.status, res.error = "failed", f"reading the preconditions failed: {e}; nothing was written"
            return False
        assert step.expect is not None
        if step.expect.holds(word):
            return True
        what = f"register 0x{step.address:04X}" + _bits(step.expect.mask) + (f" ({step.note})" if step.note else "")
        res.status, res.error = (
            "failed",
            (
                f"precondition failed: {what} is {step.expect.found(word)}, expected "
                f"{step.expect.equals}; nothing was written"
            ),
        )
        return False

    async def _health(self, step: Step, unhealthy: list[tuple[int, str]]) -> bool:
        """A health check read before the change; its failure noted in ``unhealthy``. False (nothing written) when
        a safe change cannot read it."""
        try:
            words = await self.session.read(step.address, step.count, step.function)
        except (DeviceGone, ExceptionResponse) as e:
            if not self.opts.window:
                self.res.notices.append(f"a health check could not be read before the change: {e}")
                return True
            self.res.status, self.res.error = (
                "failed",
                (f"the health checks could not be read before the change: {e}; nothing was written"),
            )
            return False
        for i, c in enumerate(self.prof.health):
            if (c.function, c.address, c.count) == (step.function, step.address, step.count) and not c.holds(words):
                unhealthy.append((i, c.failure(words)))
        return True

    def _judge(self, unhealthy: list[tuple[int, str]]) -> bool:
        """A device already failing a health check: a safe change does not write it (it would be rolled back and
        the change blamed for the old alarm), unless the operator allows it; then the checks failing before are
        not held against the change during its window (``DeviceResult.unhealthy_before``). An apply that is no
        safe change of a safe change's plan says so and writes."""
        said = "; ".join(why for _, why in unhealthy)
        res = self.res
        if self.opts.window and not self.opts.allow_unhealthy:
            res.status, res.error = (
                "failed",
                (
                    f"health check already failing before the change: {said} (the change is not to blame for it; to "
                    "write it anyway: --allow-unhealthy); nothing was written"
                ),
            )
            return False
        if self.opts.window:
            res.unhealthy_before = tuple(i for i, _ in unhealthy)
            res.notices.append(
                f"health check already failing before the change, written anyway (--allow-unhealthy): "
                f"{said}; its window does not hold that check against the change"
            )
        else:
            res.notices.append(
                f"health check failing before the change: {said} (written all the same: only a "
                "safe change, --soak or --confirm-within, is judged by the health checks)"
            )
        return True

    async def _unlock(self, step: Step, writes: bool) -> bool:
        try:
            await self._action(step)
        except (DeviceGone, ExceptionResponse) as e:
            res = self.res
            if writes:
                res.status, res.error = "failed", f"unlock failed: {e}; no parameter was written"
            else:  # a commit owed by an earlier run
                res.status, res.commit = "failed", "failed"
                res.error = f"commit not sent: unlock failed: {e}; the values are verified, in RAM, not stored"
            return False
        self.unlocked = True
        return True

    async def _action(self, step: Step) -> None:
        """A profile's own write (unlock, commit, lock) and its wait. Function 16 refused with 01 (nothing was
        written): one Function 06 per register, a deviation."""
        values = step.values if step.values is not None else secret_words(self.prof, step)
        req = step.write(values)
        try:
            await self.session.write(req)
        except ExceptionResponse as e:
            if e.code != 1 or req.function != 16:  # a coil (05) or a single register (06) has no other form
                raise
            self.learning.fc06 = True  # no Function 16 here: the recipe's writes go as Function 06 from now on
            with self.session.deviating("function-06"):
                for w in single_writes_of(req):
                    await self.session.write(w)
        if step.wait:
            await asyncio.sleep(step.wait)

    async def _merge_read(self, step: Step) -> dict[int, int]:
        try:
            return await self.session.read_blocks([step.read()])
        except (DeviceGone, ExceptionResponse) as e:  # the write is not sent: its fields' bits cannot be kept
            self.merge_failed = f"reading the register to keep its other bits: {e}"
            return {}

    async def _write(self, step: Step, desired: dict[str, tuple[int, ...]], merged: dict[int, int]) -> None:
        """One planned write, and what the device makes of it: its deviations (splits, Function 06, the recovery
        after a refusal) are sent in its place and logged against it."""
        results = self.results
        if self.merge_failed is not None and not self.stopped and self.unanswered is None:
            for nm in step.parameters:
                results[nm].status, results[nm].error = "failed", self.merge_failed
            self.stopped = self.opts.on_error == "stop"
            return
        if self.stopped or self.unanswered is not None:
            for nm in step.parameters:
                if results[nm].status != "failed":
                    results[nm].status = "skipped"
            return
        req = step.write()
        if merged:
            req = self._merged(req, desired, merged)
        pending: deque[tuple[WriteRequest, str | None]] = deque([(req, None)])
        while pending:
            req, how = pending.popleft()
            if self.stopped:
                for nm in req.parameters:
                    if results[nm].status != "failed":
                        results[nm].status = "skipped"
                continue
            if req.function == 16 and self.learning.fc06:
                pending.extendleft((w, "function-06") for w in reversed(single_writes(self.prof, req)))
                continue
            cap = self.learning.update_cap(results, self.written) if req.function == 16 else 0
            if cap and req.count > cap:
                pieces = chunks(self.prof, req, cap)
                if len(pieces) > 1:
                    pending.extendleft((w, "split") for w in reversed(pieces))
                    continue
            if how is not None:  # a part not planned as such: its bit fields' register read again first
                try:
                    with self.session.deviating("read-modify-write"):
                        req = await _remerge(self.session, self.prof, req, desired, results)
                except (DeviceGone, ExceptionResponse) as e:  # nothing of this request was sent
                    for nm in req.parameters:
                        results[nm].status, results[nm].error = (
                            "failed",
                            f"reading the register to keep its other bits: {e}",
                        )
                    self.stopped = self.opts.on_error == "stop"
                    continue
            if not await self._send(req, how, pending, desired):
                return
        if step.wait:
            await asyncio.sleep(step.wait)

    def _merged(
        self, req: WriteRequest, desired: dict[str, tuple[int, ...]], merged: Mapping[int, int]
    ) -> WriteRequest:
        """The planned write with each bit field's register merged anew over what its read found."""
        from ..planning.planner import merge_fields

        prof, regs = self.prof, list(req.registers)
        fields = [prof.parameter(n) for n in req.parameters if prof.parameter(n).mask]
        for a in sorted({f.address for f in fields if f.key in merged}):
            mates = [f for f in fields if f.address == a]
            word = merge_fields(mates, [desired[m.name][0] for m in mates], merged[mates[0].key])
            regs[a - req.address] = word
            for m in mates:
                desired[m.name] = self.results[m.name].desired_raw = (word,)
        out = WriteRequest(req.function, req.address, tuple(regs), req.parameters, req.stage)
        if out.registers != req.registers:  # another field changed since the snapshot: kept as the device holds it
            self.res.notices.append(
                f"the register at 0x{req.address:04X} changed since the plan was made: its "
                "other bits are written as the device holds them now"
            )
        return out

    async def _send(
        self,
        req: WriteRequest,
        how: str | None,
        pending: deque[tuple[WriteRequest, str | None]],
        desired: dict[str, tuple[int, ...]],
    ) -> bool:
        """Send one request (``how``: the deviation it is part of) and handle the answer; False when the device
        went away (every later write is skipped; the read-back decides what the last one did)."""
        results, session = self.results, self.session
        try:
            if how is None:
                await session.write(req)
            else:
                with session.deviating(how):
                    await session.write(req)
            self.learning.took(req)
            _attempted(results, req.parameters, self.written)
        except ExceptionResponse as e:
            self.learning.refusals += 1
            if e.code == 1 and req.function == 16 and not self.learning.fc06:  # no Function 16: nothing was written
                self.learning.fc06 = True
                pending.extendleft((w, "function-06") for w in reversed(single_writes(self.prof, req)))
                return True
            with session.deviating("recovery-read"):
                rec = await _recover(session, self.prof, req, e, desired, results, self.written, self.res.notices)
            if rec.took_all:  # the device complained, but the values are there: go on as after a plain answer
                return True
            if rec.halves is not None:  # refused whole: the halves find the culprit (under --on-error stop too)
                self.learning.refused.append((req.count, req.parameters))
                pending.extendleft((w, "split") for w in reversed(rec.halves))
                return True
            if self.opts.on_error == "continue":
                if rec.follow_up is not None:
                    pending.appendleft((rec.follow_up, "follow-up"))
            else:
                self.stopped = True
                if rec.follow_up is not None:
                    for nm in rec.follow_up.parameters:
                        results[nm].status = "skipped"
        except DeviceGone as e:
            # the request may or may not have been applied: the read-back (if any) decides
            _attempted(results, req.parameters, self.written, f"device stopped answering: {e}")
            for rest, _ in pending:
                for nm in rest.parameters:
                    results[nm].status = "skipped"
            self.unanswered = set(req.parameters)
        return self.unanswered is None

    async def _read_back(self, plan: Plan) -> None:
        """The verify steps (all of them, once), compared with what was sent; what the device taught noted."""
        if self.verified or not plan.writes:
            return
        self.verified = True
        res, results = self.res, self.results
        res.learned.update(self.learning.limits(results))
        res.notices.extend(self.learning.notices(results, self.prof.id))
        self.learning.explain(results)
        verify, reads = plan._read_back
        try:  # after a silence too: it may be back
            regs = await self.session.read_blocks(reads, self.prof, steps=verify)
        except (DeviceGone, ExceptionResponse) as e:
            for nm in self.written:
                if results[nm].error == PENDING:
                    results[nm].error = f"read-back failed: {e}"
            self.unanswered = self.unanswered or set()  # nothing verified: no commit
            return
        _verify(results, self.prof, self.values(regs), self.written, self.unanswered or ())

    async def _commit(self, step: Step, writes: bool) -> bool:
        """A commit step, sent only when every parameter verified and no window holds it; False stops the rest
        (the lock still goes)."""
        res = self.res
        if writes:
            if res.commit in ("not sent", "held", "failed") or self.unanswered is not None:
                return True  # decided at the first commit step; a device gone or not read back: nothing said
            if not all(r.status in ("ok", "unchanged") for r in self.results.values()):
                res.commit = "not sent"
                return True
            if self.opts.holds_commit:
                res.commit = "held"
                return True
        elif not all(r.status in ("ok", "unchanged") for r in self.results.values()):
            res.commit = "not sent"
            return True
        try:
            await self._action(step)
        except (DeviceGone, ExceptionResponse) as e:
            res.status, res.commit = "failed", "failed"
            why = f"commit '{step.note or hex(step.address)}' failed: {e}; the values are verified, in RAM, not stored"
            res.error = f"{res.error}; {why}" if res.error else why
            return False
        res.commit = "sent"
        return True

    async def _lock(self, plan: Plan) -> None:
        """The lock steps, whenever an unlock step went out."""
        if not self.unlocked:
            return
        for n, step in enumerate(plan.steps, 1):
            if step.kind != "lock":
                continue
            self.session.step = n
            try:
                await self._action(step)
            except (DeviceGone, ExceptionResponse) as e:
                res = self.res
                res.status = "failed"  # its parameters say what they hold; the device is not left as it should be
                why = f"lock failed: {e}; the device may be left unlocked"
                res.error = f"{res.error}; {why}" if res.error else why
                return


def single_writes_of(req: WriteRequest) -> list[WriteRequest]:
    """A profile action's Function 16 request as Function 06 requests, one per register."""
    return [WriteRequest(6, req.address + i, (w,), (), req.stage) for i, w in enumerate(req.registers)]


def _bits(mask: int) -> str:
    if mask == 0xFFFF:
        return ""
    shift = (mask & -mask).bit_length() - 1
    width = (mask >> shift).bit_length()
    return f" bit {shift}" if width == 1 else f" bits {shift}..{shift + width - 1}"


async def check_identity(session: Session, profile: Profile) -> None:
    """The profile's identity registers, outside a plan (diff, pull, the agent's reads): raises IdentityMismatch
    unless every one holds its expected value."""
    from ..errors import IdentityMismatch
    from ..profile.model import READ_FUNCTION

    for chk in profile.identity:
        (value,) = await session.read(chk.address, 1, READ_FUNCTION[chk.register_type])
        if value != chk.raw:
            what = f" ({chk.description})" if chk.description else ""
            table = "input register" if chk.register_type == "input" else "register"
            raise IdentityMismatch(
                f"identity check failed: {table} 0x{chk.address:04X}{what} holds 0x{value:04X}, expected "
                f"0x{chk.raw:04X}: another kind of device answers here",
                address=chk.address,
                expected=chk.raw,
                found=value,
            )
