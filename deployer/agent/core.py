"""The agent itself: its devices, the watch, runs and windows (docs/agent.md). No HTTP here: ``server`` is
one client of this class (the handlers call its methods), so the outward side can grow without touching it.

Everything runs on one event loop; the database is written from that loop only.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from decimal import Decimal
from typing import Any

from ..errors import (
    DeployerError,
    DeviceGone,
    ExceptionResponse,
    InputError,
    Locked,
    RunInterrupted,
    StateError,
    TransportError,
    Unreachable,
    UsageError,
)
from ..execute.connect import connected
from ..execute.executor import check_identity
from ..execute.job import Job
from ..execute.session import ApplyOptions, Session
from ..execute.verify import values_of as _values_of
from ..load.durations import format_duration, parse_duration
from ..planning.model import Target
from ..planning.planfile import plan_to_json
from ..planning.planner import plan_reads
from ..planning.steps import make_plan, pacing_for
from ..profile import Profile
from ..recipe.loader import Recipe
from ..report import DeviceResult, Report
from ..state import journal, lock
from ..transport import clients as tp
from ..transport.urls import describe
from . import desired as ds
from .firstrestores import FirstRestores
from .store import Store, boot_id

API_VERSION = 1
WRITES = (5, 6, 15, 16)
STATUSES = ("ok", "drifted", "unreachable", "replaced", "running", "not-owned", "unknown")


class ApiError(DeployerError):
    """A request the agent refuses: ``kind`` and HTTP ``status`` for the answer, ``exit_code`` for the CLI."""

    def __init__(self, kind: str, message: str, *, status: int, exit_code: int = 1,
                 diagnostics: Sequence[str] = ()) -> None:
        super().__init__(message)
        self.kind, self.status, self.diagnostics = kind, status, list(diagnostics)
        object.__setattr__(self, "exit_code", exit_code)  # per refusal: what the command line would exit with


@dataclass
class Settings:
    inventory: str
    state_dir: str = ".deployer"
    check_every: float = 300.0
    on_drift: str = "report"
    on_replace: str = "report"
    bus_share: float = 0.2  # at most this share of a bus's time goes to watching
    max_restores: int = 3  # per device and hour; a device that keeps drifting back is reported, not fought
    first_restore_soak: float = 10.0  # the first restores after a start: the canary batch's soak (firstrestores)
    endurance_warn: float = 0.8
    keep_events: float = 90 * 86400.0
    parallel: int = 64  # buses read at once by the watch


@dataclass
class Device:
    name: str
    job: Job  # the files' job (URL, unit, the files' recipe)
    adopted: Recipe | None = None
    adopted_values: dict[str, tuple[int, ...]] = field(default_factory=dict)
    owned: bool = False
    locks: list[lock.DeviceLock] = field(default_factory=list)
    not_owned_why: str | None = None
    status: str = "unknown"
    drift: list[dict[str, Any]] = field(default_factory=list)
    last_values: dict[str, tuple[int, ...]] | None = None
    asleft: dict[str, tuple[int, ...]] | None = None  # as stored in the database
    last_check: float | None = None
    unreachable_since: float | None = None
    unreachable_why: str | None = None
    run: str | None = None  # the agent's run that has it now
    checking: bool = False  # being read now (the watch and a client's check never read it twice at once)
    restores: deque[float] = field(default_factory=deque)
    replaced: str | None = None
    pending: list[dict[str, Any]] = field(default_factory=list)
    # the inventory's agent settings for it (defaults < groups < its own), over the command line's
    check_every: float = 300.0
    on_drift: str = "report"
    on_replace: str = "report"
    # counters for /metrics (loaded from the database at start, so they survive restarts)
    drift_events: int = 0
    drift_restores: int = 0
    replaced_total: int = 0
    writes: int = 0


@dataclass
class RunState:
    id: str
    command: str
    devices: list[str]
    options: dict[str, Any]
    started: float = field(default_factory=time.time)
    state: str = "running"  # running, waiting, finished, refused, interrupted
    events: list[dict[str, Any]] = field(default_factory=list)
    changed: asyncio.Event = field(default_factory=asyncio.Event)
    task: asyncio.Task[None] | None = None
    report: dict[str, Any] | None = None
    exit_code: int | None = None
    window: dict[str, Any] | None = None
    finished: float | None = None
    results: dict[str, DeviceResult] = field(default_factory=dict)

    def emit(self, event: str, **data: Any) -> None:
        self.events.append({"n": len(self.events), "event": event, "time": journal._now(), **data})
        self.changed.set()
        self.changed = asyncio.Event()

    def to_json(self, *, report: bool = True) -> dict[str, Any]:
        out: dict[str, Any] = {"id": self.id, "command": self.command, "state": self.state, "devices": self.devices,
                               "options": self.options, "started": _iso(self.started),
                               "finished": None if self.finished is None else _iso(self.finished),
                               "exit_code": self.exit_code, "window": self.window}
        if report:
            out["report"] = self.report
        return out


class Agent:
    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.state_dir = os.path.abspath(settings.state_dir)
        self.folder = os.path.join(self.state_dir, "agent")
        self.devices: dict[str, Device] = {}
        self.runs: dict[str, RunState] = {}
        self.url = ""
        self.started = time.time()
        self.boot = boot_id()
        self.store: Store | None = None
        self.files: ds.Files | None = None
        self.files_problem: list[str] = []
        self._tasks: set[asyncio.Task[Any]] = set()
        self._watch: asyncio.Task[None] | None = None
        self._wake = asyncio.Event()
        self._buses: dict[str, asyncio.Lock] = {}  # the watch reads one device of a bus at a time ...
        self._bus_free: dict[str, float] = {}  # ... and not before this monotonic time (the bus share)
        self._folder_lock: int | None = None
        self.checks = 0
        self.check_seconds = 0.0
        self.on_event: list[Callable[[dict[str, Any]], None]] = []  # the outward side's notifications hook here
        self.first = FirstRestores(settings.first_restore_soak)  # the first restores after the start, staged

    # ---- start and stop -------------------------------------------------------------------------

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
            raise StateError(f"another agent runs on the state folder {self.state_dir} "
                             f"({os.path.join(self.folder, 'agent.lock')} is locked)") from None
        self._folder_lock = fd
        self.store = Store(os.path.join(self.folder, "agent.sqlite3"))
        self.store.prune_events(self.settings.keep_events)

    async def start(self, url: str) -> None:
        """Own the devices (locks with our address), adopt what is new, resume or expire windows, watch."""
        assert self.files is not None and self.store is not None
        self.url = url
        from ..portable import raise_open_files

        # it holds two lock files per device address for as long as it runs, plus a socket per bus being read
        need = sum(2 * len(j.url.lock_keys) for j in self.files.jobs.values()) + self.settings.parallel + 128
        hard = raise_open_files(need)
        if hard is not None:
            raise StateError(f"the agent needs about {need} open files for {len(self.files.jobs)} devices, but this "
                             f"system allows {hard} (ulimit -Hn; LimitNOFILE= in its systemd unit)")
        lock.set_agent(url)
        adopted = self.store.adopted()
        counts = self._counts()
        for name, job in self.files.jobs.items():
            dev = self.devices[name] = Device(name, job)
            self._configure(dev)
            dev.drift_events, dev.drift_restores, dev.replaced_total = (counts.get((name, k), 0) for k in
                                                                       ("drift", "restored", "replaced"))
            dev.writes = sum(w + c for w, c in self.store.ledger(name).get(name, {}).values())
            row = adopted.get(name)
            try:
                if row is not None and os.path.exists(row[0]):
                    dev.adopted = ds.load_adopted(row[0])
            except InputError as e:  # an adopted file that no longer loads (its profile changed): say so
                self.event("adopt-failed", f"{name}: the adopted state {row[0] if row else ''} no longer loads: "
                           f"{'; '.join(map(str, e.diagnostics))}; adopting the files", device=name)
            if dev.adopted is None:
                self._adopt(dev, job, ds.values_of(job.recipe), run=None, why="the files at the agent's start")
            else:
                dev.adopted_values = ds.values_of(dev.adopted)
            self._take(dev)
        gone = set(adopted) - set(self.files.jobs)
        if gone:
            self.store.forget(gone)
            self.event("reload", f"no longer in the inventory, not owned: {', '.join(sorted(gone))}")
        self._pending()
        self.event("started", f"agent started at {url}: {len(self.devices)} devices, check every "
                   f"{format_duration(self.settings.check_every)}, on drift {self.settings.on_drift}, "
                   f"on replace {self.settings.on_replace}", detail={"pid": os.getpid(), "boot_id": self.boot})
        await self._recover_windows()
        self._watch = asyncio.ensure_future(self._watch_forever())

    async def stop(self) -> None:
        """SIGTERM: stop watching, end the runs safely (their soaks and windows roll back, as on Ctrl-C), let go."""
        if self._watch is not None:
            self._watch.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watch
        running = [r.task for r in self.runs.values() if r.task is not None and not r.task.done()]
        for t in [*running, *self._tasks]:
            t.cancel()
        await asyncio.gather(*running, *self._tasks, return_exceptions=True)
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

    def _counts(self) -> dict[tuple[str, str], int]:
        assert self.store is not None
        return {(d, k): n for d, k, n in self.store.db.execute(
            "SELECT device, kind, count(*) FROM events WHERE device IS NOT NULL GROUP BY device, kind")}

    # ---- events -----------------------------------------------------------------------------------

    def event(self, kind: str, message: str, *, device: str | None = None,
              detail: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """An event: in the database (committed before anyone is told), the journal, stderr, the hooks."""
        assert self.store is not None
        ev = self.store.event(kind, message, device=device, detail=detail)
        with contextlib.suppress(OSError):
            journal.append(self.state_dir, {"event": f"agent-{kind}", "time": journal._now(), "device": device,
                                            "message": message, "pid": os.getpid()})
        import sys

        print(f"agent: {kind}: {message}", file=sys.stderr, flush=True)
        for hook in self.on_event:
            with contextlib.suppress(Exception):
                hook(ev)
        from .audit_events import trailed

        trailed(self, kind, message, device, detail)  # what changes (or could change) a device: on the trail
        return ev

    # ---- ownership ----------------------------------------------------------------------------------

    def _take(self, dev: Device) -> None:
        """Take the device's locks (bus shared, unit exclusive) and keep them; or say who holds them."""
        if dev.owned:
            return
        url = dev.job.url
        try:
            dev.locks = _take_now(url, dev.job.unit)
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

    # ---- adoption and the files ---------------------------------------------------------------------

    def _adopt(self, dev: Device, job: Job, values: Mapping[str, Sequence[int]], *, run: str | None,
               why: str) -> None:
        assert self.store is not None
        path, sha = ds.write_adopted(self.state_dir, job, values, why=why)
        dev.adopted = ds.load_adopted(path)
        dev.adopted_values = ds.values_of(dev.adopted)
        self.store.adopt(dev.name, path, sha, run)

    def _pending(self) -> None:
        """Per device: the files' values that are not the adopted ones."""
        if self.files is None:
            return
        for name, dev in self.devices.items():
            job = self.files.jobs.get(name)
            dev.pending = [] if job is None else ds.differences(job.recipe.profile, dev.adopted_values, job.recipe)

    def reload(self) -> dict[str, Any]:
        """Read the files again; an invalid edit changes nothing (ApiError with the diagnostics, and an event)."""
        try:
            files = ds.load_files(self.settings.inventory)
        except InputError as e:
            diags = [str(d) for d in e.diagnostics]
            self.files_problem = diags
            self.event("reload-failed", f"the files are invalid; nothing changed: {len(diags)} error(s)",
                       detail={"diagnostics": diags})
            raise ApiError("input", "the files are invalid; nothing changed", status=400, diagnostics=diags) from None
        old = self.files
        self.files, self.files_problem = files, []
        for name, job in files.jobs.items():
            dev = self.devices.get(name)
            if dev is not None:
                dev.job = replace(job)
                self._configure(dev)
        self._pending()
        if old is None or old.sha256 != files.sha256:
            added = sorted(set(files.jobs) - set(self.devices))
            removed = sorted(set(self.devices) - set(files.jobs))
            extra = (f"; new devices ({', '.join(added)}) are owned from the agent's next start" if added else "") + \
                    (f"; devices no longer listed ({', '.join(removed)}) stay owned until then" if removed else "")
            n = sum(1 for d in self.devices.values() if d.pending)
            self.event("reload", f"files read: {n} device(s) with pending changes{extra}",
                       detail={"files_sha256": files.sha256})
        return self.pending_json()

    def pending_json(self) -> dict[str, Any]:
        out = []
        for dev in self.devices.values():
            if not dev.pending:
                continue
            job = self.files.jobs.get(dev.name) if self.files else None
            plan = None
            if job is not None and dev.last_values is not None:
                plan = plan_to_json(make_plan(job.recipe, Target(describe(job.url), job.unit,
                                                                 job.recipe.profile_ref or job.recipe.profile.id),
                                              dev.last_values, pacing=pacing_for(job.url, job.recipe.profile)))
            out.append({"name": dev.name, "changes": dev.pending, "plan": plan})
        return {"files_sha256": self.files.sha256 if self.files else None, "devices": out,
                "problems": self.files_problem}

    # ---- the watch ------------------------------------------------------------------------------------

    async def _watch_forever(self) -> None:
        while True:
            started = time.monotonic()
            try:
                await self.check(due_only=True)
            except Exception as e:  # the watch must go on; say what broke it this round
                self.event("internal", f"the check failed: {type(e).__name__}: {e}")
            if self.first.collecting:  # the first round is over: the restores it asked for, staged
                self.first.start(self)
            # a round as often as the most frequent device asks; each device is read when its own time is due
            every = min([d.check_every for d in self.devices.values()] or [self.settings.check_every])
            left = every - (time.monotonic() - started)
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._wake.wait(), max(0.0, left))
            self._wake.clear()

    async def check(self, names: Sequence[str] | None = None, *, due_only: bool = False) -> None:
        """Read every owned device (devices of one bus one after the other, within the bus share);
        ``due_only``: those whose own interval has passed since their last check."""
        now = time.time()
        todo = [d for d in self.devices.values() if (names is None or d.name in names)
                and not (due_only and d.last_check is not None and now - d.last_check < d.check_every * 0.95)]
        for d in todo:
            if not d.owned:
                self._take(d)
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
        assert self.store is not None and dev.adopted is not None
        prof = dev.adopted.profile
        names = [n for n in dev.adopted_values if prof.parameter(n).readable]
        known = self.store.identity(dev.name)
        ask43 = known is None or known[2] is not False
        try:
            values, objects, answered43 = await _read(prof, names, dev.job.url, dev.job.unit, ask43)
        except _OtherModel as e:
            dev.last_check = time.time()
            if dev.replaced != str(e):
                dev.replaced, dev.status = str(e), "replaced"
                dev.replaced_total += 1
                self.event("replace-refused", f"{dev.name}: another kind of device answers: {e}; nothing written",
                           device=dev.name)
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
            self.store.set_identity(dev.name, objects, regs, answered43 if ask43 else known[2] if known else None)
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
                self.store.set_asleft(dev.name, left, "check")
                dev.asleft = left
            return
        first = not dev.drift
        dev.drift, dev.status = drift, "drifted"
        if first:
            dev.drift_events += 1
            self.event("drift", f"{dev.name}: {', '.join(_said(d) for d in drift)}", device=dev.name,
                       detail={"parameters": drift})
        if dev.on_drift == "restore":
            self._restore(dev, "drift")

    def _replaced(self, dev: Device, known: tuple[dict[str, str] | None, dict[str, int], bool | None] | None,
                  objects: dict[str, str] | None, was_unreachable: bool,
                  values: Mapping[str, tuple[int, ...]]) -> str | None:
        """Why this looks like another unit than the one last seen (None: the same one)."""
        if known is not None and known[0] is not None and objects is not None:
            before, now = known[0], objects
            changed = [k for k in sorted(set(before) | set(now)) if before.get(k) != now.get(k)]
            if changed:
                return "its identity changed: " + ", ".join(f"{k} {before.get(k)!r} -> {now.get(k)!r}" for k in changed)
        if was_unreachable and dev.adopted is not None:
            prof = dev.adopted.profile
            # a unit's own settings (its address ...) are set on a replacement before it answers at all
            compared = [(n, prof.parameter(n).default_registers()) for n in dev.adopted_values
                        if not prof.parameter(n).per_unit]
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
                    self.event("replace-refused", f"{dev.name}: {said}", device=dev.name,
                               detail={"before": known[0], "now": objects})
                dev.status = "replaced"
                return False
        dev.status, dev.replaced = "replaced", why
        dev.replaced_total += 1
        self.event("replaced", f"{dev.name}: replaced: {why}", device=dev.name,
                   detail={"before": None if known is None else known[0], "now": objects})
        if dev.on_replace == "restore":
            self._restore(dev, "replaced")
        return True

    # ---- restores -------------------------------------------------------------------------------------

    def _restore(self, dev: Device, why: str) -> None:
        """Write the adopted state (drift) or the as-left values without per-unit parameters (replaced) back."""
        assert self.store is not None and dev.adopted is not None
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
                self.event("restore-limit", f"{dev.name}: drifted again after {self.settings.max_restores} restores "
                           "within an hour: reported, not fought (restore it through the agent after a look)",
                           device=dev.name)
            return
        dev.restores.append(now)
        recipe = dev.adopted
        if why == "replaced":  # the values it was left with, but never those that belong to the unit
            left = self.store.asleft(dev.name)
            values = dict(left[0]) if left is not None else dict(dev.adopted_values)
            prof = dev.adopted.profile
            values = {n: v for n, v in values.items() if n in dev.adopted_values and not prof.parameter(n).per_unit}
            path = os.path.join(self.folder, "restore", f"{ds._safe(dev.name)}.yaml")
            ds.write_adopted(self.state_dir, replace(dev.job, recipe=dev.adopted), values,
                             why="as left, for a replaced unit (per-unit parameters left out)", path=path)
            recipe = ds.load_adopted(path)
        job = Job(dev.name, recipe, dev.job.url, dev.job.unit)
        if self.first.keep(job, why):  # the first round's restores start together, staged, after that round
            return
        try:
            self.start_run([job], command="restore", options={"reason": why}, opts=ApplyOptions(), label=recipe.path)
        except ApiError as e:
            self.event("restore-failed", f"{dev.name}: {e}", device=dev.name)

    # ---- runs ---------------------------------------------------------------------------------------

    def start_apply(self, req: Mapping[str, Any], *, take_up: bool = True) -> RunState:
        """``POST /v1/runs`` with command apply: roll out the files for the selected devices (every check
        before anything is sent; refusals are ApiError). ``take_up``: the files are read again first, so what
        is rolled out is what they say now, checked (``files_sha256``: refused if they changed since the client
        looked); without it (a user who may not take up an edit) what was taken up last is rolled out.
        ``req["by"]``: who asked (access.Who.record), for the run's records."""
        if take_up:
            with contextlib.suppress(ApiError):
                self.reload()
        if self.files_problem:
            raise ApiError("input", "the files are invalid; nothing was sent", status=400,
                           diagnostics=self.files_problem)
        files = self.files
        assert files is not None
        want = req.get("files_sha256")
        if want and want != files.sha256:
            raise ApiError("conflict", "the files changed since you looked (files_sha256 differs): look again "
                           "(deployer plan --agent) and apply what you saw", status=409)
        try:
            chosen = [d.name for d in files.inventory.select(req.get("limit"))]
        except UsageError as e:
            raise ApiError("usage", str(e), status=400) from None
        problems = [n for n in chosen if n not in self.devices]
        if problems:
            raise ApiError("conflict", f"{', '.join(problems)}: new in the inventory; the agent owns them from its "
                           "next start", status=409, exit_code=1)
        recipe = req.get("recipe")
        if recipe:
            other = [n for n in chosen if os.path.abspath(files.jobs[n].recipe.path or "") != os.path.abspath(recipe)]
            if other:
                raise ApiError("refused", f"{recipe} is not the recipe the inventory gives {', '.join(other)}: the "
                               "agent holds one desired state; edit the files (inventory and recipes) instead",
                               status=422)
        opts = ApplyOptions(write_all=bool(req.get("write_all")))
        changes: dict[str, Any] = {}
        for key in ("soak", "health_interval", "confirm_within"):
            if req.get(key) is not None:
                try:
                    changes[key] = parse_duration(str(req[key]))
                except ValueError as e:
                    raise ApiError("usage", f"{key}: {e}", status=400) from None
        if req.get("allow_unhealthy"):
            if "soak" not in changes and "confirm_within" not in changes:
                raise ApiError("usage", "allow_unhealthy goes with soak or confirm_within (only a safe change reads "
                               "the health checks before it writes)", status=400)
            changes["allow_unhealthy"] = True
        opts = replace(opts, **changes)
        jobs = [files.jobs[n] for n in chosen]
        self._check_endurance(jobs, force=bool(req.get("force_endurance")))
        options = {k: req[k] for k in ("limit", "batch", "max_failures", "parallel", "soak", "health_interval",
                                       "confirm_within", "allow_unhealthy", "rollback_on_failure", "write_all",
                                       "by", "recipe")
                   if req.get(k) is not None}
        return self.start_run(jobs, command="apply", options=options, opts=opts, label=self.settings.inventory,
                              batch=req.get("batch"), max_failures=req.get("max_failures"),
                              parallel=int(req.get("parallel") or 8),
                              rollback_on_failure=bool(req.get("rollback_on_failure")), adopt=True)

    def start_run(self, jobs: Sequence[Job], *, command: str, options: dict[str, Any], opts: ApplyOptions,
                  label: str | None, batch: str | None = None, max_failures: str | None = None, parallel: int = 8,
                  rollback_on_failure: bool = False, adopt: bool = False, health_unchecked: bool = False) -> RunState:
        """Start a run of ``jobs`` (ApiError: refused, nothing sent). ``health_unchecked``: a soak may include
        profiles without health checks (the agent's staged first restores); a client's soak may not."""
        busy = [j.name for j in jobs if self.devices[j.name].run is not None]
        if busy:
            raise ApiError("conflict", f"{', '.join(busy)}: in run {self.devices[busy[0]].run} now; wait for it",
                           status=409, exit_code=3)
        unowned = [j.name for j in jobs if not self.devices[j.name].owned]
        if unowned:
            why = self.devices[unowned[0]].not_owned_why or "its lock is held elsewhere"
            raise ApiError("locked", f"{', '.join(unowned)}: not owned by the agent ({why}); nothing was sent",
                           status=409, exit_code=3)
        from ..run.runner import fleet_options

        try:
            fleet_options(len(jobs), parallel=parallel, batch=batch, max_failures=max_failures)
        except UsageError as e:
            raise ApiError("usage", str(e), status=400) from None
        if opts.soak is not None and not health_unchecked:
            from ..window.soak import check_soak_profiles

            try:
                check_soak_profiles([j.recipe.profile for j in jobs])
            except UsageError as e:
                raise ApiError("usage", str(e), status=400) from None
        run_id = journal.new_run_id()
        by = options.get("by") or {}
        who = by.get("user") or (f"the {by['credential']}" if by.get("credential") else None)
        opts = replace(opts, state_dir=self.state_dir, run_id=run_id, command=f"agent {command}"
                       + (f" by {who}" if who else "") + (f": {options['reason']}" if options.get("reason") else ""))
        run = RunState(run_id, command, [j.name for j in jobs], options)
        self.runs[run_id] = run
        for j in jobs:
            self.devices[j.name].run = run_id
        assert self.store is not None
        self.store.run_started(run_id, command, options)
        run.emit("run-started", run=run_id, command=command, devices=run.devices, by=options.get("by"))
        run.task = asyncio.ensure_future(self._execute(run, jobs, opts, label=label, batch=batch,
                                                       max_failures=max_failures, parallel=parallel,
                                                       rollback_on_failure=rollback_on_failure, adopt=adopt))
        return run

    async def _execute(self, run: RunState, jobs: Sequence[Job], opts: ApplyOptions, *, label: str | None,
                       batch: str | None, max_failures: str | None, parallel: int, rollback_on_failure: bool,
                       adopt: bool) -> None:
        from ..run.runner import run_async

        assert self.store is not None
        reports = os.path.join(self.folder, "reports")
        os.makedirs(reports, exist_ok=True)
        report_path = os.path.join(reports, f"{run.id}.json")
        counted: dict[str, int] = {}
        by_name = {j.name: j for j in jobs}

        def count(r: DeviceResult) -> None:
            run.results[r.name] = r
            start = counted.get(r.name, 0)
            counted[r.name] = len(r.requests)
            self._ledger(r, by_name[r.name].recipe.profile, r.requests[start:])

        def done(r: DeviceResult) -> None:
            count(r)
            run.emit("device-finished", device=r.to_json())

        def changed(r: DeviceResult) -> None:
            count(r)
            run.emit("device-changed", device=r.to_json())

        def started(j: Job) -> None:
            run.emit("device-started", name=j.name)

        def soaking(number: int, names: list[str]) -> None:
            deadline = time.time() + (opts.soak or 0)
            from ..window.held import pending_path

            self.store.open_window(run.id, "soak", names, deadline, pending_path(self.state_dir, run.id))  # type: ignore[union-attr]
            run.window = {"kind": "soak", "devices": names, "deadline": _iso(deadline), "deadline_epoch": deadline}
            run.emit("soak-started", batch=number, devices=names, deadline=_iso(deadline))

        def waiting(run_id: str, deadline: float) -> None:
            from ..window.held import pending_path

            names = [n for n, r in run.results.items() if r.status == "ok" and r.snapshot is not None]
            assert self.store is not None
            self.store.close_window(run.id, "soak", "passed")
            self.store.open_window(run.id, "confirm", names, deadline, pending_path(self.state_dir, run.id))
            run.state = "waiting"
            run.window = {"kind": "confirm", "devices": names, "deadline": _iso(deadline), "deadline_epoch": deadline}
            self.event("window-waiting", f"run {run.id} waits for its confirmation until {_iso(deadline)} "
                       f"({', '.join(names)}): deployer confirm --agent {self.url} {run.id}",
                       detail={"run": run.id, "devices": names, "deadline": _iso(deadline)})
            run.emit("window-waiting", run=run.id, devices=names, deadline=_iso(deadline), deadline_epoch=deadline)

        report: Report | None = None
        state = "finished"
        error: DeployerError | None = None
        try:
            report = await run_async(list(jobs), command=run.command, label=label, argv=[], via="agent",
                                     options=opts, parallel=parallel, batch=batch, max_failures=max_failures,
                                     report_path=report_path, on_start=started, on_done=done, on_changed=changed,
                                     on_confirm_wait=waiting, on_soak=soaking,
                                     rollback_on_failure=rollback_on_failure)
        except RunInterrupted as e:
            report, state = e.report, "interrupted"
        except DeployerError as e:  # refused before anything was sent (a stale plan ...)
            error, state = e, "refused"
        except asyncio.CancelledError:
            state = "interrupted"
        finally:
            for j in jobs:
                self.devices[j.name].run = None
            self.store.close_window(run.id, "soak", "ended")
            win = run.window
            if win is not None and win["kind"] == "confirm" and win.get("state") is None:
                win["state"] = "expired" if report is None or any(
                    r.status == "rolled-back" for r in report.devices) else "confirmed"
                self.store.close_window(run.id, "confirm", win["state"])
                if win["state"] == "expired":
                    self.event("window-expired", f"run {run.id}: not confirmed in time, rolled back",
                               detail={"run": run.id})
                    run.emit("window-expired", run=run.id)
        if report is not None:
            for r in report.devices:
                dev = self.devices[r.name]
                if r.status == "ok" and r.commit in (None, "sent"):
                    after = {p.name: tuple(p.after_raw) for p in r.parameters if p.after_raw is not None}
                    if adopt:
                        self._adopt(dev, by_name[r.name], ds.values_of(by_name[r.name].recipe), run=run.id,
                                    why=f"run {run.id}")
                    elif run.command == "rollback":  # what was restored is the state to keep, not what was undone
                        back = {n: v for n, v in ds.values_of(by_name[r.name].recipe).items()
                                if n in dev.adopted_values}
                        self._adopt(dev, dev.job, {**dev.adopted_values, **back}, run=run.id,
                                    why=f"rollback run {run.id}")
                    dev.asleft = {n: v for n, v in after.items() if n in dev.adopted_values}
                    self.store.set_asleft(r.name, dev.asleft,
                                          f"run {run.id}")
                    if run.command == "restore":
                        dev.drift_restores += 1
                        dev.drift, dev.status, dev.replaced = [], "ok", None
                        self.event("restored", f"{r.name}: restored ({run.options.get('reason')}) by run {run.id}",
                                   device=r.name, detail={"run": run.id})
                elif run.command == "restore":
                    self.event("restore-failed", f"{r.name}: the restore run {run.id} ended {r.status}: {r.error}",
                               device=r.name, detail={"run": run.id})
            self._pending()
            run.report = report.to_json()
            run.exit_code = report.exit_code
        else:
            run.exit_code = 130 if state == "interrupted" else (error.exit_code if error else 1)
        run.state, run.finished = state, time.time()
        self.first.finished(self, run.id, report, state)
        self.store.run_ended(run.id, state, run.exit_code, report_path if report is not None else None)
        self.event("run-finished", f"run {run.id} ({run.command}) {state}, exit code {run.exit_code}",
                   detail={"run": run.id, "exit_code": run.exit_code, "by": run.options.get("by")})
        if report is not None:
            from .audit_events import run_finished

            run_finished(self, report, command=run.command, by=run.options.get("by"))
        run.emit("run-finished", run=run.id, state=state, exit_code=run.exit_code, report=run.report,
                 error=None if error is None else str(error))

    def start_restore(self, req: Mapping[str, Any]) -> RunState:
        """``POST /v1/runs`` with command restore: write the adopted state back to the selected devices."""
        assert self.files is not None
        try:
            chosen = [d.name for d in self.files.inventory.select(req.get("limit")) if d.name in self.devices]
        except UsageError as e:
            raise ApiError("usage", str(e), status=400) from None
        jobs = []
        for n in chosen:
            dev = self.devices[n]
            if dev.adopted is not None:
                jobs.append(Job(n, dev.adopted, dev.job.url, dev.job.unit))
        if not jobs:
            raise ApiError("usage", "no device selected", status=400)
        self._check_endurance(jobs, force=bool(req.get("force_endurance")))
        return self.start_run(jobs, command="restore", options={"reason": "requested", "by": req.get("by")},
                              opts=ApplyOptions(), label="the adopted state")

    async def start_rollback(self, run_id: str, *, by: Mapping[str, Any] | None = None) -> RunState:
        """``POST /v1/runs/{id}/rollback``: restore what a finished run wrote, from its snapshots."""
        from ..run.rollback import report_jobs

        run = self.runs.get(run_id)
        if run is None:
            raise ApiError("not-found", f"no run {run_id} in this agent", status=404)
        if run.state in ("running", "waiting"):
            raise ApiError("conflict", f"run {run_id} has not ended (it is {run.state}); wait for it, or let its "
                           "window run out", status=409)
        path = os.path.join(self.folder, "reports", f"{run_id}.json")
        try:  # it reads the devices (do they still hold what the run wrote?) with a loop of its own
            jobs, notices = await asyncio.to_thread(report_jobs, [path])
        except DeployerError as e:
            raise ApiError("usage", f"run {run_id}: {e}", status=400) from None
        jobs = [j for j in jobs if j.name in self.devices]
        if not jobs:
            raise ApiError("usage", f"run {run_id} wrote nothing to roll back", status=400)
        return self.start_run(jobs, command="rollback", options={"reason": f"rollback of run {run_id}",
                                                                 "notices": notices, "by": by},
                              opts=ApplyOptions(), label=path)

    def ledger_json(self) -> dict[str, Any]:
        assert self.store is not None
        counts = self.store.ledger()
        out = []
        for dev in self.devices.values():
            prof = dev.adopted.profile if dev.adopted else dev.job.recipe.profile
            budgets = self._budgets(prof)
            regs = counts.get(dev.name, {})
            out.append({"name": dev.name, "registers": [
                {"register": k, "address": k & 0xFFFF, "writes": w, "commits": c,
                 "budget": budgets[k][0] if k in budgets else None} for k, (w, c) in sorted(regs.items())]})
        return {"devices": out}

    def status_json(self) -> dict[str, Any]:
        assert self.store is not None
        look = [self.device_json(d) for d in self.devices.values() if d.status not in ("ok",) or d.run or d.pending]
        return {"agent": self.agent_json(), "devices": look, "windows": self.windows_json(),
                "runs": [r.to_json(report=False) for r in self.runs.values() if r.state in ("running", "waiting")],
                "events": self.store.events(limit=20), "files_problems": self.files_problem}

    def confirm(self, run_id: str | None, *, by: Mapping[str, Any] | None = None) -> RunState:
        """Confirm a run waiting in its confirm window (the one waiting when ``run_id`` is None); ``by``: who."""
        from ..window.confirm import confirm_run

        waiting = [r for r in self.runs.values() if r.state == "waiting"]
        if run_id is None:
            if len(waiting) != 1:
                raise ApiError("conflict", "no run waits for a confirmation" if not waiting else
                               "several runs wait for a confirmation: name one: "
                               + ", ".join(r.id for r in waiting), status=409)
            run_id = waiting[0].id
        run = self.runs.get(run_id)
        if run is None:
            raise ApiError("not-found", f"no run {run_id} in this agent", status=404)
        if run.state != "waiting":
            raise ApiError("conflict", f"run {run_id} does not wait for a confirmation (it is {run.state})",
                           status=409)
        if not run.options.get("resumed"):  # a live run waits for the journal's confirmed line
            try:
                confirm_run(self.state_dir, run_id)
            except UsageError as e:
                raise ApiError("conflict", str(e), status=409) from None
        else:
            journal.append(self.state_dir, {"event": "confirmed", "run": run_id, "time": journal._now(),
                                            "user": journal.user_name(), "pid": os.getpid(), "via": "agent"})
        assert self.store is not None
        self.store.close_window(run_id, "confirm", "confirmed")
        if run.window is not None:
            run.window["state"] = "confirmed"
        run.state = "running"
        self.event("window-confirmed", f"run {run_id} confirmed" + (f" by {by['user']}" if by and by.get("user")
                                                                    else ""), detail={"run": run_id, "by": by})
        run.emit("window-confirmed", run=run_id)
        return run

    async def _recover_windows(self) -> None:
        """Windows left open by an agent that died: expired (deadline passed, or another boot) ones are
        rolled back from their snapshots; the others keep waiting, then commit or roll back."""
        assert self.store is not None
        for w in self.store.windows():
            expired = w["boot_id"] != self.boot or w["deadline_epoch"] <= time.time() or w["kind"] == "soak"
            why = ("the machine restarted (another boot) during the window" if w["boot_id"] != self.boot else
                   "the agent stopped during the soak (a soak not watched to its end did not pass)"
                   if w["kind"] == "soak" else "the window ran out while the agent was down")
            if expired:
                await self._roll_back_window(w, why)
            else:
                self._tasks.add(asyncio.ensure_future(self._resume_window(w)))

    async def _roll_back_window(self, w: dict[str, Any], why: str) -> None:
        from ..run.rollback import report_jobs

        assert self.store is not None
        self.store.close_window(w["run"], w["kind"], "expired")
        self.event("window-expired", f"run {w['run']}: {why}; rolling back {', '.join(w['devices'])}",
                   detail={"run": w["run"], "devices": w["devices"]})
        try:
            jobs, _ = await asyncio.to_thread(report_jobs, [w["report"]], force=True, even_if_changed=True)
        except DeployerError as e:
            self.event("restore-failed", f"run {w['run']}: cannot roll back its window: {e}",
                       detail={"run": w["run"]})
            return
        jobs = [j for j in jobs if j.name in self.devices]
        if not jobs:
            return
        try:
            run = self.start_run(jobs, command="rollback", options={"reason": f"window of run {w['run']}: {why}"},
                                 opts=ApplyOptions(hold_commit=True), label=w["report"])
        except ApiError as e:
            self.event("restore-failed", f"run {w['run']}: cannot roll back its window: {e}",
                       detail={"run": w["run"]})
            return
        if run.task is not None:
            await asyncio.shield(run.task)
        with contextlib.suppress(KeyError, OSError):
            journal.resolve(self.state_dir, w["run"], note=f"agent: rolled back by run {run.id} ({why})")
        with contextlib.suppress(OSError):
            os.remove(w["report"])

    async def _resume_window(self, w: dict[str, Any]) -> None:
        """A confirm window that outlived its agent and has time left: wait for the confirmation, then commit."""
        from ..report import read_report
        from ..window.finish import send_commit
        from ..window.held import Written

        run_id = w["run"]
        run = RunState(run_id, "apply (resumed window)", list(w["devices"]), {"resumed": True})
        run.state = "waiting"
        run.window = {"kind": "confirm", "devices": w["devices"], "deadline": w["deadline"],
                      "deadline_epoch": w["deadline_epoch"]}
        self.runs[run_id] = run
        for n in w["devices"]:
            if n in self.devices:
                self.devices[n].run = run_id
        self.event("window-waiting", f"run {run_id} (from before the agent's restart) waits for its confirmation "
                   f"until {w['deadline']}", detail={"run": run_id, "devices": w["devices"]})
        left = w["deadline_epoch"] - time.time()
        deadline = time.monotonic() + left  # from now on the monotonic clock counts
        try:
            while run.state == "waiting" and time.monotonic() < deadline:
                ev = run.changed
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(ev.wait(), min(0.2, max(0.0, deadline - time.monotonic())))
        except asyncio.CancelledError:
            for n in w["devices"]:
                if n in self.devices:
                    self.devices[n].run = None
            raise
        for n in w["devices"]:
            if n in self.devices:
                self.devices[n].run = None
        if run.state == "waiting":  # not confirmed
            run.state = "finished"
            await self._roll_back_window(w, "not confirmed in time")
            run.finished = time.time()
            run.emit("run-finished", run=run_id, state="rolled-back", exit_code=4, report=None, error=None)
            return
        from ..report import report_from_json

        held = report_from_json(read_report(w["report"]))  # what the run wrote and read back, per parameter
        opts = ApplyOptions(state_dir=self.state_dir, run_id=run_id)
        for res in held.devices:
            if res.name not in self.devices or res.commit != "held":
                continue
            dev = self.devices[res.name]
            sent = len(res.requests)
            # the commit reads the run's parameters again first: one changed meanwhile is never committed
            await send_commit(Written(Job(dev.name, dev.job.recipe, dev.job.url, dev.job.unit), res), opts)
            self._ledger(res, dev.job.recipe.profile, res.requests[sent:])
            run.results[dev.name] = res
            if _committed(res):  # the run's end, which its agent did not live to see: adopted now
                values = {p.name: tuple(p.desired_raw) for p in res.parameters if p.status in ("ok", "unchanged")}
                self._adopt(dev, dev.job, {**dev.adopted_values, **values}, run=run_id,
                            why=f"run {run_id}, confirmed after the agent's restart")
        self._pending()
        with contextlib.suppress(KeyError, OSError):
            journal.resolve(self.state_dir, run_id, note="agent: confirmed after the agent's restart, commit sent")
        with contextlib.suppress(OSError):
            os.remove(w["report"])
        run.state, run.finished, run.exit_code = "finished", time.time(), 0
        run.emit("run-finished", run=run_id, state="finished", exit_code=0, report=None, error=None)

    # ---- the write ledger ---------------------------------------------------------------------------

    def _ledger(self, r: DeviceResult, profile: Profile, requests: Sequence[Any]) -> None:
        """Count write requests (every attempt sent) per register; a commit action's register counts commits."""
        assert self.store is not None
        from ..profile.model import SPACE

        commit_keys = {a.key for a in profile.commit}
        writes: dict[int, int] = {}
        commits: dict[int, int] = {}
        for q in requests:
            if q.function not in WRITES or not q.attempts:
                continue
            space = SPACE["coil"] << 16 if q.function in (5, 15) else 0
            for a in range(q.address, q.address + q.count):
                target = commits if space | a in commit_keys else writes
                target[space | a] = target.get(space | a, 0) + q.attempts
        if not writes and not commits:
            return
        self.store.count_writes(r.name, writes, commits)
        dev = self.devices.get(r.name)
        if dev is not None:
            dev.writes += sum(writes.values()) + sum(commits.values())
            self._endurance_warnings(dev, profile, set(writes) | set(commits))

    def _budgets(self, profile: Profile) -> dict[int, tuple[int, str]]:
        """Register key -> (endurance, what) for the registers a profile states a budget for."""
        out: dict[int, tuple[int, str]] = {}
        for p in profile.parameters:
            e = p.endurance or profile.endurance
            if e:
                for k in range(p.key, p.key + p.count):
                    out[k] = (e, p.name)
        if profile.endurance:
            for a in profile.commit:
                out[a.key] = (profile.endurance, "commit")
        return out

    def _endurance_warnings(self, dev: Device, profile: Profile, keys: set[int]) -> None:
        assert self.store is not None
        budgets = self._budgets(profile)
        counts = self.store.ledger(dev.name).get(dev.name, {})
        for k in sorted(keys & set(budgets)):
            budget, what = budgets[k]
            used = sum(counts.get(k, (0, 0)))
            if used >= budget * self.settings.endurance_warn:
                self.event("endurance-warning", f"{dev.name}: register 0x{k & 0xFFFF:04X} ({what}) has taken {used} "
                           f"of the {budget} writes its memory is rated for", device=dev.name,
                           detail={"register": k, "writes": used, "endurance": budget})

    def _check_endurance(self, jobs: Sequence[Job], *, force: bool) -> None:
        assert self.store is not None
        over = []
        for j in jobs:
            budgets = self._budgets(j.recipe.profile)
            counts = self.store.ledger(j.name).get(j.name, {})
            keys = {k for d in j.recipe.desired for k in range(d.parameter.key, d.parameter.key + d.parameter.count)}
            keys |= {a.key for a in j.recipe.profile.commit}
            for k in sorted(keys & set(budgets)):
                used = sum(counts.get(k, (0, 0)))
                if used >= budgets[k][0]:
                    over.append(f"{j.name} register 0x{k & 0xFFFF:04X} ({budgets[k][1]}): {used} of "
                                f"{budgets[k][0]} writes")
        if over and not force:
            self.event("endurance-refused", "past the endurance budget: " + "; ".join(over))
            raise ApiError("refused", "past the rated endurance of its memory, nothing sent: " + "; ".join(over)
                           + " (force_endurance, --force-endurance, to write anyway)", status=422, exit_code=1)

    # ---- views ------------------------------------------------------------------------------------------

    def device_json(self, dev: Device, *, full: bool = False) -> dict[str, Any]:
        prof = dev.adopted.profile if dev.adopted else dev.job.recipe.profile
        status = "running" if dev.run else dev.status
        out: dict[str, Any] = {
            "name": dev.name, "url": describe(dev.job.url), "unit": dev.job.unit, "profile": prof.id,
            "status": status, "owned": dev.owned, "drifted": bool(dev.drift), "drift": dev.drift,
            "last_check": None if dev.last_check is None else _iso(dev.last_check),
            "unreachable": dev.unreachable_why, "replaced": dev.replaced, "not_owned": dev.not_owned_why,
            "pending": len(dev.pending), "run": dev.run, "restores_last_hour": len(dev.restores),
            "writes": dev.writes, "check_every": dev.check_every, "on_drift": dev.on_drift,
            "on_replace": dev.on_replace,
        }
        if full and self.store is not None:
            ident = self.store.identity(dev.name)
            left = self.store.asleft(dev.name)
            out.update({
                "identity": None if ident is None else {"objects": ident[0], "registers": ident[1],
                                                        "function_43": ident[2]},
                "adopted": {n: prof.parameter(n).show_registers(v) for n, v in dev.adopted_values.items()},
                "adopted_recipe": dev.adopted.path if dev.adopted else None,
                "last_values": None if dev.last_values is None else
                {n: prof.parameter(n).show_registers(v) for n, v in dev.last_values.items()},
                "asleft": None if left is None else {n: prof.parameter(n).show_registers(v)
                                                     for n, v in left[0].items() if prof.get(n) is not None},
                "pending_changes": dev.pending,
            })
        return out

    def windows_json(self) -> list[dict[str, Any]]:
        assert self.store is not None
        now = time.time()
        return [{**{k: v for k, v in w.items() if k != "options"}, "seconds_left": max(0.0, w["deadline_epoch"] - now)}
                for w in self.store.windows()]

    def agent_json(self) -> dict[str, Any]:
        from importlib.metadata import PackageNotFoundError, version

        try:
            v = version("modbus-deployer")
        except PackageNotFoundError:  # pragma: no cover - a source checkout without install
            v = "unknown"
        s = self.settings
        return {"version": v, "api": API_VERSION, "url": self.url, "inventory": os.path.abspath(s.inventory),
                "state_dir": self.state_dir, "pid": os.getpid(), "boot_id": self.boot, "started": _iso(self.started),
                "auth": "none", "files_sha256": self.files.sha256 if self.files else None,
                "options": {"check_every": s.check_every, "on_drift": s.on_drift, "on_replace": s.on_replace,
                            "bus_share": s.bus_share, "max_restores": s.max_restores,
                            "endurance_warn": s.endurance_warn, "first_restore_soak": s.first_restore_soak},
                "restores_stopped": self.first.stopped,
                "checks": self.checks, "last_check_seconds": self.check_seconds}


