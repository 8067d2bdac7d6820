"""Waiting for ``deployer confirm`` (apply --confirm-within), and the runs ``status`` shows waiting or soaking."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from ..errors import NotCommitted, StateError, UsageError
from ..execute.session import ApplyOptions
from ..report import DeviceResult
from ..state import durable, holder, journal
from .held import pending_path
from .held import record as _journal


async def await_confirmation(
    run: str,
    seconds: float,
    options: ApplyOptions,
    *,
    on_wait: Callable[[float], None] | None = None,
    poll: float = 0.2,
    results: Sequence[DeviceResult] = (),
    gone: asyncio.Event | None = None,
) -> bool:
    """Wait until ``deployer confirm`` wrote a ``confirmed`` line for ``run`` (True) or ``seconds`` ran out.

    The wait runs on the monotonic clock (a step of the wall clock changes nothing); the journal's
    ``confirm-awaited`` line has the deadline on both. ``on_wait`` gets the deadline (time.time()) once that
    line is on disk; ``results``: the devices waiting (they say what the journal could not record). ``gone``: the
    wait ends (False) once it is set (every device waiting was rolled back: nothing is left to confirm).
    """
    # a wait may last minutes: the run's snapshot files fsync'ed and their write-ahead log closed first (nothing
    # of the run stays open for writing in the state folder while nobody writes there)
    await durable.settled()
    path = journal.path_of(options.state_dir)
    until = journal.deadline(seconds)
    deadline = until["deadline_monotonic"]
    _journal(
        options,
        {
            "event": "confirm-awaited",
            "run": run,
            "time": journal._now(),
            "pid": os.getpid(),
            "pid_start": holder.process_start(os.getpid()),
            **until,
            "report": pending_path(options.state_dir, run),
        },
        *results,
    )
    offset = _size(path)
    if on_wait is not None:
        on_wait(until["deadline_epoch"])
    while True:
        offset, got = _confirmed_since(path, offset, run)
        if got:
            return True
        left = deadline - time.monotonic()
        if left <= 0:
            _journal(options, {"event": "confirm-expired", "run": run, "time": journal._now()}, *results)
            return False
        if gone is not None and gone.is_set():
            _journal(
                options,
                {
                    "event": "confirm-interrupted",
                    "run": run,
                    "time": journal._now(),
                    "reason": "every device waiting failed its health checks and was rolled back",
                },
                *results,
            )
            return False
        try:
            await asyncio.sleep(min(poll, left))
        except asyncio.CancelledError:
            _journal(options, {"event": "confirm-interrupted", "run": run, "time": journal._now()}, *results)
            raise


def _size(path: str) -> int:
    try:
        return os.path.getsize(path)
    except OSError:  # the journal could not be written (a full disk): a confirmation appends it
        return 0


def _confirmed_since(path: str, offset: int, run: str) -> tuple[int, bool]:
    """Read the journal's new complete lines from ``offset``: is one of them ``confirmed`` for ``run``?"""
    try:
        with open(path, "rb") as f:
            f.seek(offset)
            data = f.read()
    except OSError:
        return offset, False
    end = data.rfind(b"\n") + 1  # a line being appended right now is read next time, whole
    for line in data[:end].splitlines():
        with contextlib.suppress(ValueError):
            rec = json.loads(line)
            if isinstance(rec, dict) and rec.get("event") == "confirmed" and rec.get("run") == run:
                return offset + end, True
    return offset + end, False


@dataclass
class Awaiting:
    """A run that asked for confirmation and has no answer yet (from the journal)."""

    run: str
    pid: int | None
    deadline: str
    deadline_epoch: float
    report: str
    recipe: str | None = None
    pid_start: float | None = None  # the waiting process's start (holder.process_start): a reused PID is not it
    deadline_monotonic: float | None = None  # what the waiting process goes by (this boot only)
    boot_id: str | None = None

    @property
    def alive(self) -> bool:
        """The waiting process is still there (the same process: its PID and its start time)."""
        return self.pid is not None and holder.process_alive(self.pid, self.pid_start)

    def left(self) -> float:
        """Seconds until the waiting run gives up, as that run counts them (its monotonic clock, when this is the
        boot it was written in; else the wall clock)."""
        if self.deadline_monotonic is not None and self.boot_id is not None and self.boot_id == holder.boot_id():
            return self.deadline_monotonic - time.monotonic()
        return self.deadline_epoch - time.time()

    def until(self) -> str:
        """The deadline as this machine's wall clock reads now (a step since the run started is taken out)."""
        return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(time.time() + self.left()))


