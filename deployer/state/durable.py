"""Group commit: new files (snapshots) and journal lines made durable by one writer thread.

A fleet of 128 devices in flight used to send three jobs per device to asyncio's small thread
pool (the snapshot with its file and folder fsync, then the journal's "device-started" and
"device-finished" lines, each fsync'ed on its own): devices queued behind each other's fsyncs
for 50-100 ms each. Here one thread takes everything pending at once and makes it durable with
as few fsyncs as the guarantees allow: the new files' text appended to the write-ahead log of
their folder (``state.wal``) with one write and one fsync, then the lines for each journal file
appended with one write and one fsync. Once batches have company (a fleet), the writer waits
``GATHER`` for more before each one, so they grow. A caller's future completes only after the fsync covering
its own data, so "the snapshot is on disk before the first write" and "device-started is on disk
before the first write" hold per device; within one batch the files are durable before any line
naming them. The files themselves are fsync'ed when the log is settled (``settled``: a run's end).
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import errno
import hashlib
import json
import os
import secrets
import stat
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from .. import portable
from ..errors import UsageError
from ..portable import O_BINARY, O_CLOEXEC, O_NOFOLLOW, write_all, writev_all
from . import oslock, wal

# once a batch had company (a fleet: many devices waiting), the writer waits this long for more before it commits:
# every batch costs two fsyncs (the log, the journal) and the system calls around them, each a moment a worker's
# event loop may wait for the GIL. At --parallel 256 a worker's batches grew from 3-6 operations to 7-10, half the
# fsyncs (benchmarks/RESULTS.md, run L); a device waits up to this much longer for its snapshot, against Modbus
# round trips of tens of milliseconds. A lone operation (one device) never waits.
GATHER = 0.002


@dataclass
class NewFile:
    """A file that must not exist yet (O_EXCL), with its text; ``line``: a journal record naming it.

    ``paths`` yields the candidate paths in order (the next one after a name collision); ``text``
    renders the content for a path (the text may mention its own path).
    """

    paths: Iterator[str]
    text: Callable[[str], str]
    first: tuple[str, str]  # the first candidate and its text, rendered by the caller
    journal: str | None = None  # the journal file that gets ``line`` once the file is durable
    line: dict[str, Any] | None = None  # its "path" key is set to the file's final path
    path_key: str = "snapshot"
    digest: str | None = None  # set once written: the SHA-256 of the file's bytes


@dataclass
class Settle:
    """Settle the write-ahead log: every new file logged so far fsync'ed, then the log removed."""


@dataclass
class Line:
    """One JSON line for a journal file (appended, fsync'ed)."""

    journal: str
    record: dict[str, Any]


@dataclass(eq=False)
class _Pending:
    op: NewFile | Line | Settle
    path: str | None = None  # a NewFile's final path
    digest: str | None = None  # the SHA-256 of a NewFile's bytes (the journal line names it: edits show)
    data: bytes | None = None  # its journal line as written, encoded by the caller (see ``submit``)
    record: list[bytes] | None = None  # a NewFile's write-ahead log record (``wal.record``: pieces, its bytes
    # among them), made with the file
    error: BaseException | None = None
    finished: bool = False
    # who waits: a future of an event loop (resolved there, a whole batch per wake-up), else a thread
    waiter: asyncio.Future[str | None] | None = None
    event: threading.Event | None = None

    def outcome(self) -> str | None:
        """Once committed: the NewFile's final path (None for a Line), or the error that was its own."""
        if self.error is not None:
            raise self.error
        return self.path


