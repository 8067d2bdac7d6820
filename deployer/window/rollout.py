"""The window of a rollout: after each batch its soak and commits, at the end the confirmation or the rollback."""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import Callable, Sequence
from dataclasses import replace

from ..errors import UsageError
from ..execute.job import Job
from ..execute.session import ApplyOptions
from ..load.durations import format_duration
from ..report import DeviceResult, Report, write_json
from ..state import journal
from ..state.lock import DeviceLock
from .confirm import await_confirmation
from .finish import per_line, roll_back, send_commit
from .held import Written, needs_soak, pending_path, record, reserve, unreserve
from .soak import soak


def settle_commits(devices: Sequence[Written]) -> None:
    """A commit held for a device that did not end ok is never sent."""
    for w in devices:
        if w.result.commit == "held" and w.result.status != "ok":
            w.result.commit = "not sent"


class Window:
    """The safe-change part of one rollout (``options.soak``, ``options.confirm_within``, ``rollback_on_failure``).

    ``on_changed`` is told of a device whose result changed after it was reported done (rolled back,
    committed); ``on_soak(batch number, device names)`` when a soak starts; ``on_confirm_wait(run,
    deadline)`` once the run waits for its confirmation.
    """

    def __init__(
        self,
        opts: ApplyOptions,
        recipe_name: str | None,
        *,
        on_changed: Callable[[DeviceResult], None] | None = None,
        on_soak: Callable[[int, list[str]], None] | None = None,
        on_confirm_wait: Callable[[str, float], None] | None = None,
    ) -> None:
        self.opts = opts
        self.recipe_name = recipe_name
        self.on_changed = on_changed
        self.on_soak = on_soak
        self.on_confirm_wait = on_confirm_wait
        self.locks: dict[str, list[DeviceLock]] = {}  # device name -> the locks its window keeps
        if self.held:
            reserve(opts)

    def keep(self, res: DeviceResult, held: list[DeviceLock]) -> bool:
        """``ApplyOptions.keep_lock``: a device written and verified keeps its lock until its window ends (its
        commit, or its rollback), so no other run writes it in between."""
        if not needs_soak(res):
            return False
        self.locks[res.name] = held
        return True

    def device(self, job: Job, result: DeviceResult) -> Written:
        """The device of ``job`` in its window (with the locks it keeps, if any)."""
        return Written(job, result, self.locks.setdefault(job.name, []))

    @property
    def held(self) -> bool:
        """Whether changes wait at all (a soak or a confirmation)."""
        return self.opts.soak is not None or self.opts.confirm_within is not None

    def changed(self, devices: Sequence[Written]) -> None:
        if self.on_changed is not None:
            for w in devices:
                if w.result.snapshot is not None:
                    self.on_changed(w.result)

    async def after_batch(self, number: int, batch: Sequence[Written], so_far: Report) -> list[str]:
        """The batch's soak (its commits follow unless a confirmation waits); the devices whose health failed."""
        opts = self.opts
        if opts.soak is None:
            return []
        unhealthy: list[str] = []
        pending = self.write_pending(so_far)
        soaking = [w.name for w in batch if needs_soak(w.result)]
        if self.on_soak is not None and soaking:
            self.on_soak(number, soaking)
        passed = await soak(batch, opts, on_failed=lambda w: unhealthy.append(w.name), report=pending)
        if opts.confirm_within is None:  # the soak passed: the change is kept
            await per_line(passed, lambda w: send_commit(w, opts))
        self.changed(batch)
        return unhealthy

    async def end(self, devices: Sequence[Written], stop: str | None, *, rollback_on_failure: bool) -> None:
        """The rollout is over: roll everything back when it stopped (``rollback_on_failure``), then wait for the
        confirmation (its commits, or every device rolled back)."""
        opts = self.opts
        if stop is not None and rollback_on_failure:
            reason = f"rolled back: the rollout stopped ({stop.removeprefix('not started: ')})"
            await per_line(
                [
                    w
                    for w in devices
                    if w.result.snapshot is not None
                    and w.result.status not in ("rolled-back", "skipped", "unreachable")
                ],
                lambda w: roll_back(w, reason, opts),
            )
        if opts.confirm_within is not None:
            await self.confirm_or_roll_back(devices)
        settle_commits(devices)
        if rollback_on_failure or opts.confirm_within is not None:
            self.changed(devices)

    def interrupted(self, devices: Sequence[Written]) -> None:
        """The run was interrupted: the devices its window rolled back say so (the report file too)."""
        settle_commits(devices)
        if self.held:
            self.changed(devices)

    async def confirm_or_roll_back(self, devices: Sequence[Written]) -> None:
        """``confirm_within``: wait for ``deployer confirm``; then send the held commits, else roll every device
        back. While it waits, a report of the run lies in STATE/pending/ (``deployer status`` points a rollback
        at it should this process die)."""
        opts = self.opts
        assert opts.confirm_within is not None and opts.run_id is not None
        waiting = [w for w in devices if needs_soak(w.result)]
        if not waiting:
            return
        pending = self.write_pending(Report(self.recipe_name, [w.result for w in devices]))
        run = opts.run_id

        def on_wait(deadline: float) -> None:
            for w in waiting:  # a run refused meanwhile names this window and its deadline
                for h in w.locks:
                    h.in_window("confirm", deadline)
            if self.on_confirm_wait is not None:
                self.on_confirm_wait(run, deadline)

        # the health checks go on being read until the answer: a device that fails meanwhile is rolled back at once
        stop, gone = asyncio.Event(), asyncio.Event()
        watched = [w for w in waiting if w.recipe.profile.health]
        watcher = (
            asyncio.ensure_future(
                soak(
                    watched,
                    replace(opts, soak=opts.confirm_within),
                    report=pending,
                    until=stop,
                    during="the confirmation wait",
                )
            )
            if watched
            else None
        )
        if watcher is not None and len(watched) == len(waiting):  # all of them rolled back: nothing to confirm
            watcher.add_done_callback(
                lambda _: gone.set() if not any(w.result.status == "ok" for w in waiting) else None
            )
        try:
            confirmed = await await_confirmation(
                run, opts.confirm_within, opts, on_wait=on_wait, results=[w.result for w in waiting], gone=gone
            )
        except asyncio.CancelledError:  # Ctrl-C while waiting: the answer is no, at once
            stop.set()
            rolling = asyncio.ensure_future(
                self._stop_watching(watcher, waiting, "interrupted while waiting for the confirmation")
            )
            await asyncio.shield(rolling)
            raise
        stop.set()
        if watcher is not None:
            await watcher
            self.changed([w for w in watched if w.result.status != "ok"])
        holding = [w for w in waiting if w.result.status == "ok"]  # the unhealthy ones are rolled back already
        if confirmed:
            await per_line(holding, lambda w: send_commit(w, opts))
        else:
            why = f"not confirmed within {format_duration(opts.confirm_within)}"
            await per_line(holding, lambda w: roll_back(w, why, opts))
        # what `deployer confirm` waits for, to say whether the commit went out
        record(
            opts,
            {
                "event": "confirm-outcome",
                "run": run,
                "time": journal._now(),
                "confirmed": confirmed,
                "committed": [w.name for w in waiting if w.result.commit == "sent"],
                # confirmed, with no commit step to send: the values stay as written (in RAM where the
                # device keeps Modbus writes there)
                "kept": [w.name for w in waiting if not w.recipe.profile.commit and w.result.status == "ok"],
                "not_committed": {
                    w.name: w.result.error or w.result.status
                    for w in waiting
                    if w.result.status != "ok" or (w.recipe.profile.commit and w.result.commit != "sent")
                },
            },
            *(w.result for w in waiting),
        )

    async def _stop_watching(
        self, watcher: asyncio.Future[list[Written]] | None, waiting: Sequence[Written], why: str
    ) -> None:
        """Interrupted while waiting: the health watch ends, then every device still holding the change is
        rolled back."""
        if watcher is not None:
            await watcher
        await per_line([w for w in waiting if w.result.status == "ok"], lambda w: roll_back(w, why, self.opts))

    def write_pending(self, report: Report) -> str | None:
        """While devices hold uncommitted values (a soak, a confirmation wait), the run's report so far lies in
        STATE/pending/RUN.json: ``deployer status`` points a rollback at it should this process die."""
        opts = self.opts
        if opts.run_id is None:
            return None
        path = pending_path(opts.state_dir, opts.run_id)
        try:
            write_json(report.to_json(), path)
        except (UsageError, OSError) as e:  # a full disk never stops a window: its journal lines name the snapshots
            for d in report.devices:
                if d.snapshot is not None:
                    d.unrecorded.append(f"the pending report {path} could not be written: {e}")
            return None
        return path

    def close(self) -> None:
        """The run ended (or was interrupted and rolled back): every lock a window still keeps goes (a device
        whose profile has no commit step), and so do its pending report and its reserved disk space."""
        for held in self.locks.values():
            for h in reversed(held):
                h.release()
            held.clear()
        opts = self.opts
        if opts.run_id is not None and self.held:
            with contextlib.suppress(OSError):  # gone already, or a folder that refuses it (status names the run)
                os.remove(pending_path(opts.state_dir, opts.run_id))
            unreserve(opts)
