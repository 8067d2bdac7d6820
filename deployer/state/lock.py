"""One writer per device on this machine: an exclusive lock per device (URL + unit).

Two runs writing one device at once interleave on the wire: both snapshots record the
original values, one run's values are overwritten a moment after it verified them, and either
rollback restores the wrong state. So apply, rollback and fleet runs take the device's lock
before their first read and hold it until the read-back is done.

The lock is an OS file lock (``state.oslock``: ``flock`` on POSIX, ``LockFileEx`` on Windows) on a
file in a directory every run on this machine shares, whatever its working or state directory:
``$DEPLOYER_LOCK_DIR``, else a fixed folder per system (``lock_dir``): ``/tmp/deployer-locks`` on
POSIX, ``%ProgramData%\\deployer\\locks`` on Windows, never $TMPDIR, which differs between a login
shell, a service and macOS users, so they would not see each other's locks. The system drops such
a lock when its process dies (even ``kill -9``), so a lock can never stay stuck; the file keeps who
held it (PID, host, start, command) for the message a second run prints, and a record left by a
process that is gone is reported as a stale lock taken over.
Across machines the orchestrator must serialize (docs/ansible.md).

A site agent's ownership does not depend on the lock folder (``owner_dir``, docs/locks.md): processes given
different folders never see each other's locks, so the agent also marks each device it owns in a folder no
setting moves (an exclusive mark per unit, its address in the record), and every run holds a shared mark on
each unit it writes beside its lock. The agent's mark refuses the run; the run's mark keeps an agent from
taking the device while it is being written.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import functools
import hashlib
import json
import os
import stat
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from .. import portable
from ..errors import Locked
from . import holder, oslock

ENV = "DEPLOYER_LOCK_DIR"

# a site agent (``deployer agent``) holds its devices' locks for as long as it runs: its address goes into
# each record it writes (so another run is told where to go instead), and the keys it holds are not taken
# again by its own runs (a second flock of the same file by this process would refuse itself)
_agent: dict[str, str] = {}
_owned: dict[str, DeviceLock] = {}
_owned_marks: dict[str, DeviceLock] = {}  # the agent's marks in owner_dir, by key (the same keys as _owned)


def set_agent(address: str | None) -> None:
    """This process is the agent at ``address`` (None: it is not): lock records it writes carry the address."""
    if address is None:
        _agent.clear()
    else:
        _agent["address"] = address


def hold(locks: Sequence[DeviceLock]) -> None:
    """Keep ``locks`` for this process's lifetime: its runs use them instead of taking them again."""
    for h in locks:
        (_owned_marks if h.mark else _owned)[h.key] = h


def let_go(keys: Sequence[str]) -> None:
    """Release held locks and marks (the agent stops owning a device)."""
    for k in keys:
        for table in (_owned, _owned_marks):
            h = table.pop(k, None)
            if h is not None:
                h.release()


def held(key: str) -> bool:
    return key in _owned


def default_lock_dir() -> str:
    """The folder every run on this machine shares when $DEPLOYER_LOCK_DIR is not set."""
    if os.name == "nt":
        return os.path.join(os.environ.get("PROGRAMDATA") or r"C:\ProgramData", "deployer", "locks")
    return "/tmp/deployer-locks"


def lock_dir() -> str:
    return os.environ.get(ENV) or default_lock_dir()


@functools.cache  # asked per device of a fleet; a process's answer does not change
def owner_dir() -> str:
    """Where agents mark the devices they own and runs the units they write, whatever each one's lock folder:
    a fixed folder no setting moves. Linux: /dev/shm, which a systemd service shares with every other process
    (its private /tmp and read-only file system do not reach /dev), else /tmp; Windows: %ProgramData%."""
    if os.name == "nt":
        return os.path.join(os.environ.get("PROGRAMDATA") or r"C:\ProgramData", "deployer", "owners")
    if sys.platform.startswith("linux") and os.access("/dev/shm", os.W_OK | os.X_OK):
        return "/dev/shm/deployer-owners"
    return "/tmp/deployer-owners"


def same_folder(a: str, b: str) -> bool:
    return os.path.normcase(os.path.abspath(a)) == os.path.normcase(os.path.abspath(b))


