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
import pwd
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from ..errors import StateError
from .durable import append_lines, disk_error
from .lock import pid_alive

if TYPE_CHECKING:
    from ..report import DeviceResult, Report

AUDIT = "audit.jsonl"


def user_name() -> str:
    """The login name (not the uid): who ran it is what an audit trail is for."""
    with contextlib.suppress(KeyError, OSError):
        return pwd.getpwuid(os.getuid()).pw_name
    return os.environ.get("USER") or os.environ.get("LOGNAME") or str(os.getuid())


def new_run_id() -> str:
    return f"{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}-{os.getpid()}"


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def path_of(state_dir: str) -> str:
    return os.path.join(state_dir, AUDIT)


def append(state_dir: str, record: dict[str, Any]) -> None:
    """One line, written with a single append and fsync'ed: concurrent runs never interleave inside a line.

    Raises StateError when the state directory cannot take it (disk full, read-only)."""
    try:
        append_lines(path_of(state_dir), [record])
    except OSError as e:
        raise StateError(f"cannot write the journal {path_of(state_dir)}: {disk_error(e)}") from None


def run_started(state_dir: str, run: str, *, command: str, argv: Sequence[str], recipe: str | None,
                devices: Iterable[tuple[str, str, int]]) -> None:
    append(state_dir, {"event": "run-started", "run": run, "time": _now(), "user": user_name(), "pid": os.getpid(),
                       "command": command, "argv": list(argv), "recipe": recipe,
                       "devices": [{"name": n, "url": u, "unit": un} for n, u, un in devices]})


def device_started(run: str, *, name: str, url: str, unit: int, plan_digest: str,
                   batch: int | None = None) -> dict[str, Any]:
    """The ``device-started`` record, without its ``snapshot`` (``durable`` adds the file's final path).
    ``batch``: a fleet run's batch number (not in the record of a single device's run)."""
    return {"event": "device-started", "run": run, "time": _now(), "name": name, "url": url, "unit": unit,
            **({"batch": batch} if batch is not None else {}), "snapshot": None, "plan_sha256": plan_digest}


def device_finished(run: str, res: DeviceResult) -> dict[str, Any]:
    """The ``device-finished`` record (status after the read-back)."""
    return {"event": "device-finished", "run": run, "time": _now(), "name": res.name, "url": res.url,
            "unit": res.unit, **_batch(res), "status": res.status, "snapshot": res.snapshot,
            "written": _written(res), "write_requests": res.write_requests,
            **({"identity": dict(res.identity)} if res.identity is not None else {})}


def _batch(res: DeviceResult) -> dict[str, int]:
    return {} if res.batch is None else {"batch": res.batch}


def _written(res: DeviceResult) -> list[str]:
    return [p.name for p in res.parameters if p.status in ("ok", "failed", "mismatch", "unverified")]


def run_finished(state_dir: str, run: str | None, report: Report, *, command: str, argv: Sequence[str] = ()) -> None:
    """The run's outcome: who, when, what, and per device its status and snapshot."""
    append(state_dir, {
        "event": "run-finished", "run": run,
        "time": _now(), "user": user_name(), "command": command, "argv": list(argv), "recipe": report.recipe,
        "exit_code": report.exit_code,
        "devices": [{"name": d.name, "url": d.url, "unit": d.unit, **_batch(d), "status": d.status,
                     "snapshot": d.snapshot,
                     "written": _written(d), "write_requests": d.write_requests} for d in report.devices],
    })


@dataclass
class Unfinished:
    """A run with a run-started line and no run-finished line."""

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

    @property
    def running(self) -> bool:
        """The process is still alive (a run in progress, not a crash)."""
        return self.pid is not None and pid_alive(self.pid)


def unfinished(state_dir: str) -> tuple[list[Unfinished], int]:
    """Runs that never finished, oldest first, and the number of lines that were not JSON (a torn last line)."""
    path = path_of(state_dir)
    runs: dict[str, Unfinished] = {}
    bad = 0
    try:
        f = open(path, encoding="utf-8")  # noqa: SIM115 - closed below
    except FileNotFoundError:
        return [], 0
    with f:
        for line in f:
            try:
                rec = json.loads(line)
            except ValueError:
                bad += 1
                continue
            if not isinstance(rec, dict):
                continue
            run, event = rec.get("run"), rec.get("event")
            if not run:
                continue
            if event == "run-started":
                runs[run] = Unfinished(run, rec.get("time", ""), rec.get("user", ""), rec.get("pid"),
                                       rec.get("command", ""), rec.get("argv", []), rec.get("recipe"),
                                       rec.get("devices", []))
            elif event == "device-started" and run in runs:
                runs[run].interrupted.append(rec)
            elif event == "device-finished" and run in runs:
                u = runs[run]
                u.interrupted = [d for d in u.interrupted if (d.get("name"), d.get("url"), d.get("unit")) !=
                                 (rec.get("name"), rec.get("url"), rec.get("unit"))]
                u.finished.append(rec)
            elif event == "run-finished":
                runs.pop(run, None)
    return list(runs.values()), bad
