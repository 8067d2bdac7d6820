"""The audit log as a journal: STATE/audit.jsonl, one JSON object per line, each fsync'ed.

A run appends ``run-started`` before touching any device, ``device-started`` (device, snapshot,
plan digest) before its first write to a device, ``device-finished`` after that device's
read-back, and ``run-finished`` (the whole outcome) at the end. After a crash (``kill -9``, a
laptop going to sleep) the log still says which devices were being written and where their
snapshots are: ``deployer status`` lists the runs that never finished.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from .. import portable
from ..errors import StateError
from .durable import append_lines, disk_error
from .holder import boot_id
from .lock import pid_alive

if TYPE_CHECKING:
    from ..report import DeviceResult, Report

AUDIT = "audit.jsonl"


def user_name() -> str:
    """The login name (not the uid): who ran it is what an audit trail is for."""
    return portable.user_name()


_issued: dict[str, int] = {}  # run ids this process gave out in its current second


def new_run_id() -> str:
    """Time and PID; a second run started by one process within the same second (the agent, an API user)
    gets ``-2``, ``-3`` ... so ids never repeat."""
    base = f"{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}-{os.getpid()}"
    n = _issued.get(base, 0) + 1
    _issued.clear()  # only the current second matters
    _issued[base] = n
    return base if n == 1 else f"{base}-{n}"


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def deadline(seconds: float) -> dict[str, Any]:
    """A window's deadline ``seconds`` from now, for its journal line: on the wall clock (for people, and after a
    reboot) and on the monotonic clock (what the waiting process goes by: a clock step changes nothing), with
    this boot's id (a monotonic time means nothing in another boot)."""
    now = time.time()
    return {
        "deadline": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(now + seconds)),
        "deadline_epoch": now + seconds,
        "deadline_monotonic": time.monotonic() + seconds,
        "boot_id": boot_id(),
    }


def path_of(state_dir: str) -> str:
    return os.path.join(state_dir, AUDIT)


def append(state_dir: str, record: dict[str, Any]) -> None:
    """One line, written with a single append and fsync'ed: concurrent runs never interleave inside a line.

    Raises StateError when the state directory cannot take it (disk full, read-only)."""
    try:
        append_lines(path_of(state_dir), [record])
    except OSError as e:
        raise StateError(f"cannot write the journal {path_of(state_dir)}: {disk_error(e)}") from None


def run_started(
    state_dir: str,
    run: str,
    *,
    command: str,
    argv: Sequence[str],
    recipe: str | None,
    devices: Iterable[tuple[str, str, int]],
    via: str = "cli",
    user: str | None = None,
) -> None:
    """``via``: who started the run (``cli``, ``api``, ``ansible``, ``agent``); ``user``: who asked, where it is not
    this process's user (the agent's authenticated user)."""
    append(
        state_dir,
        {
            "event": "run-started",
            "run": run,
            "time": _now(),
            "user": user or user_name(),
            "pid": os.getpid(),
            "command": command,
            "via": via,
            "argv": list(argv),
            "recipe": recipe,
            "devices": [{"name": n, "url": u, "unit": un} for n, u, un in devices],
        },
    )


def device_started(
    run: str,
    *,
    name: str,
    url: str,
    unit: int,
    plan_digest: str,
    batch: int | None = None,
    restoring: str | None = None,
) -> dict[str, Any]:
    """The ``device-started`` record, without its ``snapshot`` (``durable`` adds the file's final path).
    ``batch``: a fleet run's batch number (not in the record of a single device's run); ``restoring``:
    a rollback's snapshot that this device is being restored from."""
    rec: dict[str, Any] = {
        "event": "device-started",
        "run": run,
        "time": _now(),
        "name": name,
        "url": url,
        "unit": unit,
        **({"batch": batch} if batch is not None else {}),
        "snapshot": None,
        "plan_sha256": plan_digest,
    }
    if restoring is not None:
        rec["restoring"] = restoring
    return rec


def snapshots_restored(restored: Sequence[str], log: str) -> dict[str, Any]:
    """The line saying which snapshots were restored from the write-ahead log folder ``log`` (``state.wal``)."""
    return {
        "event": "snapshots-restored",
        "time": _now(),
        "snapshots": list(restored),
        "why": f"a process ended before its snapshots were fsync'ed; restored from the write-ahead log in {log}",
    }