def run_marks(buses: Sequence[str], unit: int, directory: str | None = None) -> list[DeviceLock]:
    """The marks a run holds beside its locks (in ``directory``): a shared one on each unit it writes, an exclusive
    one on each bus for a broadcast. Raises Locked (nothing sent) when a site agent owns the device, whatever
    lock folder it was given. None needed where the lock folder is the owners' folder (the locks are the marks),
    nor for a device this process (the agent) owns."""
    d = owner_dir()
    if same_folder(directory or lock_dir(), d):
        return []
    keys = sorted(set(buses))
    wanted = [(f"{b}#bus", False) for b in keys] if unit == 0 else [(device_key(b, unit), True) for b in keys]
    if any(k in _owned for k, _ in wanted):
        return []

    def why(key: str, e: Locked) -> Locked:
        if unit == 0 and e.busy:  # units of the bus are owned (or written) by others: say by whom
            return Locked(_bus_users(key[: -len("#bus")], d) or str(e), busy=False)
        return e

    return _marks(wanted, command_line(), why, d)


def agent_marks(buses: Sequence[str], unit: int) -> list[DeviceLock]:
    """The site agent's marks of a device it owns: each bus shared, each unit exclusive with its record (the
    agent's address), in ``owner_dir``; none when its lock folder is that folder. Raises Locked when a run holds
    the unit now (the agent tries again at its next check)."""
    d = owner_dir()
    if same_folder(lock_dir(), d):
        return []
    keys = sorted(set(buses))
    return _marks(
        [(f"{b}#bus", True) for b in keys] + [(device_key(b, unit), False) for b in keys],
        "deployer agent",
        lambda _key, e: Locked(f"a run on this machine is writing it (its mark in {d}): {e}", busy=e.busy),
        d,
    )


def _marks(
    wanted: Sequence[tuple[str, bool]], command: str, why: Callable[[str, Locked], Locked], d: str
) -> list[DeviceLock]:
    """Each mark of ``wanted`` ((key, shared) in ``d``, the owners' folder), or none: ``why(key, refusal)`` is
    raised."""
    held: list[DeviceLock] = []
    try:
        for key, shared in wanted:
            try:
                h = try_lock(key, command=command, directory=d, shared=shared)
            except Locked as e:
                raise why(key, e) from None
            h.mark = True
            held.append(h)
        return held
    except BaseException:
        for h in reversed(held):
            h.release()
        raise


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
    record: dict[str, Any] | None = None  # what the file says about us (exclusive holders only)
    size: int = 0  # the file's length: what a new record or the release writes over
    mark: bool = False  # in owner_dir: a run's or an agent's mark of the device, beside its lock

    def in_window(self, window: str, deadline: float | None) -> None:
        """Say in the lock file that a safe-change window keeps this lock (``soak``/``confirm``) until ``deadline``
        (time.time()): a run refused meanwhile names the window and when it ends."""
        if self.fd < 0 or self.record is None:
            return
        self.record = holder.in_window(self.record, window, deadline)
        with contextlib.suppress(OSError):  # the record is for messages; the lock itself holds regardless
            self.size = _write_record(self.fd, self.record, self.size)

    def release(self) -> None:
        """Unlock; an exclusive holder first blanks its record (a clean release leaves none to call stale).

        The file stays for the next run of this device: a fleet that created and removed two files per
        device spent most of its system time in the file system's inode allocation, which skips every inode
        freed in the last minutes (ext4's ``recently_deleted``: quadratic in the devices of a run). An older
        deployer removes it on release; ``try_lock`` opens the path again when its file went meanwhile.
        The record is overwritten with spaces, never truncated: a change of the file's size waits for the file
        system's journal, which a busy fleet commits every few milliseconds (15% of a worker's time went there).
        Positioned reads and writes: a fleet takes two locks per device, and every system call of a worker is a
        moment its other threads may take the GIL from it (benchmarks/RESULTS.md, run L).
        """
        if self.fd < 0:
            return
        backend = oslock.backend()
        if not self.shared and self.size:
            with contextlib.suppress(OSError):
                portable.pwrite_all(self.fd, b" " * self.size, 0)
        # a mark's file goes with its last holder, removed under an exclusive lock so that whoever opened it meanwhile
        # finds it nameless (_checked): one held exclusively, or a shared one turned exclusive (flock converts the lock
        # of the same open file; refused, it may drop ours, which we let go of anyway). Five system calls a device of
        # a fleet, where unlocking and opening the file again to lock it took eight. Windows removes no open file.
        here = self.mark and not portable.WINDOWS and (not self.shared or backend.name == "flock")
        if here:
            with contextlib.suppress(OSError):
                if (not self.shared or backend.try_lock(self.fd)) and _alone(self.fd):
                    _remove(self.path)
        with contextlib.suppress(OSError):
            backend.unlock(self.fd)
        os.close(self.fd)
        self.fd = -1
        if self.mark and not here:  # Windows (ours closed first), or a shared mark without flock's conversion
            _remove_unheld(self.path)


