"""Who holds a device: the record kept in a lock file (one JSON object, ``deployer.lock/1``).

Every holder writes the same record, whoever it is (a command-line run, an API caller, the site
agent), so a second run can say who is in its way: the run id, the command, until when a safe-change
window holds the device (its deadline), and which process (PID and that process's start time: a
PID reused by an unrelated process is not taken for the holder). docs/locks.md describes the fields.
"""

from __future__ import annotations

import json
import os
import socket
import stat
import time
from typing import Any

from .. import portable

FORMAT = "deployer.lock/1"


def process_start(pid: int) -> float | None:
    """When process ``pid`` started (``portable.process_start``: Linux and Windows; None where the system
    does not say). A PID is reused once its process is gone; the pair (PID, start time) names one process."""
    return portable.process_start(pid)


def process_alive(pid: int, start: float | None = None) -> bool:
    """Whether process ``pid`` exists on this machine and, when ``start`` is known, is the one that started
    then (someone else's process counts: it is alive)."""
    if not portable.pid_alive(pid):
        return False
    if start is None:
        return True
    now = process_start(pid)
    return now is None or abs(now - start) < 0.05


def boot_id() -> str | None:
    """This boot of the machine (Linux): a PID and its start time name one process only within one boot."""
    try:
        with open("/proc/sys/kernel/random/boot_id", encoding="ascii") as f:
            return f.read().strip() or None
    except OSError:
        return None


_ME: dict[int, tuple[float | None, str | None, str]] = {}  # this process (by PID: a fork is another one)


def _me(pid: int) -> tuple[float | None, str | None, str]:
    """This process's start time, the boot and the host name: read once (a fleet takes two locks a device)."""
    me = _ME.get(pid)
    if me is None:
        me = _ME[pid] = (process_start(pid), boot_id(), socket.gethostname())
    return me


def new(key: str, *, command: str, run: str | None = None, agent: str | None = None) -> dict[str, Any]:
    """The record of the process taking a lock now."""
    pid = os.getpid()
    start, boot, host = _me(pid)
    return {
        "format": FORMAT,
        "key": key,
        "pid": pid,
        "pid_start": start,
        "boot_id": boot,
        "host": host,
        "since": time.time(),
        "command": command,
        "run": run,
        "window": None,
        "deadline": None,
        "agent": agent,
    }


def in_window(record: dict[str, Any], window: str, deadline: float | None) -> dict[str, Any]:
    """The record of a lock a safe-change window keeps: which window (``soak``, ``confirm``) and its deadline
    (time.time(); None: not known yet)."""
    return {**record, "window": window, "deadline": None if deadline is None else _iso(deadline)}


def _iso(t: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t))


def describe(record: dict[str, Any]) -> str:
    """Who holds it, for a message: the process (PID, host, since, command), then the site agent, the run, and a
    safe-change window with its deadline when there is one."""
    since = record.get("since")
    when = _iso(since) if isinstance(since, int | float) else "?"
    what = f" ({record['command']})" if record.get("command") else ""
    out = f"PID {record.get('pid', '?')} on {record.get('host', '?')} since {when}{what}"
    if record.get("agent"):
        out += f", the site agent at {record['agent']}"
    if record.get("run"):
        out += f", run {record['run']}"
    window = {"soak": "its soak", "confirm": "its confirmation window"}.get(str(record.get("window")))
    if window is not None:
        out += f", in {window}" + (f" until {record['deadline']}" if record.get("deadline") else "")
    return out


def parse(data: bytes) -> dict[str, Any]:
    """A lock file's record ({} when empty or not a record)."""
    try:
        rec = json.loads(data) if data.strip() else {}
    except ValueError:
        return {}
    return rec if isinstance(rec, dict) else {}


def held(directory: str) -> list[dict[str, Any]]:
    """The records of every lock held now in ``directory`` by a live process of this machine (a lock file whose
    process is gone is an old record: the kernel released its lock). Read only: nothing is locked to find out."""
    host = socket.gethostname()
    out = []
    try:
        names = sorted(os.listdir(directory))
    except OSError:
        return []
    for name in names:
        if not name.endswith(".lock"):
            continue
        try:
            fd = portable.open_nofollow(
                os.path.join(directory, name), os.O_RDONLY | portable.O_NONBLOCK | portable.O_BINARY
            )
        except OSError:
            continue
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                continue
            rec = parse(os.read(fd, 65536))
        except OSError:
            continue
        finally:
            os.close(fd)
        pid, start = rec.get("pid"), rec.get("pid_start")
        if (
            rec.get("host") == host
            and isinstance(pid, int)
            and process_alive(pid, start if isinstance(start, int | float) else None)
        ):
            out.append(rec)
    return out


def summary(records: list[dict[str, Any]], shown: int = 3) -> list[str]:
    """One line per holder (a process, its run and window): who, and the devices it holds (the first ``shown``
    of them by key, then how many more): a fleet run holding thousands of devices is one line."""
    holders: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for rec in records:
        who = (rec.get("pid"), rec.get("host"), rec.get("run"), rec.get("window"), rec.get("deadline"))
        holders.setdefault(who, []).append(rec)
    out = []
    for recs in holders.values():
        keys = sorted(str(r.get("key", "?")) for r in recs)
        more = f" and {len(keys) - shown} more" if len(keys) > shown else ""
        out.append(f"{', '.join(keys[:shown])}{more}: {describe(recs[0])}")
    return out