class GroupCommit:
    """One writer thread, started on first use; ``submit`` queues an operation and returns it.

    The thread only makes system calls on bytes the callers prepared (the files created and written,
    the journal lines encoded) and wakes each event loop once per batch: any Python work it does holds
    the GIL, and a busy event loop coming back from a system call of its own waited for it (in a fleet
    of 10,000 devices a create of a lock file took 190 us where 40 us were the file system's)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._queue: list[_Pending] = []
        self._thread: threading.Thread | None = None
        self._log = wal.Log()  # the writer thread's own

    def submit(self, p: _Pending) -> _Pending:
        """Queue ``p``; a NewFile is created and written here, and every journal line encoded, by the caller
        (OSError, TypeError: nothing queued)."""
        op = p.op
        if isinstance(op, NewFile):
            _create(p)
            if op.journal is not None and op.line is not None:
                p.data = _line({**op.line, op.path_key: p.path, f"{op.path_key}_sha256": p.digest})
        elif isinstance(op, Line):
            p.data = _line(op.record)
        with self._cond:
            self._queue.append(p)
            if self._thread is None or not self._thread.is_alive():
                # a daemon: it only ever waits for work when idle, and every caller waits for its own operation
                self._thread = threading.Thread(target=self._loop, name="deployer-group-commit", daemon=True)
                self._thread.start()
            if len(self._queue) == 1:  # more in the queue: the thread was woken already
                self._cond.notify()
        return p

    def logged(self) -> bool:
        """Whether the writer holds a write-ahead log not settled yet."""
        return self._log.pending()

    def _loop(self) -> None:
        crowded = False  # the last batch held more than one operation
        while True:
            with self._cond:
                while not self._queue:
                    if self._log.pending():  # settled once nothing came for a while (a process that lives on)
                        if not self._cond.wait(wal.IDLE) and not self._queue:
                            break
                    else:
                        self._cond.wait()
            if crowded:
                time.sleep(GATHER)  # the others' operations join this batch (the waiters wait a little longer)
            with self._cond:
                batch, self._queue = self._queue, []
            crowded = len(batch) > 1
            try:
                commit(batch, self._log)
                if not batch or any(isinstance(p.op, Settle) for p in batch):
                    self._log.settle()
            except Exception as e:  # a bug must not leave its callers waiting
                for p in batch:
                    if not p.finished:
                        p.error, p.finished = e, True
            _wake(batch)


def _wake(batch: list[_Pending]) -> None:
    """Tell the batch's waiters: each event loop once (one wake-up of its loop), each thread by its event."""
    loops: dict[asyncio.AbstractEventLoop, list[_Pending]] = {}
    for p in batch:
        if p.waiter is not None:
            loops.setdefault(p.waiter.get_loop(), []).append(p)
        elif p.event is not None:
            p.event.set()
    for loop, ps in loops.items():
        with contextlib.suppress(RuntimeError):  # its loop is closed: nobody waits any more
            loop.call_soon_threadsafe(_resolve, ps)


def _resolve(ps: list[_Pending]) -> None:
    """In the waiters' event loop: each one's result (a waiter cancelled meanwhile is done already)."""
    for p in ps:
        w = p.waiter
        if w is not None and not w.done():
            if p.error is not None:
                w.set_exception(p.error)
            else:
                w.set_result(p.path)


def _line(record: dict[str, Any]) -> bytes:
    return (json.dumps(record) + "\n").encode()


def commit(batch: list[_Pending], log: wal.Log | None = None) -> None:
    """Make a batch durable: its files' text in their folders' write-ahead log (one write and one fsync for
    each folder), then the journal lines. Each operation ends ``finished`` with its ``error`` (None: durable);
    ``log``: the writer's (None: one of its own, settled before returning).

    The files are not fsync'ed one by one here, and the whole file system never is (``syncfs``: that flushed
    whatever else was written there too, the lock records, the report stream, any other program's data, so a
    snapshot waited for others' writes; benchmarks/RESULTS.md, run F): their log is one sequential file."""
    failed: dict[int, BaseException] = {}
    own = log is None
    log = wal.Log() if log is None else log
    files = [p for p in batch if isinstance(p.op, NewFile)]
    for p in files:
        if p.path is None:
            _create_or_fail(p, failed)
    folders: dict[str, list[_Pending]] = {}
    for p in files:
        if id(p) not in failed and p.path is not None and p.record is not None:
            folders.setdefault(os.path.dirname(p.path), []).append(p)
    for folder, ps in folders.items():
        try:
            pieces = [b for p in ps if p.record is not None for b in p.record]
            log.append(folder, pieces, [p.path for p in ps if p.path])
        except OSError as e:
            failed.update((id(p), e) for p in ps)
    lines: dict[str, list[_Pending]] = {}
    for p in batch:
        op = p.op
        if id(p) in failed or isinstance(op, Settle):
            continue
        if p.data is None:  # not through ``submit`` (its file created here): encoded now
            try:
                p.data = (
                    _line(op.record)
                    if isinstance(op, Line)
                    else None
                    if op.journal is None or op.line is None
                    else _line({**op.line, op.path_key: p.path, f"{op.path_key}_sha256": p.digest})
                )
            except (TypeError, ValueError) as e:
                failed[id(p)] = e
                continue
        if p.data is not None:
            lines.setdefault(op.journal if isinstance(op, Line) else op.journal or "", []).append(p)
    for path, ps in lines.items():
        try:
            append_bytes(path, [p.data for p in ps if p.data is not None])
        except OSError as e:
            failed.update((id(p), e) for p in ps)
    for p in batch:
        p.error, p.finished = failed.get(id(p)), True
    if own:
        log.settle()