def device_finished(run: str, res: DeviceResult) -> dict[str, Any]:
    """The ``device-finished`` record (status after the read-back)."""
    return {"event": "device-finished", "run": run, "time": _now(), **_device(res)}


def _device(d: DeviceResult) -> dict[str, Any]:
    out: dict[str, Any] = {
        "name": d.name,
        "url": d.url,
        "unit": d.unit,
        **_batch(d),
        "status": d.status,
        "snapshot": d.snapshot,
        "written": _written(d),
        "write_requests": d.write_requests,
    }
    if d.restored is not None:
        out["restored"] = d.restored
    if d.identity is not None:
        out["identity"] = dict(d.identity)
    return out


def _batch(res: DeviceResult) -> dict[str, int]:
    return {} if res.batch is None else {"batch": res.batch}


def _written(res: DeviceResult) -> list[str]:
    return list(res.written)


def run_finished(state_dir: str, run: str | None, report: Report, *, command: str, argv: Sequence[str] = ()) -> None:
    """The run's outcome: who, when, what, and per device its status and snapshot (``interrupted``: the
    signal that stopped it early)."""
    append(state_dir, finished_record(run, report, command=command, argv=argv))


def finished_record(run: str | None, report: Report, *, command: str, argv: Sequence[str] = ()) -> dict[str, Any]:
    """The ``run-finished`` record (``run_finished`` appends it; the runner queues it behind its devices' lines)."""
    rec: dict[str, Any] = {
        "event": "run-finished",
        "run": run,
        "time": _now(),
        "user": user_name(),
        "command": command,
        "argv": list(argv),
        "recipe": report.recipe,
        "exit_code": report.exit_code,
        "devices": [_device(d) for d in report.devices],
    }
    if report.interrupted is not None:
        rec["interrupted"] = report.interrupted
    return rec


def run_refused(
    state_dir: str, run: str, why: str, *, command: str, argv: Sequence[str] = (), recipe: str | None = None
) -> None:
    """A run that ended before its first write (a stale saved plan, a "no" at the prompt): nothing to look at."""
    append(
        state_dir,
        {
            "event": "run-finished",
            "run": run,
            "time": _now(),
            "user": user_name(),
            "command": command,
            "argv": list(argv),
            "recipe": recipe,
            "exit_code": 1,
            "refused": why,
            "devices": [],
        },
    )


@dataclass
class Unfinished:
    """A run that needs a look: no run-finished line (a crash, ``kill -9``), or one that says it was
    interrupted while writing some devices; until those are rolled back or the run is resolved."""

    run: str
    time: str
    user: str
    pid: int | None
    command: str
    argv: list[str]
    recipe: str | None
    devices: list[dict[str, Any]]  # every device the run selected
    interrupted: list[dict[str, Any]] = field(default_factory=list)  # started writing, never finished
    finished: list[dict[str, Any]] = field(default_factory=list)
    via: str = "cli"  # who started it: cli, api, ansible
    ended: str | None = None  # it has a run-finished line: the interruption that ended it ("SIGINT" ...)

    @property
    def running(self) -> bool:
        """The process is still alive (a run in progress, not a crash)."""
        return self.ended is None and self.pid is not None and pid_alive(self.pid)


def _key(rec: dict[str, Any]) -> tuple[Any, Any, Any]:
    return rec.get("name"), rec.get("url"), rec.get("unit")


def read(state_dir: str, *, containing: str | None = None, missing_ok: bool = True) -> Iterator[dict[str, Any] | None]:
    """The journal's records in order, and None for each line that is not JSON (a torn line); JSON that
    is not an object is passed over.

    ``containing``: lines without this text are passed over unparsed (a cheap filter). No journal:
    nothing, or FileNotFoundError unless ``missing_ok``; other OSErrors are the caller's.
    """
    try:
        f = open(path_of(state_dir), encoding="utf-8", errors="replace")  # noqa: SIM115 - closed below
    except FileNotFoundError:
        if missing_ok:
            return
        raise
    with f:
        for line in f:
            if containing is not None and containing not in line:
                continue
            try:
                rec = json.loads(line)
            except ValueError:
                yield None
                continue
            if isinstance(rec, dict):
                yield rec