_holder_text = holder.describe


def _remove(path: str) -> None:
    # a mark's file goes with its last holder: the owners' folder (in RAM on Linux) keeps no file per device ever
    # written, which the lock folder does for speed on disk (a file system's inode allocation, DeviceLock.release).
    # Windows removes no file a process has open: the file then stays, which is harmless.
    with contextlib.suppress(OSError):
        os.remove(path)


def _remove_unheld(path: str) -> None:
    """Remove a mark's file if nobody holds it now (taken exclusively for the moment of the removal)."""
    try:
        fd = portable.open_nofollow(path, os.O_RDWR | portable.O_NONBLOCK | portable.O_CLOEXEC | portable.O_BINARY)
    except OSError:
        return
    try:
        if oslock.backend().try_lock(fd) and _alone(fd):
            if portable.WINDOWS:  # removes no open file: closed first; one opened meanwhile stays (its removal fails)
                os.close(fd)
                fd = -1
            _remove(path)
    except OSError:
        pass
    finally:
        if fd >= 0:
            os.close(fd)


def _alone(fd: int) -> bool:
    """Whether the (locked) file is a plain one with one name: still the one at its path, removable as ours."""
    st = os.fstat(fd)
    return stat.S_ISREG(st.st_mode) and st.st_nlink == 1


def _read_record(fd: int) -> dict[str, Any]:
    return _read(fd)[0]


def _read(fd: int) -> tuple[dict[str, Any], int]:
    """The file's record ({} when blank or none) and its length in bytes."""
    try:
        data = portable.pread(fd, 65536, 0)
    except OSError:
        return {}, 0
    return holder.parse(data), len(data)


def _write_record(fd: int, record: dict[str, Any], size: int) -> int:
    """Write ``record`` over what the file holds (``size`` bytes), padded with spaces where it is shorter (JSON
    allows them after a value; a file of spaces is no record); the file's length after it.

    The file's size never shrinks: a truncation waits for the file system's journal (and one to zero makes
    ext4 write the file out at its close: 0.3 ms a device)."""
    data = json.dumps(record).encode()
    portable.pwrite_all(fd, data + b" " * (size - len(data)) if size > len(data) else data, 0)
    return max(size, len(data))


def pid_alive(pid: int, start: float | None = None) -> bool:
    """Whether process ``pid`` exists on this machine (someone else's counts: it is alive) and, with ``start``,
    is the process that started then (``holder.process_start``), not a later one given the same PID."""
    return holder.process_alive(pid, start)


_ready: set[str] = set()  # lock directories made and checked by this process


def _directory(d: str) -> None:
    """Make the folder, or check one that is there: every user's runs share it, so it must be a real
    folder (not a link), and if others may write in it, sticky (like /tmp: nobody removes or replaces
    another user's lock files). Windows has no sticky bit and no modes to check: there the folder's
    ACL decides (docs/windows.md)."""
    if d in _ready:
        return
    try:
        os.makedirs(d, exist_ok=True)
        st = os.lstat(d)
        if portable.owner_is_me(st) and stat.S_ISDIR(st.st_mode):
            os.chmod(d, 0o1777)  # every user's runs share it
            st = os.lstat(d)
    except OSError as e:
        raise Locked(
            f"cannot use the lock directory {d}: {e.strerror} (set {ENV} to another folder)", busy=False
        ) from None
    if not stat.S_ISDIR(st.st_mode) or portable.is_link(st):
        what = "a symbolic link" if portable.is_link(st) else "not a folder"
        raise Locked(
            f"cannot use the lock directory {d}: it is {what} (a lock folder must be a real folder; "
            f"set {ENV} to another folder)",
            busy=False,
        )
    if portable.has_modes() and st.st_mode & 0o022 and not st.st_mode & stat.S_ISVTX:
        raise Locked(
            f"cannot use the lock directory {d}: others may write in it but it is not sticky, so they could "
            f"replace lock files (chmod 1777 {d}, or set {ENV} to another folder)",
            busy=False,
        )
    _ready.add(d)