def _number(value: object) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def awaiting(state_dir: str) -> list[Awaiting]:
    """Runs whose ``confirm-awaited`` line has no answer (``confirmed``, ``confirm-expired``,
    ``confirm-interrupted``) or ``run-finished`` after it."""
    out: dict[str, Awaiting] = {}
    recipes: dict[str, str | None] = {}
    for rec in journal.read(state_dir):
        if rec is None or not rec.get("run"):
            continue
        run, event = str(rec["run"]), rec.get("event")
        if event == "run-started":
            recipes[run] = rec.get("recipe")
        elif event == "confirm-awaited":
            pid = rec.get("pid")
            out[run] = Awaiting(
                run,
                pid if isinstance(pid, int) else None,
                str(rec.get("deadline", "")),
                _number(rec.get("deadline_epoch")) or 0.0,
                str(rec.get("report", "")),
                recipes.get(run),
                _number(rec.get("pid_start")),
                _number(rec.get("deadline_monotonic")),
                str(rec["boot_id"]) if rec.get("boot_id") else None,
            )
        elif event in ("confirmed", "confirm-expired", "confirm-interrupted", "run-finished"):
            out.pop(run, None)
    return list(out.values())


def soaking(state_dir: str) -> dict[str, str | None]:
    """Runs whose last ``soak-started`` line has no ``soak-finished`` or ``run-finished`` after it: run -> the
    report of the run so far (None from a run without one)."""
    out: dict[str, str | None] = {}
    for rec in journal.read(state_dir):
        if rec is None or not rec.get("run"):
            continue
        run, event = str(rec["run"]), rec.get("event")
        if event == "soak-started":
            out[run] = rec.get("report")
        elif event in ("soak-finished", "run-finished"):
            out.pop(run, None)
    return out


def confirm_run(state_dir: str, run: str | None = None) -> Awaiting:
    """``deployer confirm [RUN]``: write the ``confirmed`` line the waiting run looks for (UsageError if none)."""
    waiting = awaiting(state_dir)
    where = journal.path_of(state_dir)
    if run is not None:
        match = [a for a in waiting if a.run == run]
        if not match:
            raise UsageError(
                f"run {run} does not wait for a confirmation in {where}"
                + (f" (waiting: {', '.join(a.run for a in waiting)})" if waiting else "")
            )
        target = match[0]
    elif not waiting:
        soaks = soaking(state_dir)
        soaking_now = sorted(r.run for r in journal.unfinished(state_dir)[0] if r.run in soaks and r.running)
        if soaking_now:
            raise UsageError(
                f"run {', '.join(soaking_now)} is still soaking: it asks for the confirmation once its "
                "soak passed (deployer status shows it)"
            )
        raise UsageError(f"no run waits for a confirmation in {where} (wrong --state-dir?)")
    elif len(waiting) > 1:
        raise UsageError(
            "several runs wait for a confirmation: name one (deployer confirm RUN): "
            + ", ".join(f"{a.run} ({a.recipe or '?'}, until {a.until()})" for a in waiting)
        )
    else:
        target = waiting[0]
    if not target.alive:
        raise UsageError(
            f"run {target.run} waited for a confirmation, but its process (PID {target.pid}) is gone: "
            "nothing can send its commit. Its devices hold uncommitted values; restore them with: "
            f"deployer rollback --from-report {target.report} --state-dir {state_dir} --yes"
        )
    if target.left() <= 0:
        raise UsageError(
            f"run {target.run}: the confirmation time ran out at {target.until()}; "
            "it is rolling back (see deployer status)"
        )
    options = ApplyOptions(state_dir=state_dir, run_id=target.run)  # on a full disk, the run's reserve takes it
    if not _journal(
        options,
        {
            "event": "confirmed",
            "run": target.run,
            "time": journal._now(),
            "user": journal.user_name(),
            "pid": os.getpid(),
        },
    ):
        raise StateError(
            f"cannot write the journal {where}: the confirmation was not recorded, so run {target.run} "
            f"does not see it (disk full?); it rolls back at {target.until()} unless confirmed"
        )
    return target


def outcome(state_dir: str, target: Awaiting, *, poll: float = 0.1) -> dict[str, Any]:
    """Wait for what the confirmed run did: its ``confirm-outcome`` line (committed, not committed with why).

    Raises NotCommitted when the commit was not sent to every device (a parameter changed during the window,
    a step failed, the time ran out first) or the run's process ended without saying."""
    while True:
        for rec in journal.read(state_dir, containing=target.run):
            if (
                rec is not None
                and rec.get("run") == target.run
                and rec.get("event") in ("confirm-outcome", "run-finished")
            ):
                return _said(target, rec)
        if not target.alive:
            raise NotCommitted(
                f"run {target.run} ended without saying whether it sent its commit (see deployer status)"
            )
        time.sleep(poll)


def _said(target: Awaiting, rec: dict[str, Any]) -> dict[str, Any]:
    if rec.get("event") == "run-finished":  # an older run, or one that could not write its outcome line
        bad = [d for d in rec.get("devices") or [] if isinstance(d, dict) and d.get("status") not in ("ok", "sent")]
        if bad:
            raise NotCommitted(
                f"run {target.run}: the commit was not sent to "
                + ", ".join(f"{d.get('name')} ({d.get('status')})" for d in bad)
            )
        return rec
    failed = rec.get("not_committed") or {}
    if isinstance(failed, dict) and failed:
        raise NotCommitted(
            f"run {target.run}: the commit was not sent to "
            + "; ".join(f"{name}: {why}" for name, why in failed.items())
        )
    return rec