class _OtherModel(Exception):
    """The identity registers say another kind of device answers at the address."""


async def _read(profile: Profile, names: Sequence[str], url: tp.DeviceURL, unit: int, ask43: bool
                ) -> tuple[dict[str, tuple[int, ...]], dict[str, str] | None, bool]:
    """One check's read: Function 43 objects (when the device answers it), the identity registers, the values."""
    async with connected(url, unit, profile) as session:
        return await _read_in(session, profile, names, url, unit, ask43)


async def _read_in(session: Session, profile: Profile, names: Sequence[str], url: tp.DeviceURL, unit: int,
                   ask43: bool) -> tuple[dict[str, tuple[int, ...]], dict[str, str] | None, bool]:
    try:
        objects = await session.identify() if ask43 else None
        from ..errors import IdentityMismatch

        try:
            await check_identity(session, profile)
        except IdentityMismatch as e:
            raise _OtherModel(str(e)) from None
        params = [profile.parameter(n) for n in names]
        values = _values_of(params, await session.read_blocks(plan_reads(profile, list(names)), profile))
        return values, objects, objects is not None
    except ExceptionResponse as e:
        raise Unreachable(f"{describe(url)} unit {unit}: reading answered {e}") from None


def _take_now(url: tp.DeviceURL, unit: int) -> list[lock.DeviceLock]:
    """The device's locks without waiting (the agent's start and each check try again), and its marks where
    every process looks whatever its lock folder (``lock.agent_marks``)."""
    keys = sorted(set(url.lock_keys))
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


def drifted(profile: Profile, adopted: Mapping[str, tuple[int, ...]], values: Mapping[str, tuple[int, ...]]
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
        out.append({"name": n, "adopted": p.show_registers(want),
                    "device": None if have is None else p.show_registers(have),
                    "adopted_raw": list(want), "device_raw": None if have is None else list(have)})
    return out


def _committed(res: DeviceResult) -> bool:
    return res.commit == "sent"


def _said(d: Mapping[str, Any]) -> str:
    return f"{d['name']} is {d['device'] if d['device'] is not None else 'unreadable'} (adopted {d['adopted']})"


def _iso(t: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t))