def _create(p: _Pending) -> None:
    """Create a NewFile (never over an existing one; its folder too where it is missing), write its text, close it,
    and encode its log record (the file is fsync'ed when the log is settled)."""
    op = p.op
    assert isinstance(op, NewFile)
    path, text = op.first
    while True:
        try:
            fd = _open_in_folder(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | O_BINARY | O_CLOEXEC)
            break
        except FileExistsError:
            path = next(op.paths)
            text = op.text(path)
    try:
        data = text.encode()
        p.digest = op.digest = hashlib.sha256(data).hexdigest()
        write_all(fd, data)
        p.record = wal.record(path, p.digest, data)
    except OSError:
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(path)  # a partial snapshot must not look like one
        raise
    os.close(fd)
    p.path = path


def _open_in_folder(path: str, flags: int) -> int:
    """``os.open`` of a file to create, its folder made where it is missing: asked of the system only then, since a
    fleet creates a snapshot per device and its writer appends to the journal every batch.

    The folder may appear between the open that failed and the look at it: a fleet's worker processes create
    their first snapshots in a new folder together, and the one that lost the race opens again (it used to fail
    its device: "cannot save the snapshot ...: No such file or directory"). An open that fails again raises."""
    try:
        return os.open(path, flags, 0o644)
    except FileNotFoundError:
        folder = os.path.dirname(path) or "."
        if not os.path.isdir(folder):
            try:
                os.makedirs(folder, exist_ok=True)
            except FileExistsError:  # a file where the folder should be: Windows says "not found" of a path through it
                raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), folder) from None
        return os.open(path, flags, 0o644)


def _create_or_fail(p: _Pending, failed: dict[int, BaseException]) -> None:
    try:
        _create(p)
    except OSError as e:
        failed[id(p)] = e


def _fsync_dir(folder: str) -> None:
    """The folder's entries made durable (POSIX; Windows cannot: ``portable.fsync_dir``); an OSError says
    it was the folder's fsync that failed, not the file's write."""
    try:
        portable.fsync_dir(folder)
    except OSError as e:
        raise OSError(e.errno, f"the fsync of its folder {folder} failed: {e.strerror}") from None


def append_lines(path: str, records: list[dict[str, Any]]) -> None:
    """JSON lines appended with a single write and fsync'ed: concurrent runs never interleave inside a line.

    Every record starts on its own line: when the file does not end with a newline (a line cut by a
    crash or a full disk), a newline goes first, so the torn line costs only itself. The file's lock
    (``state.oslock``) is held from that look to the write: another process's append in flight shows a size
    whose last byte is not yet its newline (Linux grows the file page by page), and a newline added for it
    made an empty line; Windows' appends are a seek and a write, not one step.
    """
    append_bytes(path, [_line(r) for r in records])


def append_bytes(path: str, lines: list[bytes]) -> None:
    """``append_lines`` of lines encoded already (each ending with a newline)."""
    data = b"".join(lines)
    fd = _open_in_folder(path, os.O_RDWR | os.O_APPEND | os.O_CREAT | O_BINARY | O_CLOEXEC)
    try:
        oslock.backend().lock(fd)  # released by the close
        size = os.fstat(fd).st_size
        if size and _byte_at(fd, size - 1) != b"\n":
            data = b"\n" + data
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)


def _byte_at(fd: int, offset: int) -> bytes:
    return portable.pread(fd, 1, offset)  # Windows: a seek; an O_APPEND write goes to the end anyway


# ---- output files: one rule, one atomic write ----------------------------------------------------


class OutputRefused(UsageError):
    """A path deployer will not write to: a link, FIFO, device, folder, or an existing file without --force."""


def check_output(path: str, *, replace: bool = True, what: str = "") -> None:
    """Whether ``path`` may be written, said before any work (and before anything is sent to a device).

    deployer writes only new paths and regular files: a symbolic link, FIFO, device node, socket or
    folder at the path is refused (nothing is opened there, so a FIFO never blocks). An existing
    regular file is replaced only with ``replace`` (reports and plans: yes; exported profiles and
    pages: only with --force). Raises OutputRefused (exit 1).
    """
    name = f"{what} {path}" if what else path
    device = portable.reserved_name(path) if portable.WINDOWS else None
    if device is not None:
        raise OutputRefused(
            f"refusing to write {name}: Windows reserves the name {device} for a device, whatever "
            f"its extension (choose another name)"
        )
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    except OSError as e:
        raise OutputRefused(f"cannot write {name}: {e.strerror}") from None
    kind = _kind(st.st_mode)
    if kind is not None:
        raise OutputRefused(
            f"refusing to write {name}: it is {kind}; deployer writes only regular files (choose another path)"
        )
    if not replace:
        raise OutputRefused(f"{name} exists; pass --force to overwrite it")


def _kind(mode: int) -> str | None:
    """What a path is when it is not a regular file."""
    if stat.S_ISREG(mode):
        return None
    return (
        "a symbolic link"
        if stat.S_ISLNK(mode)
        else "a folder"
        if stat.S_ISDIR(mode)
        else "a FIFO"
        if stat.S_ISFIFO(mode)
        else "a device"
        if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
        else "a socket"
        if stat.S_ISSOCK(mode)
        else "not a regular file"
    )


