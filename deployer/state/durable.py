"""Group commit: new files (snapshots) and journal lines made durable by one writer thread.

A fleet of 128 devices in flight used to send three jobs per device to asyncio's small thread
pool (the snapshot with its file and folder fsync, then the journal's "device-started" and
"device-finished" lines, each fsync'ed on its own): devices queued behind each other's fsyncs
for 50-100 ms each. Here one thread takes everything pending at once and makes it durable with
as few fsyncs as the guarantees allow: each new file fsync'ed, each folder that got new files
fsync'ed once, then the lines for each journal file appended with one write and one fsync. A
caller's future completes only after the fsync covering its own data, so "the snapshot is on
disk before the first write" and "device-started is on disk before the first write" hold per
device exactly as before; within one batch the files are durable before any line naming them.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any


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
class Line:
    """One JSON line for a journal file (appended, fsync'ed)."""

    journal: str
    record: dict[str, Any]


@dataclass
class _Pending:
    op: NewFile | Line
    done: Future[str | None] = field(default_factory=Future)
    path: str | None = None  # a NewFile's final path
    digest: str | None = None  # the SHA-256 of a NewFile's bytes (the journal line names it: edits show)
    fd: int = -1


class GroupCommit:
    """One writer thread, started on first use; ``submit`` returns a future per operation."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._queue: list[_Pending] = []
        self._thread: threading.Thread | None = None

    def submit(self, op: NewFile | Line) -> _Pending:
        """Queue ``op``; a NewFile is created and written here, by the caller (OSError: nothing queued),
        so the writer thread only has to fsync it: each call it makes waits for the GIL, which a busy
        event loop holds, and that wait, not the disk, was most of a device's time here."""
        p = _Pending(op)
        if isinstance(op, NewFile):
            _create(p)
        with self._cond:
            self._queue.append(p)
            if self._thread is None or not self._thread.is_alive():
                # a daemon: it only ever waits for work when idle, and every caller waits for its own future
                self._thread = threading.Thread(target=self._loop, name="deployer-group-commit", daemon=True)
                self._thread.start()
            self._cond.notify()
        return p

    def _loop(self) -> None:
        while True:
            with self._cond:
                while not self._queue:
                    self._cond.wait()
                batch, self._queue = self._queue, []
            try:
                commit(batch)
            except Exception as e:  # a bug (say, a record JSON cannot say) must not leave its callers waiting
                for p in batch:
                    if not p.done.done():
                        p.done.set_exception(e)


def commit(batch: list[_Pending]) -> None:
    """Make a batch durable: its files (each fsync'ed), their folders (once each), then the journal lines."""
    failed: dict[int, BaseException] = {}
    files = [p for p in batch if isinstance(p.op, NewFile)]
    for p in files:
        if p.fd < 0:
            _create_or_fail(p, failed)
        if p.fd >= 0:
            try:
                os.fsync(p.fd)
            except OSError as e:
                failed[id(p)] = e
    folders: dict[str, list[_Pending]] = {}
    for p in files:
        if id(p) not in failed and p.path is not None:
            folders.setdefault(os.path.dirname(p.path), []).append(p)
    for folder, ps in folders.items():
        try:
            _fsync_dir(folder)  # the directory entries, or a crash can lose the files
        except OSError as e:
            failed.update((id(p), e) for p in ps)
    lines: dict[str, list[tuple[_Pending, dict[str, Any]]]] = {}
    for p in batch:
        op = p.op
        if id(p) in failed:
            continue
        if isinstance(op, Line):
            lines.setdefault(op.journal, []).append((p, op.record))
        elif op.journal is not None and op.line is not None:
            lines.setdefault(op.journal, []).append((p, {**op.line, op.path_key: p.path,
                                                         f"{op.path_key}_sha256": p.digest}))
    for path, entries in lines.items():
        try:
            append_lines(path, [r for _, r in entries])
        except OSError as e:
            failed.update((id(p), e) for p, _ in entries)
    for p in batch:
        err = failed.get(id(p))
        if err is not None:
            p.done.set_exception(err)
        else:
            p.done.set_result(p.path)


def _create(p: _Pending) -> None:
    """Create a NewFile (never over an existing one) and write its text; the fd stays open for the fsync."""
    op = p.op
    assert isinstance(op, NewFile)
    path, text = op.first
    while True:
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            break
        except FileExistsError:
            path = next(op.paths)
            text = op.text(path)
    try:
        data = text.encode()
        p.digest = op.digest = hashlib.sha256(data).hexdigest()
        while data:
            data = data[os.write(fd, data):]
    except OSError:
        os.close(fd)
        raise
    p.path, p.fd = path, fd


def _create_or_fail(p: _Pending, failed: dict[int, BaseException]) -> None:
    try:
        _create(p)
    except OSError as e:
        failed[id(p)] = e


def _close(p: _Pending) -> None:
    if p.fd >= 0:
        os.close(p.fd)
        p.fd = -1


def _fsync_dir(folder: str) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def append_lines(path: str, records: list[dict[str, Any]]) -> None:
    """JSON lines appended with a single write and fsync'ed: concurrent runs never interleave inside a line."""
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    data = "".join(json.dumps(r) + "\n" for r in records).encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)


_WRITER = GroupCommit()


async def durable(op: NewFile | Line) -> str | None:
    """Wait until ``op`` is on disk (with whatever else was pending); a NewFile's final path."""
    p = _WRITER.submit(op)
    try:
        return await asyncio.wrap_future(p.done)
    finally:
        if p.done.done():
            _close(p)
        else:  # cancelled while the writer may be using the fd: it closes when it is done with it
            p.done.add_done_callback(lambda _: _close(p))


def durable_now(op: NewFile | Line) -> str | None:
    """The same, from synchronous code (no event loop)."""
    p = _WRITER.submit(op)
    try:
        return p.done.result()
    finally:
        _close(p)


def queue(op: Line) -> asyncio.Future[str | None]:
    """Queue a line now and hand back its wait, to be awaited later (a fleet device frees its slot first)."""
    return asyncio.wrap_future(_WRITER.submit(op).done)
