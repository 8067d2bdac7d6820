"""Waiting for ``deployer confirm`` (apply --confirm-within), and the runs ``status`` shows waiting or soaking."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass

from ..execute.session import ApplyOptions
from ..load.diagnostics import UsageError
from ..state import journal
from .held import pending_path
from .held import record as _journal


async def await_confirmation(run: str, seconds: float, options: ApplyOptions, *,
                             on_wait: Callable[[float], None] | None = None,
                             poll: float = 0.2) -> bool:
    """Wait until ``deployer confirm`` wrote a ``confirmed`` line for ``run`` (True) or ``seconds`` ran out.

    ``on_wait`` gets the deadline (time.time()) once the ``confirm-awaited`` line is on disk.
    """
    path = journal.path_of(options.state_dir)
    deadline = time.time() + seconds
    _journal(options, {"event": "confirm-awaited", "run": run, "time": journal._now(), "pid": os.getpid(),
                       "deadline": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(deadline)),
                       "deadline_epoch": deadline, "report": pending_path(options.state_dir, run)})
    offset = os.path.getsize(path)
    if on_wait is not None:
        on_wait(deadline)
    while True:
        offset, got = _confirmed_since(path, offset, run)
        if got:
            return True
        left = deadline - time.time()
        if left <= 0:
            _journal(options, {"event": "confirm-expired", "run": run, "time": journal._now()})
            return False
        try:
            await asyncio.sleep(min(poll, left))
        except asyncio.CancelledError:
            _journal(options, {"event": "confirm-interrupted", "run": run, "time": journal._now()})
            raise


def _confirmed_since(path: str, offset: int, run: str) -> tuple[int, bool]:
    """Read the journal's new complete lines from ``offset``: is one of them ``confirmed`` for ``run``?"""
    with open(path, "rb") as f:
        f.seek(offset)
        data = f.read()
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

    @property
    def alive(self) -> bool:
        from ..portable import pid_alive  # never os.kill(pid, 0): on Windows it ends the process

        return self.pid is not None and pid_alive(self.pid)


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
            out[run] = Awaiting(run, rec.get("pid"), str(rec.get("deadline", "")),
                                float(rec.get("deadline_epoch", 0)), str(rec.get("report", "")), recipes.get(run))
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
            raise UsageError(f"run {run} does not wait for a confirmation in {where}"
                             + (f" (waiting: {', '.join(a.run for a in waiting)})" if waiting else ""))
        target = match[0]
    elif not waiting:
        soaks = soaking(state_dir)
        soaking_now = sorted(r.run for r in journal.unfinished(state_dir)[0] if r.run in soaks and r.running)
        if soaking_now:
            raise UsageError(f"run {', '.join(soaking_now)} is still soaking: it asks for the confirmation once its "
                             "soak passed (deployer status shows it)")
        raise UsageError(f"no run waits for a confirmation in {where} (wrong --state-dir?)")
    elif len(waiting) > 1:
        raise UsageError("several runs wait for a confirmation: name one (deployer confirm RUN): "
                         + ", ".join(f"{a.run} ({a.recipe or '?'}, until {a.deadline})" for a in waiting))
    else:
        target = waiting[0]
    if not target.alive:
        raise UsageError(f"run {target.run} waited for a confirmation, but its process (PID {target.pid}) is gone: "
                         "nothing can send its commit. Its devices hold uncommitted values; restore them with: "
                         f"deployer rollback --report {target.report} --state-dir {state_dir}")
    if time.time() > target.deadline_epoch:
        raise UsageError(f"run {target.run}: the confirmation time ran out at {target.deadline}; "
                         "it is rolling back (see deployer status)")
    _journal(ApplyOptions(state_dir=state_dir), {"event": "confirmed", "run": target.run, "time": journal._now(),
                                                  "user": journal.user_name(), "pid": os.getpid()})
    return target