def unfinished(state_dir: str) -> tuple[list[Unfinished], int]:
    """Runs that need a look, oldest first, and the number of lines that were not JSON (a torn line).

    A run drops out when it finished without leaving a device interrupted, when every device it left
    interrupted was restored afterwards from that device's snapshot (a rollback that ended ok), or when
    someone resolved it (``run-resolved``).
    """
    runs: dict[str, Unfinished] = {}
    bad = 0

    undone: set[str] = set()  # snapshots restored by a later rollback that ended ok

    def restored(snapshot: str) -> None:
        undone.add(snapshot)
        for r, u in list(runs.items()):
            left = [d for d in u.interrupted if d.get("snapshot") != snapshot]
            wrote = {d.get("snapshot") for d in u.finished if d.get("snapshot") and d.get("status") != "rolled-back"}
            if len(left) == len(u.interrupted) and snapshot not in wrote:
                continue
            u.interrupted = left
            # a run that died in its window (its devices finished, their commit held): gone once each is restored
            if not left and not u.running and wrote <= undone:
                del runs[r]

    for rec in read(state_dir):
        if rec is None:
            bad += 1
            continue
        run, event = rec.get("run"), rec.get("event")
        if not run:
            continue
        if event == "run-started":
            runs[run] = Unfinished(
                run,
                rec.get("time", ""),
                rec.get("user", ""),
                rec.get("pid"),
                rec.get("command", ""),
                rec.get("argv", []),
                rec.get("recipe"),
                rec.get("devices", []),
                via=str(rec.get("via", "cli")),
            )
        elif event == "device-started" and run in runs:
            runs[run].interrupted.append(rec)
        elif event == "device-finished" and run in runs:
            u = runs[run]
            u.interrupted = [d for d in u.interrupted if _key(d) != _key(rec)]
            u.finished.append(rec)
        elif event == "run-finished":
            ended = runs.pop(run, None)
            devices = [d for d in rec.get("devices") or [] if isinstance(d, dict)]
            left = [d for d in devices if d.get("status") == "interrupted" and d.get("snapshot")]
            if ended is not None and left:  # ended early while writing these: they need a look
                starts = {_key(d): d for d in ended.interrupted}
                ended.interrupted = [{**starts.get(_key(d), {}), **d} for d in left]
                ended.finished = [d for d in devices if d not in left]
                ended.ended = str(rec.get("interrupted") or "interrupted")
                runs[run] = ended
            for d in devices:
                if d.get("status") == "ok" and d.get("restored"):
                    restored(str(d["restored"]))
        elif event == "run-resolved":
            runs.pop(run, None)
    return list(runs.values()), bad


def resolve(state_dir: str, run: str, *, note: str | None = None) -> Unfinished:
    """Acknowledge a run ``status`` lists (after a look): a ``run-resolved`` line, by whom and when.
    Raises KeyError when no such run is listed."""
    listed = {u.run: u for u in unfinished(state_dir)[0]}
    if run not in listed:
        raise KeyError(run)
    rec: dict[str, Any] = {"event": "run-resolved", "run": run, "time": _now(), "user": user_name(), "pid": os.getpid()}
    if note:
        rec["note"] = note
    append(state_dir, rec)
    return listed[run]


def records(state_dir: str, run: str) -> list[dict[str, Any]]:
    """Every readable line of one run, in order (OSError when the journal cannot be read)."""
    return [
        rec
        for rec in read(state_dir, containing=f'"{run}"', missing_ok=False)
        if rec is not None and rec.get("run") == run
    ]


def snapshot_digest(state_dir: str, snapshot: str) -> str | None:
    """The SHA-256 the journal's ``device-started`` line recorded for ``snapshot`` (an absolute path), if any."""
    found = None
    with contextlib.suppress(OSError):
        # the path as the line spells it: JSON doubles a backslash (every Windows path has some) and escapes
        # what is not ASCII (a user name like Jürgen)
        for rec in read(state_dir, containing=json.dumps(snapshot)[1:-1]):
            if rec is not None and rec.get("event") == "device-started" and rec.get("snapshot") == snapshot:
                found = rec.get("snapshot_sha256") or found
    return found if isinstance(found, str) else None
