"""What the agent holds: its settings, its devices and their locks, the files and the state it adopted from them,
its store, and its events. The parts (``watch``, ``runs``, ``commands``, ``ledger``) work on it; ``core.Agent``
is this with its parts wired, started and stopped.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from ..errors import InputError, Locked, StateError
from ..execute.job import Job
from ..state import journal, lock
from . import desired as ds
from .audit_events import trailed
from .firstrestores import FirstRestores
from .model import ApiError, Device, RunState, Settings
from .store import Store, boot_id

if TYPE_CHECKING:
    from ..api import Report


class Site:
    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.state_dir = os.path.abspath(settings.state_dir)
        self.folder = os.path.join(self.state_dir, "agent")
        self.devices: dict[str, Device] = {}
        self.url = ""
        self.started = time.time()
        self.boot = boot_id()
        self.store: Store | None = None
        self.files: ds.Files | None = None
        self.files_problem: list[str] = []
        self._folder_lock: int | None = None
        self.on_event: list[Callable[[dict[str, Any]], None]] = []  # the outward side's notifications hook here
        self.first = FirstRestores(settings.first_restore_soak)  # the first restores after the start, staged

    def open(self) -> None:
        """Read the files (InputError: the agent does not start) and open the state folder; nothing is sent."""
        self.files = ds.load_files(self.settings.inventory)
        os.makedirs(self.folder, exist_ok=True)
        from ..portable import O_BINARY, O_CLOEXEC
        from ..state import oslock  # flock, or LockFileEx on Windows

        fd = os.open(os.path.join(self.folder, "agent.lock"), os.O_RDWR | os.O_CREAT | O_CLOEXEC | O_BINARY, 0o644)
        try:
            got = oslock.backend().try_lock(fd)
        except OSError:
            got = False
        if not got:
            os.close(fd)
            raise StateError(
                f"another agent runs on the state folder {self.state_dir} "
                f"({os.path.join(self.folder, 'agent.lock')} is locked)"
            ) from None
        self._folder_lock = fd
        self.store = Store(os.path.join(self.folder, "agent.sqlite3"))
        self.store.prune_events(self.settings.keep_events)

    def close(self) -> None:
        """Let go of the devices, the store and the state folder."""
        for dev in self.devices.values():
            lock.let_go([h.key for h in dev.locks])
            dev.locks = []
        lock.set_agent(None)
        if self.store is not None:
            self.event("stopped", "agent stopped")
            self.store.close()
            self.store = None
        if self._folder_lock is not None:
            os.close(self._folder_lock)
            self._folder_lock = None

    # ---- the devices ------------------------------------------------------------------------------

    def own(self) -> None:
        """Each device of the files: its settings, its counters, its adopted state (the files' when none, or when
        the one adopted no longer loads), its locks. Devices no longer listed are forgotten."""
        assert self.files is not None and self.store is not None
        adopted = self.store.adopted()
        counts = {
            (d, k): n
            for d, k, n in self.store.db.execute(
                "SELECT device, kind, count(*) FROM events WHERE device IS NOT NULL GROUP BY device, kind"
            )
        }
        for name, job in self.files.jobs.items():
            dev = self.devices[name] = Device(name, job)
            self._configure(dev)
            dev.drift_events, dev.drift_restores, dev.replaced_total = (
                counts.get((name, k), 0) for k in ("drift", "restored", "replaced")
            )
            dev.writes = sum(w + c for w, c in self.store.ledger(name).get(name, {}).values())
            row = adopted.get(name)
            try:
                if row is not None and os.path.exists(row[0]):
                    dev.adopted = ds.load_adopted(row[0])
            except InputError as e:  # an adopted file that no longer loads (its profile changed): say so
                self.event(
                    "adopt-failed",
                    f"{name}: the adopted state {row[0] if row else ''} no longer loads: "
                    f"{'; '.join(map(str, e.diagnostics))}; adopting the files",
                    device=name,
                )
            if dev.adopted is None:
                self.adopt(dev, job, ds.values_of(job.recipe), run=None, why="the files at the agent's start")
            else:
                dev.adopted_values = ds.values_of(dev.adopted)
            self.take(dev)
        gone = set(adopted) - set(self.files.jobs)
        if gone:
            self.store.forget(gone)
            self.event("reload", f"no longer in the inventory, not owned: {', '.join(sorted(gone))}")
        self.pending()

    def _configure(self, dev: Device) -> None:
        """The device's watch settings: the inventory's ``agent:`` for it, else the command line's."""
        s = self.settings
        own: Mapping[str, Any] = {}
        if self.files is not None:
            found = [d for d in self.files.inventory.devices if d.name == dev.name]
            own = found[0].agent if found else {}
        dev.check_every = float(own.get("check_every", s.check_every))
        dev.on_drift = str(own.get("on_drift", s.on_drift))
        dev.on_replace = str(own.get("on_replace", s.on_replace))

    def take(self, dev: Device) -> None:
        """Take the device's locks (bus shared, unit exclusive) and keep them; or say who holds them."""
        if dev.owned:
            return
        try:
            dev.locks = _take_now(dev.job.url.lock_keys, dev.job.unit)
        except Locked as e:
            if dev.not_owned_why != str(e):
                self.event("not-owned", f"{dev.name}: not owned yet: {e}", device=dev.name)
            dev.not_owned_why, dev.status = str(e), "not-owned"
            return
        lock.hold(dev.locks)
        dev.owned, dev.not_owned_why = True, None
        if dev.status == "not-owned":
            dev.status = "unknown"
            self.event("owned", f"{dev.name}: owned now", device=dev.name)

    # ---- events -----------------------------------------------------------------------------------

    def event(
        self, kind: str, message: str, *, device: str | None = None, detail: Mapping[str, Any] | None = None
    ) -> dict[str, Any]:
        """An event: in the database (committed before anyone is told), the journal, stderr, the hooks."""
        assert self.store is not None
        ev = self.store.event(kind, message, device=device, detail=detail)
        with contextlib.suppress(OSError):
            journal.append(
                self.state_dir,
                {
                    "event": f"agent-{kind}",
                    "time": journal._now(),
                    "device": device,
                    "message": message,
                    "pid": os.getpid(),
                },
            )
        print(f"agent: {kind}: {message}", file=sys.stderr, flush=True)
        for hook in self.on_event:
            with contextlib.suppress(Exception):
                hook(ev)
        trailed(self, kind, message, device, detail)  # what changes (or could change) a device: on the trail
        return ev

    # ---- adoption and the files ---------------------------------------------------------------------

    def adopt(self, dev: Device, job: Job, values: Mapping[str, Sequence[int]], *, run: str | None, why: str) -> None:
        assert self.store is not None
        path, sha = ds.write_adopted(self.state_dir, job, values, why=why)
        dev.adopted = ds.load_adopted(path)
        dev.adopted_values = ds.values_of(dev.adopted)
        self.store.adopt(dev.name, path, sha, run)

    def run_ended(self, run: RunState, report: Report, by_name: Mapping[str, Job], *, adopt: bool) -> None:
        """Each device that ended ok: what it holds adopted (an apply, a rollback), its as-left values kept."""
        store = self.store
        assert store is not None
        for r in report.devices:
            dev = self.devices[r.name]
            if r.status == "ok" and r.commit in (None, "sent"):
                after = {p.name: tuple(p.after_raw) for p in r.parameters if p.after_raw is not None}
                if adopt:
                    self.adopt(
                        dev, by_name[r.name], ds.values_of(by_name[r.name].recipe), run=run.id, why=f"run {run.id}"
                    )
                elif run.command == "rollback":  # what was restored is the state to keep, not what was undone
                    back = {n: v for n, v in ds.values_of(by_name[r.name].recipe).items() if n in dev.adopted_values}
                    self.adopt(dev, dev.job, {**dev.adopted_values, **back}, run=run.id, why=f"rollback run {run.id}")
                dev.asleft = {n: v for n, v in after.items() if n in dev.adopted_values}
                store.set_asleft(r.name, dev.asleft, f"run {run.id}")
                if run.command == "restore":
                    dev.drift_restores += 1
                    dev.drift, dev.status, dev.replaced = [], "ok", None
                    self.event(
                        "restored",
                        f"{r.name}: restored ({run.options.get('reason')}) by run {run.id}",
                        device=r.name,
                        detail={"run": run.id},
                    )
            elif run.command == "restore":
                self.event(
                    "restore-failed",
                    f"{r.name}: the restore run {run.id} ended {r.status}: {r.error}",
                    device=r.name,
                    detail={"run": run.id},
                )
        self.pending()

    def pending(self) -> None:
        """Per device: the files' values that are not the adopted ones."""
        if self.files is None:
            return
        for name, dev in self.devices.items():
            job = self.files.jobs.get(name)
            dev.pending = [] if job is None else ds.differences(job.recipe.profile, dev.adopted_values, job.recipe)

    def reload(self) -> None:
        """Read the files again; an invalid edit changes nothing (ApiError with the diagnostics, and an event)."""
        try:
            files = ds.load_files(self.settings.inventory)
        except InputError as e:
            diags = [str(d) for d in e.diagnostics]
            self.files_problem = diags
            self.event(
                "reload-failed",
                f"the files are invalid; nothing changed: {len(diags)} error(s)",
                detail={"diagnostics": diags},
            )
            raise ApiError("input", "the files are invalid; nothing changed", status=400, diagnostics=diags) from None
        old = self.files
        self.files, self.files_problem = files, []
        for name, job in files.jobs.items():
            dev = self.devices.get(name)
            if dev is not None:
                dev.job = replace(job)
                self._configure(dev)
        self.pending()
        if old is None or old.sha256 != files.sha256:
            added = sorted(set(files.jobs) - set(self.devices))
            removed = sorted(set(self.devices) - set(files.jobs))
            extra = (f"; new devices ({', '.join(added)}) are owned from the agent's next start" if added else "") + (
                f"; devices no longer listed ({', '.join(removed)}) stay owned until then" if removed else ""
            )
            n = sum(1 for d in self.devices.values() if d.pending)
            self.event(
                "reload",
                f"files read: {n} device(s) with pending changes{extra}",
                detail={"files_sha256": files.sha256},
            )


def _take_now(addresses: Sequence[str], unit: int) -> list[lock.DeviceLock]:
    """The device's locks (its URL's ``lock_keys``) without waiting (the agent's start and each check try again),
    and its marks where every process looks whatever its lock folder (``lock.agent_marks``)."""
    keys = sorted(set(addresses))
    held: list[lock.DeviceLock] = []
    try:
        for b in keys:
            held.append(lock.try_lock(f"{b}#bus", command="deployer agent", shared=True))
        for b in keys:
            held.append(lock.try_lock(lock.device_key(b, unit), command="deployer agent"))
        held += lock.agent_marks(keys, unit)
    except BaseException:
        for h in reversed(held):
            h.release()
        raise
    return held