def _open(path: str) -> int:
    """The lock file, opened without following a link (``_checked`` says whether it may be used).

    The folder is shared and the names predictable: a planted symlink is never opened, and a FIFO never
    blocks the open. Windows has no O_NOFOLLOW: ``portable.open_nofollow`` checks the path before and after
    opening instead.
    """
    try:
        return portable.open_nofollow(
            path, os.O_RDWR | os.O_CREAT | portable.O_NONBLOCK | portable.O_CLOEXEC | portable.O_BINARY, 0o666
        )
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise Locked(
                f"refusing the lock file {path}: it is a symbolic link (planted? remove it)", busy=False
            ) from None
        hint = (
            " (on Windows every account whose runs share the lock folder needs the right to modify files "
            "there: see docs/windows.md)"
            if portable.WINDOWS and isinstance(e, PermissionError)
            else ""
        )
        raise Locked(f"cannot open the lock file {path}: {e.strerror}{hint}", busy=False) from None


def _checked(fd: int, path: str) -> bool:
    """Whether the locked file is the one at the path (False: removed since it was opened, so its lock holds
    nothing; the caller opens the path again); refused (closed, Locked) unless it is a plain file of its own.

    Asked of the file itself once it is locked: one ``fstat`` tells both. A file removed or replaced has no name
    left (``st_nlink`` 0: its holder removed it at its release, as an older deployer does); a planted hard link to
    another file (a root run would write over it) has two, and a FIFO or device is not a regular file: neither is
    ever read or written. (A fleet takes two locks per device: the path's own ``stat`` was one system call more
    per lock, and every system call beside a worker's event loop lets its other thread take the GIL.)
    """
    st = os.fstat(fd)
    if st.st_nlink == 0 and stat.S_ISREG(st.st_mode):
        return False
    why = (
        "not a regular file"
        if not stat.S_ISREG(st.st_mode)
        else f"it has {st.st_nlink} names (a hard link to another file?)"
        if st.st_nlink != 1
        else None
    )
    if why is not None:
        os.close(fd)
        raise Locked(f"refusing the lock file {path}: {why}; remove it", busy=False)
    if portable.owner_is_me(st) and stat.S_IMODE(st.st_mode) != 0o666:
        with contextlib.suppress(OSError):
            portable.fchmod(fd, 0o666)  # other users' runs lock (and record in) it too, whatever our umask
    return True


def try_lock(
    key: str, *, command: str = "", directory: str | None = None, shared: bool = False, run: str | None = None
) -> DeviceLock:
    """Take the lock now or raise Locked naming the holder.

    ``shared``: many holders at once (the bus lock of runs writing single units); an exclusive holder
    (a broadcast to the whole bus) excludes them all. Shared holders leave no record.
    """
    d = directory or lock_dir()
    _directory(d)
    name = hashlib.sha256(key.encode()).hexdigest()[:24] + ".lock"
    path = os.path.join(d, name)
    while True:
        fd = _open(path)
        try:
            got = oslock.backend().try_lock(fd, shared=shared)
        except OSError as e:
            os.close(fd)
            raise Locked(f"cannot lock {path}: {e.strerror}", busy=False) from None
        if not _checked(fd, path):
            os.close(fd)  # its holder removed it (meanwhile, or while holding it): the file now at the path
            continue
        if not got:
            record = _read_record(fd)
            os.close(fd)
            if not record:  # held shared: runs writing devices of this bus, one by one
                raise Locked("the bus is in use: another run is writing a device on it") from None
            if record.get("agent"):  # waiting does not help: the agent holds it until it stops
                a = record["agent"]
                raise Locked(
                    f"owned by the deployer agent at {a} (PID {record.get('pid', '?')}): run it through the "
                    f"agent (deployer apply --agent {a} ...), or stop the agent",
                    busy=False,
                ) from None
            raise Locked(f"locked by {_holder_text(record)}") from None
        break
    if shared:
        return DeviceLock(key, path, fd, None, shared=True)
    old, size = _read(fd)
    stale = None
    record = holder.new(key, command=command, run=run, agent=_agent.get("address"))
    if old.get("pid") and old.get("host") == record["host"] and old.get("pid") != os.getpid():
        pid, start = old["pid"], old.get("pid_start")
        if isinstance(pid, int) and not pid_alive(pid, start if isinstance(start, int | float) else None):
            stale = f"took over a stale lock of {_holder_text(old)}: that process is gone (it did not finish)"
    size = _write_record(fd, record, size)
    return DeviceLock(key, path, fd, stale, record=record, size=size)