def disk_error(e: OSError) -> str:
    """An OSError of a state or output file, said plainly."""
    if e.errno == errno.ENOSPC:
        return "the disk is full"
    said = portable.path_error(e) or e.strerror or str(e)
    if portable.WINDOWS and isinstance(e, PermissionError):  # Windows replaces no file another program has open
        said += " (on Windows also when another program has the file open: close the program, or choose another path)"
    return said


def write_atomic(path: str, text: str | bytes | Iterable[bytes], *, replace: bool = True, what: str = "") -> None:
    """The one way deployer writes an output file: whole or not at all, and durable.

    ``check_output``'s rule first (and again right before the rename); then a new temporary file in
    the same folder (which must exist; never following a link), the text written (pieces of bytes, taken as
    they come and written with gathering writes: a big fleet report is never joined in memory), fsync'ed,
    renamed over ``path``, and the folder fsync'ed so the new name survives a crash (POSIX; Windows cannot
    fsync a folder: there the rename is as durable as NTFS's own journal makes it). An existing file keeps
    its permissions.
    Raises OutputRefused for a path it will not write, UsageError when the disk refuses (full, read-only).
    """
    check_output(path, replace=replace, what=what)
    name = f"{what} {path}" if what else path
    directory = os.path.dirname(os.path.abspath(path))
    tmp = ""
    try:
        while True:
            tmp = os.path.join(directory, f".{os.path.basename(path)[:80]}.{secrets.token_hex(4)}.tmp")
            try:
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | O_NOFOLLOW | O_CLOEXEC | O_BINARY, 0o666)
                break
            except FileExistsError:
                continue
        try:
            with contextlib.suppress(FileNotFoundError):
                portable.fchmod(fd, stat.S_IMODE(os.stat(path, follow_symlinks=False).st_mode))
            if isinstance(text, str):
                write_all(fd, text.encode())
            elif isinstance(text, bytes):
                write_all(fd, text)
            else:
                _write_pieces(fd, text)
            os.fsync(fd)
        finally:
            os.close(fd)
        check_output(path, replace=replace, what=what)  # nobody planted anything meanwhile
        portable.replace(tmp, path)  # Windows: retried while a reader holds ``path`` open
        tmp = ""
        _fsync_dir(directory)
    except OSError as e:
        raise UsageError(f"cannot write {name}: {disk_error(e)}") from None
    finally:
        if tmp:
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def _write_pieces(fd: int, pieces: Iterable[bytes]) -> None:
    """Pieces as they come (an iterator may produce them as it goes), gathered into writes of about 1 MB."""
    batch: list[bytes] = []
    size = 0
    for piece in pieces:
        batch.append(piece)
        size += len(piece)
        if size >= 1 << 20:
            writev_all(fd, batch)
            batch, size = [], 0
    if batch:
        writev_all(fd, batch)


_WRITER = GroupCommit()


def _writer_after_fork() -> None:
    """A forked worker (``fleet.workers``) has no writer thread, and what its parent had queued is its parent's:
    a writer of its own."""
    global _WRITER
    _WRITER = GroupCommit()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_writer_after_fork)


def _at_exit() -> None:
    """What the writer logged and did not settle (no run's end settled it: ``apply_device`` called on its own)
    is settled before the process ends, so no log is left for the next process to recover."""
    if _WRITER.logged():
        durable_now(Settle())


atexit.register(_at_exit)


async def durable(op: NewFile | Line) -> str | None:
    """Wait until ``op`` is on disk (with whatever else was pending); a NewFile's final path."""
    return await queue(op)


async def settled() -> None:
    """Wait until every new file written so far is fsync'ed itself and its write-ahead log is removed (a run's
    end: its snapshot files then need no log). A file or folder that cannot be fsync'ed leaves its log on disk,
    for ``wal.recover``: nothing is lost, so nothing is raised."""
    await queue(Settle())


def durable_now(op: NewFile | Line | Settle) -> str | None:
    """The same, from synchronous code (no event loop)."""
    p = _Pending(op, event=threading.Event())
    _WRITER.submit(p)
    assert p.event is not None
    p.event.wait()
    return p.outcome()


def queue(op: NewFile | Line | Settle) -> asyncio.Future[str | None]:
    """Queue ``op`` now and hand back its wait, to be awaited later (a fleet device frees its slot first).
    Cancelling the wait does not stop the operation: the writer finishes it."""
    p = _Pending(op, waiter=asyncio.get_running_loop().create_future())
    _WRITER.submit(p)
    assert p.waiter is not None
    return p.waiter
