"""One writer per device on this machine: an exclusive lock per device (URL + unit).

Two runs writing one device at once interleave on the wire: both snapshots record the
original values, one run's values are overwritten a moment after it verified them, and either
rollback restores the wrong state. So apply, rollback and fleet runs take the device's lock
before their first read and hold it until the read-back is done.

The lock is an ``flock`` on a file in a directory every run on this machine shares, whatever
its working or state directory: ``$DEPLOYER_LOCK_DIR``, else ``<tmp>/deployer-locks``. The
kernel drops an ``flock`` when its process dies (even ``kill -9``), so a lock can never stay
stuck; the file keeps who held it (PID, host, start, command) for the message a second run
prints, and a record left by a process that is gone is reported as a stale lock taken over.
Across machines the orchestrator must serialize (see README, Ansible).
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import hashlib
import json
import os
import socket
import sys
import tempfile
import time
from dataclasses import dataclass
from typing import Any

from ..errors import Locked as Locked  # importable from here as before

ENV = "DEPLOYER_LOCK_DIR"


def lock_dir() -> str:
    return os.environ.get(ENV) or os.path.join(tempfile.gettempdir(), "deployer-locks")


def device_key(bus: str, unit: int) -> str:
    """The device's identity: its bus (serial path after symlinks, host:port) and unit id."""
    return f"{bus}#unit{unit}"


@dataclass
class DeviceLock:
    key: str
    path: str
    fd: int
    stale: str | None = None  # a warning when a dead process's record was taken over
    shared: bool = False

    def release(self) -> None:
        if self.fd < 0:
            return
        if not self.shared:
            with contextlib.suppress(OSError):
                os.ftruncate(self.fd, 0)  # a clean release leaves no record to call stale
        with contextlib.suppress(OSError):
            fcntl.flock(self.fd, fcntl.LOCK_UN)
        os.close(self.fd)
        self.fd = -1


def _holder_text(record: dict[str, Any]) -> str:
    since = record.get("since")
    when = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(since)) if isinstance(since, int | float) else "?"
    what = f" ({record['command']})" if record.get("command") else ""
    return f"PID {record.get('pid', '?')} on {record.get('host', '?')} since {when}{what}"


def _read_record(fd: int) -> dict[str, Any]:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        data = os.read(fd, 4096)
        rec = json.loads(data) if data.strip() else {}
        return rec if isinstance(rec, dict) else {}
    except (OSError, ValueError):
        return {}


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this machine (someone else's counts: it is alive)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's process, alive
    return True


_ready: set[str] = set()  # lock directories made and opened to every user by this process


def _directory(d: str) -> None:
    if d in _ready:
        return
    try:
        os.makedirs(d, exist_ok=True)
        # every user's runs share the directory (sticky, like /tmp)
        if os.stat(d).st_uid == os.getuid():
            os.chmod(d, 0o1777)
    except OSError as e:
        raise Locked(f"cannot use the lock directory {d}: {e.strerror} (set {ENV} to another folder)",
                     busy=False) from None
    _ready.add(d)


def try_lock(key: str, *, command: str = "", directory: str | None = None, shared: bool = False) -> DeviceLock:
    """Take the lock now or raise Locked naming the holder.

    ``shared``: many holders at once (the bus lock of runs writing single units); an exclusive holder
    (a broadcast to the whole bus) excludes them all. Shared holders leave no record.
    """
    d = directory or lock_dir()
    _directory(d)
    name = hashlib.sha256(key.encode()).hexdigest()[:24] + ".lock"
    path = os.path.join(d, name)
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError as e:
        raise Locked(f"cannot open the lock file {path}: {e.strerror}", busy=False) from None
    try:
        fcntl.flock(fd, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
    except BlockingIOError:
        record = _read_record(fd)
        os.close(fd)
        if not record:  # held shared: runs writing devices of this bus, one by one
            raise Locked("the bus is in use: another run is writing a device on it") from None
        raise Locked(f"locked by {_holder_text(record)}") from None
    except OSError as e:
        os.close(fd)
        raise Locked(f"cannot lock {path}: {e.strerror}", busy=False) from None
    if shared:
        return DeviceLock(key, path, fd, None, shared=True)
    old = _read_record(fd)
    stale = None
    host = socket.gethostname()
    if old.get("pid") and old.get("host") == host and old.get("pid") != os.getpid():
        pid = old["pid"]
        if isinstance(pid, int) and not pid_alive(pid):
            stale = f"took over a stale lock of {_holder_text(old)}: that process is gone (it did not finish)"
    record = {"pid": os.getpid(), "host": host, "since": time.time(), "key": key, "command": command}
    os.ftruncate(fd, 0)
    os.lseek(fd, 0, os.SEEK_SET)
    os.write(fd, json.dumps(record).encode())
    return DeviceLock(key, path, fd, stale)


async def acquire(key: str, *, timeout: float = 0.0, command: str = "", directory: str | None = None,
                  poll: float = 0.1, shared: bool = False) -> DeviceLock:
    """One lock; waits up to ``timeout`` seconds (0: fail at once). Raises Locked."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return try_lock(key, command=command, directory=directory, shared=shared)
        except Locked as e:
            if time.monotonic() >= deadline or not e.busy:
                if timeout > 0 and e.busy:
                    raise Locked(f"{e}; still locked after waiting {timeout:g} s") from None
                raise
        await asyncio.sleep(poll)


async def acquire_device(bus: str, unit: int, *, timeout: float = 0.0, command: str = "",
                         directory: str | None = None) -> list[DeviceLock]:
    """The locks a run writing ``unit`` on ``bus`` holds: the bus's, shared, then the unit's, exclusive.

    A broadcast (unit 0) writes every unit of the bus: it takes the bus's lock exclusively, so it waits
    for (or is refused by) any run writing a unit there, and they for it. Always bus first, then unit:
    two runs can never hold one each and wait for the other.
    """
    start = time.monotonic()
    bus_lock = await acquire(f"{bus}#bus", timeout=timeout, command=command, directory=directory, shared=unit != 0)
    if unit == 0:
        return [bus_lock]
    try:
        left = max(0.0, timeout - (time.monotonic() - start))
        return [bus_lock, await acquire(device_key(bus, unit), timeout=left, command=command, directory=directory)]
    except BaseException:
        bus_lock.release()
        raise


def command_line() -> str:
    return " ".join(os.path.basename(a) if i == 0 else a for i, a in enumerate(sys.argv))[:200]
