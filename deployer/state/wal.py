"""The write-ahead log of new snapshot files: their text made durable with one fsync per batch.

Each new snapshot used to be fsync'ed on its own before its device's first write, then its folder: in a
fleet at ``--parallel 256`` that was most of the kernel's work per device and most of a device's wait
before its first write (benchmarks/RESULTS.md, run I). Now the group commit (``state.durable``) appends
each new file's path, SHA-256 and text to this process's log segment for the file's folder
(``FOLDER/.wal/SEGMENT.jsonl``) and fsyncs that one file per batch; the snapshot files themselves are
written but not fsync'ed then. The segment is *settled* when its run ends (``durable.settled``), when the
writer has had nothing to do for ``IDLE`` seconds, and at exit: every file it names fsync'ed (a few at a
time, so the file system commits them together), the folder fsync'ed, the segment removed.

A segment is a header line, then one record per file: a JSON line with its path, SHA-256 and size, then the
file's bytes as written, then a newline. The bytes are not escaped into the JSON: the log costs one small
header per file beyond the file itself, and is written from the very buffers the file was written from.

A segment is locked (``state.oslock``) while the process that writes it lives. A segment nobody holds was
left by a process that died before settling it: ``recover`` (run before snapshots are read: at a run's
start, by rollback) restores every file it names that is missing or differs from its record (a crash cut
it), fsyncs the files and their folder, then removes the segment. A record the crash cut was never
acknowledged (its fsync did not return), so no device was written after it: it is skipped.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import re
import secrets
import stat
import threading
import time
from collections.abc import Iterator

from .. import portable
from ..portable import O_BINARY, O_CLOEXEC, O_NOFOLLOW, write_all, writev_all
from . import oslock

FOLDER = ".wal"  # inside the folder of the files it logs (a snapshot folder: STATE/snapshots/.wal)
IDLE = 2.0  # seconds without a batch after which the writer settles what it logged
MAX_BYTES = 64 << 20  # a segment this big is settled at once (a long fleet: the log stays bounded)
FSYNCS_AT_ONCE = 8  # a settle's fsyncs in flight together: the file system commits them as one
_HEADER = "deployer write-ahead log of new files"
_NAME = re.compile(r"^[^./\\][^/\\]*\.yaml$")  # what a record may restore: a snapshot's file name, nothing else


def record(path: str, digest: str, body: bytes) -> list[bytes]:
    """A segment's record of a new file, as pieces to write in order: where it is, the SHA-256 and size of its
    bytes (a JSON line), the bytes, a newline."""
    return [(json.dumps({"path": path, "sha256": digest, "size": len(body)}) + "\n").encode(), body, b"\n"]


def records(data: bytes) -> Iterator[tuple[str, str, bytes]]:
    """The whole records of a segment's text: (path, SHA-256 as recorded, bytes). The first record that is not
    whole (a crash cut it: it was never acknowledged, and nothing was appended after it) ends them."""
    pos = data.find(b"\n") + 1  # after the header line
    while 0 < pos < len(data):
        end = data.find(b"\n", pos)
        if end < 0:
            return
        try:
            head = json.loads(data[pos:end])
            path, digest, size = head["path"], head["sha256"], head["size"]
        except (ValueError, KeyError, TypeError):
            return
        if not (isinstance(path, str) and isinstance(digest, str) and isinstance(size, int) and size >= 0):
            return
        body = data[end + 1 : end + 1 + size]
        if len(body) != size or data[end + 1 + size : end + 2 + size] != b"\n":
            return
        yield path, digest, body
        pos = end + 2 + size


class Segment:
    """This process's log for one folder: created (and its own folder entry made durable) on first use,
    locked while it is open, appended to with one write and one fsync per batch."""

    def __init__(self, folder: str) -> None:
        self.folder = folder
        self.files: list[str] = []  # every file a record names, in order
        self.size = 0
        self.broken = False  # an append failed part way: later batches go to a new segment
        wal = os.path.join(folder, FOLDER)
        for attempt in range(10):
            if not os.path.isdir(wal):
                os.makedirs(wal, exist_ok=True)
                portable.fsync_dir(folder)
            stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
            self.path = os.path.join(wal, f"{stamp}-{os.getpid()}-{secrets.token_hex(4)}.jsonl")
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL | O_BINARY | O_CLOEXEC | O_NOFOLLOW, 0o644)
            except FileExistsError:
                continue
            except FileNotFoundError:  # another process's settle removed the empty folder meanwhile
                if attempt == 9:
                    raise
                continue
            if self._mine(fd):
                break
            os.close(fd)  # another process's recover took it first, as a dead one's: it removes it
        else:
            raise OSError(errno.EEXIST, f"no new log in {wal}")
        try:
            write_all(fd, (json.dumps({"log": _HEADER, "version": 1, "pid": os.getpid()}) + "\n").encode())
            portable.fsync_dir(wal)  # the segment's name; its lines are covered by the append's fsync
        except BaseException:
            os.close(fd)
            with contextlib.suppress(OSError):
                os.unlink(self.path)
            raise
        self.fd = fd

    def _mine(self, fd: int) -> bool:
        """Locked, and still at its path: between the create and the lock, a recover in another process can take
        a new segment for a dead process's (it has no records), remove it and let it go; a lock taken after that
        holds a file nobody would find after a crash."""
        try:
            return oslock.backend().try_lock(fd) and portable.still_at(self.path, os.fstat(fd))
        except OSError:
            return False

    def append(self, pieces: list[bytes], files: list[str]) -> None:
        """The records (``record``'s pieces, in order) on disk, in as few writes as the system allows and one
        fsync; OSError leaves the segment ``broken``."""
        try:
            writev_all(self.fd, pieces)
            os.fsync(self.fd)
        except OSError:
            self.broken = True
            raise
        self.size += sum(len(p) for p in pieces)
        self.files.extend(files)

    def settle(self) -> bool:
        """Fsync every file the segment names, then their folder; remove the segment once they are durable.
        False (the segment left for ``recover``, closed) when a file or the folder could not be fsync'ed."""
        ok = True
        try:
            ok = _fsync_files(self.files)
            if ok:
                portable.fsync_dir(self.folder)
        except OSError:
            ok = False
        _remove(self.path, self.fd, remove=ok)
        self.fd = -1
        if ok:  # nothing pending: the snapshot folder holds only snapshots again (another process's log stays)
            with contextlib.suppress(OSError):
                os.rmdir(os.path.dirname(self.path))
        return ok


class Log:
    """A process's segments, one per folder (the group commit's writer thread is their only user)."""

    def __init__(self) -> None:
        self.segments: dict[str, Segment] = {}
        self.done: list[Segment] = []  # broken: no more appends, settled with the rest
        self.settling: list[threading.Thread] = []  # full segments settled beside the fleet

    def append(self, folder: str, pieces: list[bytes], files: list[str]) -> None:
        seg = self.segments.get(folder)
        if seg is not None and (seg.broken or seg.size >= MAX_BYTES):
            del self.segments[folder]
            if seg.broken:
                self.done.append(seg)
            else:  # a long fleet (about 12,000 snapshots a segment): the next batch does not wait for it
                t = threading.Thread(target=seg.settle, name="deployer-settle", daemon=True)
                try:
                    t.start()
                    self.settling.append(t)
                except RuntimeError:  # the interpreter is shutting down: no new thread
                    seg.settle()
            seg = None
        if seg is None:
            seg = self.segments[folder] = Segment(folder)
        seg.append(pieces, files)

    def pending(self) -> bool:
        return bool(self.segments or self.done or self.settling)

    def settle(self) -> None:
        """Every segment settled (or, when that fails, left for ``recover``)."""
        segs, self.segments, self.done = [*self.done, *self.segments.values()], {}, []
        for seg in segs:
            seg.settle()
        threads, self.settling = self.settling, []
        for t in threads:
            t.join()


def _fsync_files(files: list[str]) -> bool:
    """Each file fsync'ed (even after one failed), by ``FSYNCS_AT_ONCE`` threads, each taking every n-th file: a
    pool's map made a future for each of them at once (2-8 MB in a worker at the end of a big fleet). Where no
    thread may start any more (the exit handler: the interpreter is shutting down), the rest here."""
    n = min(FSYNCS_AT_ONCE, len(files))
    if n <= 1:
        return all([_fsync_file(f) for f in files])
    ok = [True] * n

    def part(i: int) -> None:
        ok[i] = all([_fsync_file(f) for f in files[i::n]])

    started: list[threading.Thread] = []
    for i in range(n):
        t = threading.Thread(target=part, args=(i,), name="deployer-settle", daemon=True)
        try:
            t.start()
        except RuntimeError:
            part(i)
            continue
        started.append(t)
    for t in started:
        t.join()
    return all(ok)


def _fsync_file(path: str) -> bool:
    """A file made durable (opened for writing: Windows' FlushFileBuffers needs it); one that is gone
    (its owner removed it) needs nothing."""
    try:
        fd = os.open(path, os.O_WRONLY | O_BINARY | O_CLOEXEC | O_NOFOLLOW)
    except FileNotFoundError:
        return True
    except OSError:
        return False
    try:
        os.fsync(fd)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


def _remove(path: str, fd: int, *, remove: bool) -> None:
    """Close a segment (its lock goes with it), removing it first where the system allows removing an
    open file (POSIX: so nobody can take it for a dead process's in between), after it elsewhere."""
    if remove and not portable.WINDOWS:
        with contextlib.suppress(OSError):
            os.unlink(path)
    os.close(fd)
    if remove and portable.WINDOWS:
        with contextlib.suppress(OSError):
            os.unlink(path)


def recover(folder: str) -> list[str]:
    """Settle every segment in ``folder``'s log that no living process holds: the files restored from it
    (missing, or cut by a crash). Segments it cannot take or read are left for the next call (OSError only
    when a file cannot be restored: the segment stays)."""
    wal = os.path.join(folder, FOLDER)
    try:
        names = sorted(n for n in os.listdir(wal) if n.endswith(".jsonl"))
    except (FileNotFoundError, NotADirectoryError):
        return []
    restored: list[str] = []
    for name in names:
        path = os.path.join(wal, name)
        try:
            fd = os.open(path, os.O_RDWR | O_BINARY | O_CLOEXEC | O_NOFOLLOW)
        except OSError:
            continue  # settled meanwhile by its owner or by another recover
        try:
            if not oslock.backend().try_lock(fd):
                os.close(fd)
                continue  # its process is alive
            files = _replay(folder, _read_all(fd), restored)
        except BaseException:
            os.close(fd)
            raise
        if not _fsync_files(files):
            os.close(fd)
            raise OSError(errno.EIO, f"cannot make the snapshots of {path} durable")
        portable.fsync_dir(folder)
        _remove(path, fd, remove=True)
    with contextlib.suppress(OSError):
        os.rmdir(wal)  # empty now, unless a living process logs there
    return restored


def _replay(folder: str, data: bytes, restored: list[str]) -> list[str]:
    """Each whole, intact record of a segment's text: its file made what the record says. The files named."""
    files: list[str] = []
    for path, digest, body in records(data):
        if not _NAME.match(os.path.basename(path)) or hashlib.sha256(body).hexdigest() != digest:
            continue
        # the file of this folder the record names (however the folder was reached), never one elsewhere
        path = os.path.join(folder, os.path.basename(path))
        done = _restore(path, body, digest)
        if done is None:
            continue  # a link or folder planted where the snapshot was: never written through
        if done:
            restored.append(path)
        files.append(path)
    return files


def _restore(path: str, body: bytes, digest: str) -> bool | None:
    """The file holds ``body`` afterwards (durably once fsync'ed); True when it had to be written, None when
    something other than a regular file is there."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        st = None
    if st is not None:
        if not stat.S_ISREG(st.st_mode):
            return None
        try:
            with open(path, "rb") as f:
                if hashlib.sha256(f.read()).hexdigest() == digest:
                    return False
        except OSError:
            pass
    tmp = f"{path}.{secrets.token_hex(4)}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | O_BINARY | O_CLOEXEC | O_NOFOLLOW, 0o644)
    try:
        write_all(fd, body)
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    os.close(fd)
    portable.replace(tmp, path)
    return True


def _read_all(fd: int) -> bytes:
    chunks = []
    while chunk := os.read(fd, 1 << 20):
        chunks.append(chunk)
    return b"".join(chunks)