async def acquire(
    key: str,
    *,
    timeout: float = 0.0,
    command: str = "",
    directory: str | None = None,
    poll: float = 0.1,
    shared: bool = False,
    run: str | None = None,
) -> DeviceLock:
    """One lock; waits up to ``timeout`` seconds (0: fail at once). Raises Locked."""
    if key in _owned:  # this process (the agent) holds it already: nothing to take, nothing to release
        return DeviceLock(key, _owned[key].path, -1, shared=shared)
    deadline = time.monotonic() + timeout
    while True:
        try:
            return try_lock(key, command=command, directory=directory, shared=shared, run=run)
        except Locked as e:
            if time.monotonic() >= deadline or not e.busy:
                if timeout > 0 and e.busy:
                    raise Locked(f"{e}; still locked after waiting {timeout:g} s") from None
                raise
        await asyncio.sleep(poll)


async def acquire_device(
    buses: str | Sequence[str],
    unit: int,
    *,
    timeout: float = 0.0,
    command: str = "",
    directory: str | None = None,
    run: str | None = None,
) -> list[DeviceLock]:
    """The locks a run writing ``unit`` on ``buses`` holds: each bus's, shared, then the unit's, exclusive.

    ``buses``: the device's lock keys (DeviceURL.lock_keys: one per address its host resolves to).
    A broadcast (unit 0) writes every unit of the bus: it takes the bus's lock exclusively, so it waits
    for (or is refused by) any run writing a unit there, and they for it. Always buses first, then units,
    each in sorted order: two runs can never hold one each and wait for the other.
    """
    keys = sorted({buses} if isinstance(buses, str) else set(buses))
    start = time.monotonic()
    held: list[DeviceLock] = []
    try:
        wanted = [(f"{b}#bus", unit != 0) for b in keys]
        wanted += [(device_key(b, unit), False) for b in keys] if unit else []
        for key, shared in wanted:
            left = max(0.0, timeout - (time.monotonic() - start))
            try:
                held.append(
                    await acquire(key, timeout=left, command=command, directory=directory, shared=shared, run=run)
                )
            except Locked as e:
                if unit == 0 and e.busy:
                    who = _bus_users(key[: -len("#bus")], directory)
                    if who is not None:
                        raise Locked(who) from None
                raise
        # wherever its lock folder is: refused when a site agent owns the device (marks, docs/locks.md)
        held += run_marks(keys, unit, directory)
        return held
    except BaseException:
        for h in reversed(held):
            h.release()
        raise


def _bus_users(bus: str, directory: str | None) -> str | None:
    """Who writes units of ``bus`` now (for a refused broadcast): the records of its held unit locks."""
    d = directory or lock_dir()
    who = []
    try:
        names = sorted(os.listdir(d))
    except OSError:
        return None
    for name in names:
        if not name.endswith(".lock"):
            continue
        try:
            fd = portable.open_nofollow(os.path.join(d, name), os.O_RDONLY | portable.O_NONBLOCK | portable.O_BINARY)
        except OSError:
            continue
        try:
            record = _read_record(fd) if stat.S_ISREG(os.fstat(fd).st_mode) else {}
            key = str(record.get("key", ""))
            if not key.startswith(f"{bus}#unit"):
                continue
            try:
                free = oslock.backend().try_lock(fd, shared=True)  # we got it: nobody holds it, an old record
            except OSError:
                free = False
            if not free:
                who.append(f"unit {key.rsplit('#unit', 1)[1]} by {_holder_text(record)}")
        finally:
            os.close(fd)
    return f"the bus is in use: {'; '.join(who)} is being written" if who else None


def command_line() -> str:
    return " ".join(os.path.basename(a) if i == 0 else a for i, a in enumerate(sys.argv))[:200]
