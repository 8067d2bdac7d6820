"""The watch: every device read at its interval (devices of one bus one after the other, within the bus share),
drift found against the adopted state, a replaced unit told from the one it replaces, and the restores that
``--on-drift restore`` and ``--on-replace restore`` ask for (runs of their own: ``runs.Runs``).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import replace
from decimal import Decimal
from typing import Any

from ..api import Profile
from ..errors import DeviceGone, ExceptionResponse, IdentityMismatch, TransportError, Unreachable
from ..execute.connect import connected
from ..execute.executor import check_identity
from ..execute.job import Job
from ..execute.session import ApplyOptions
from ..execute.verify import values_of
from ..planning.planner import plan_reads
from ..transport.urls import describe
from . import desired as ds
from .model import ApiError, Device
from .runs import Runs
from .site import Site


class Watch:
    def __init__(self, site: Site, runs: Runs) -> None:
        self.site, self.runs = site, runs
        self.settings, self.devices, self.first, self.event = site.settings, site.devices, site.first, site.event
        self.wake = asyncio.Event()  # a round now (a reload, a client's check)
        self._buses: dict[str, asyncio.Lock] = {}  # the watch reads one device of a bus at a time ...
        self._bus_free: dict[str, float] = {}  # ... and not before this monotonic time (the bus share)
        self.checks = 0  # rounds done
        self.check_seconds = 0.0  # the last round's

    async def forever(self) -> None:
        while True:
            started = time.monotonic()
            try:
                await self.check(due_only=True)
            except Exception as e:  # the watch must go on; say what broke it this round
                self.event("internal", f"the check failed: {type(e).__name__}: {e}")
            if self.first.collecting:  # the first round is over: the restores it asked for, staged
                self.first.start(self.runs)
            # a round as often as the most frequent device asks; each device is read when its own time is due
            every = min([d.check_every for d in self.devices.values()] or [self.settings.check_every])
            left = every - (time.monotonic() - started)
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self.wake.wait(), max(0.0, left))
            self.wake.clear()

    async def check(self, names: Sequence[str] | None = None, *, due_only: bool = False) -> None:
        """Read every owned device (devices of one bus one after the other, within the bus share);
        ``due_only``: those whose own interval has passed since their last check."""
        now = time.time()
        todo = [
            d
            for d in self.devices.values()
            if (names is None or d.name in names)
            and not (due_only and d.last_check is not None and now - d.last_check < d.check_every * 0.95)
        ]
        for d in todo:
            if not d.owned:
                self.site.take(d)
        buses: dict[str, list[Device]] = {}
        for d in todo:
            if d.owned and d.run is None and not d.checking:
                buses.setdefault(d.job.url.bus, []).append(d)
        gate = asyncio.Semaphore(self.settings.parallel)
        t0 = time.monotonic()

        async def bus(key: str, devs: list[Device]) -> None:
            one_at_a_time = self._buses.setdefault(key, asyncio.Lock())
            async with gate:
                for d in devs:
                    async with one_at_a_time:  # the watch and a client's check share the bus's pace
                        wait = self._bus_free.get(key, 0.0) - time.monotonic()
                        if wait > 0:
                            await asyncio.sleep(wait)
                        began = time.monotonic()
                        await self._check_one(d)
                        spent = time.monotonic() - began
                        # leave the bus to others: watching takes at most its share of the bus's time
                        self._bus_free[key] = time.monotonic() + spent * (1 / self.settings.bus_share - 1)

        await asyncio.gather(*(bus(k, g) for k, g in buses.items()))
        self.checks += 1
        self.check_seconds = time.monotonic() - t0

    async def _check_one(self, dev: Device) -> None:
        if dev.adopted is None or dev.run is not None or dev.checking:
            return
        dev.checking = True
        try:
            await self._check_device(dev)
        finally:
            dev.checking = False

    async def _check_device(self, dev: Device) -> None:
        assert self.site.store is not None and dev.adopted is not None
        prof = dev.adopted.profile
        names = [n for n in dev.adopted_values if prof.parameter(n).readable]
        known = self.site.store.identity(dev.name)
        ask43 = known is None or known[2] is not False
        try:
            values, objects, answered43 = await _read(dev.job, prof, names, ask43)
        except _OtherModel as e:
            dev.last_check = time.time()
            if dev.replaced != str(e):
                dev.replaced, dev.status = str(e), "replaced"
                dev.replaced_total += 1
                self.event(
                    "replace-refused",
                    f"{dev.name}: another kind of device answers: {e}; nothing written",
                    device=dev.name,
                )
            return
        except (TransportError, DeviceGone) as e:
            dev.last_check = time.time()
            if dev.unreachable_since is None:
                dev.unreachable_since = time.time()
                self.event("unreachable", f"{dev.name}: {e}", device=dev.name)
            dev.status, dev.unreachable_why = "unreachable", str(e)
            return
        was_unreachable = dev.unreachable_since is not None
        if was_unreachable:
            dev.unreachable_since = dev.unreachable_why = None
            self.event("reachable", f"{dev.name}: answers again", device=dev.name)
        dev.last_values, dev.last_check = values, time.time()
        regs = {f"0x{c.address:04X}": c.raw for c in prof.identity}
        replaced = self._replaced(dev, known, objects, was_unreachable, values)
        if replaced is not None and not await self._on_replaced(dev, known, objects, replaced):
            return  # another model: its identity is not recorded, so every check refuses it again, quietly
        if known is None or known[0] != objects or (ask43 and known[2] is None):
            self.site.store.set_identity(dev.name, objects, regs, answered43 if ask43 else known[2] if known else None)
        if replaced is not None:
            return
        dev.replaced = None
        drift = drifted(prof, dev.adopted_values, values)
        if not drift:
            if dev.drift:
                self.event("drift-cleared", f"{dev.name}: holds the adopted state again", device=dev.name)
            dev.drift, dev.status = [], "ok"
            left = {n: values[n] for n in dev.adopted_values if n in values}
            if left != dev.asleft:  # a commit (an fsync) only when they changed, not at every check
                self.site.store.set_asleft(dev.name, left, "check")
                dev.asleft = left
            return
        first = not dev.drift
        dev.drift, dev.status = drift, "drifted"
        if first:
            dev.drift_events += 1
            self.event(
                "drift",
                f"{dev.name}: {', '.join(_said(d) for d in drift)}",
                device=dev.name,
                detail={"parameters": drift},
            )
        if dev.on_drift == "restore":
            self._restore(dev, "drift")

    def _replaced(
        self,
        dev: Device,
        known: tuple[dict[str, str] | None, dict[str, int], bool | None] | None,
        objects: dict[str, str] | None,
        was_unreachable: bool,
        values: Mapping[str, tuple[int, ...]],
    ) -> str | None:
        """Why this looks like another unit than the one last seen (None: the same one)."""
        if known is not None and known[0] is not None and objects is not None:
            before, now = known[0], objects
            changed = [k for k in sorted(set(before) | set(now)) if before.get(k) != now.get(k)]
            if changed:
                return "its identity changed: " + ", ".join(f"{k} {before.get(k)!r} -> {now.get(k)!r}" for k in changed)
        if was_unreachable and dev.adopted is not None:
            prof = dev.adopted.profile
            # a unit's own settings (its address ...) are set on a replacement before it answers at all
            compared = [
                (n, prof.parameter(n).default_registers()) for n in dev.adopted_values if not prof.parameter(n).per_unit
            ]
            compared = [(n, d) for n, d in compared if d is not None and n in values]
            differs = [n for n, d in compared if not prof.parameter(n).same_value(dev.adopted_values[n], d)]
            at_default = [n for n, d in compared if prof.parameter(n).same_value(values[n], d)]
            if differs and len(at_default) == len(compared):
                return f"it answers again holding its factory defaults ({', '.join(differs)} not as adopted)"
        return None

    async def _on_replaced(self, dev: Device, known: Any, objects: dict[str, str] | None, why: str) -> bool:
        """A replaced unit: restored (``--on-replace restore``) or reported. False: another model, refused."""
        if known is not None and known[0] is not None and objects is not None:
            model = [k for k in ("vendor", "product_code") if known[0].get(k) != objects.get(k)]
            if model:
                said = f"replaced by another model ({why}); nothing written"
                if dev.replaced != said:
                    dev.replaced, dev.status = said, "replaced"
                    dev.replaced_total += 1
                    self.event(
                        "replace-refused",
                        f"{dev.name}: {said}",
                        device=dev.name,
                        detail={"before": known[0], "now": objects},
                    )
                dev.status = "replaced"
                return False
        dev.status, dev.replaced = "replaced", why
        dev.replaced_total += 1
        self.event(
            "replaced",
            f"{dev.name}: replaced: {why}",
            device=dev.name,
            detail={"before": None if known is None else known[0], "now": objects},
        )
        if dev.on_replace == "restore":
            self._restore(dev, "replaced")
        return True

    # ---- restores -------------------------------------------------------------------------------------

    def _restore(self, dev: Device, why: str) -> None:
        """Write the adopted state (drift) or the as-left values without per-unit parameters (replaced) back."""
        assert self.site.store is not None and dev.adopted is not None
        if dev.run is not None:  # a run has it already (a restore started by a check a moment ago)
            return
        if self.first.stopped is not None:  # the first restores failed: reported, not written, until a restart
            return
        now = time.time()
        while dev.restores and dev.restores[0] < now - 3600:
            dev.restores.popleft()
        if len(dev.restores) >= self.settings.max_restores:
            if len(dev.restores) == self.settings.max_restores:
                dev.restores.append(now)  # said once per hour, not at every check
                self.event(
                    "restore-limit",
                    f"{dev.name}: drifted again after {self.settings.max_restores} restores "
                    "within an hour: reported, not fought (restore it through the agent after a look)",
                    device=dev.name,
                )
            return
        dev.restores.append(now)
        recipe = dev.adopted
        if why == "replaced":  # the values it was left with, but never those that belong to the unit
            left = self.site.store.asleft(dev.name)
            values = dict(left[0]) if left is not None else dict(dev.adopted_values)
            prof = dev.adopted.profile
            values = {n: v for n, v in values.items() if n in dev.adopted_values and not prof.parameter(n).per_unit}
            path = os.path.join(self.site.folder, "restore", f"{ds._safe(dev.name)}.yaml")
            ds.write_adopted(
                self.site.state_dir,
                replace(dev.job, recipe=dev.adopted),
                values,
                why="as left, for a replaced unit (per-unit parameters left out)",
                path=path,
            )
            recipe = ds.load_adopted(path)
        job = Job(dev.name, recipe, dev.job.url, dev.job.unit)
        if self.first.keep(job, why):  # the first round's restores start together, staged, after that round
            return
        try:
            self.runs.start_run(
                [job], command="restore", options={"reason": why}, opts=ApplyOptions(), label=recipe.path
            )
        except ApiError as e:
            self.event("restore-failed", f"{dev.name}: {e}", device=dev.name)


class _OtherModel(Exception):
    """The identity registers say another kind of device answers at the address."""


async def _read(
    job: Job, profile: Profile, names: Sequence[str], ask43: bool
) -> tuple[dict[str, tuple[int, ...]], dict[str, str] | None, bool]:
    """One check's read at ``job``'s address: Function 43 objects (when the device answers it), the identity
    registers, the values of ``names`` (as ``profile``, the adopted one, has them)."""
    async with connected(job.url, job.unit, profile) as session:
        try:
            objects = await session.identify() if ask43 else None
            try:
                await check_identity(session, profile)
            except IdentityMismatch as e:
                raise _OtherModel(str(e)) from None
            params = [profile.parameter(n) for n in names]
            values = values_of(params, await session.read_blocks(plan_reads(profile, list(names)), profile))
            return values, objects, objects is not None
        except ExceptionResponse as e:
            raise Unreachable(f"{describe(job.url)} unit {job.unit}: reading answered {e}") from None


def drifted(
    profile: Profile, adopted: Mapping[str, tuple[int, ...]], values: Mapping[str, tuple[int, ...]]
) -> list[dict[str, Any]]:
    """The adopted parameters the device does not hold (beyond their tolerance), or cannot be read."""
    out = []
    for n, want in adopted.items():
        p = profile.parameter(n)
        if not p.readable:
            continue
        have = values.get(n)
        if have is not None and p.same_value(have, want):
            continue
        if have is not None and p.tolerance and not p.is_string and not p.values:
            try:
                if abs(p.to_engineering(have) - p.to_engineering(want)) <= Decimal(p.tolerance):
                    continue
            except Exception:  # a value the codec cannot show is drift, not a crash
                pass
        out.append(
            {
                "name": n,
                "adopted": p.show_registers(want),
                "device": None if have is None else p.show_registers(have),
                "adopted_raw": list(want),
                "device_raw": None if have is None else list(have),
            }
        )
    return out


def _said(d: Mapping[str, Any]) -> str:
    return f"{d['name']} is {d['device'] if d['device'] is not None else 'unreadable'} (adopted {d['adopted']})"
