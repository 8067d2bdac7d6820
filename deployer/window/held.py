"""A device in its window, and the window's journal lines."""

from __future__ import annotations

import contextlib
import errno
import os
from dataclasses import dataclass, field
from typing import Any

from ..execute.job import Job
from ..execute.session import ApplyOptions
from ..portable import O_BINARY, O_CLOEXEC, O_NOFOLLOW
from ..recipe.loader import Recipe
from ..report import DeviceResult
from ..state import journal
from ..state.durable import append_lines, disk_error
from ..state.lock import DeviceLock
from ..transport import clients as tp


@dataclass(frozen=True)
class Written:
    """A device whose change is verified and waits: for its soak, its commit or the run's confirmation."""

    job: Job
    result: DeviceResult
    locks: list[DeviceLock] = field(default_factory=list)  # the device's, kept from the write to the window's end

    @property
    def name(self) -> str:
        return self.job.name

    @property
    def recipe(self) -> Recipe:
        return self.job.recipe

    @property
    def url(self) -> tp.DeviceURL:
        return self.job.url

    @property
    def unit(self) -> int:
        return self.job.unit


def needs_soak(r: DeviceResult) -> bool:
    """Something was written and verified (a device with nothing to write has nothing to watch or undo)."""
    return r.status == "ok" and r.snapshot is not None


def pending_path(state_dir: str, run: str) -> str:
    """The report of a run that waits for its confirmation (what ``status`` points a rollback at)."""
    return os.path.join(os.path.abspath(state_dir), "pending", f"{run}.json")


RESERVE = 256 * 1024  # bytes kept free for a window's journal lines: hundreds of lines, even on a full disk


def reserve_path(state_dir: str, run: str) -> str:
    return os.path.join(os.path.abspath(state_dir), f".reserve-{run}")


def reserve(options: ApplyOptions) -> None:
    """Set disk space aside in the state folder for the window's journal lines (a rollback must be recorded even
    when the disk fills up meanwhile); ``record`` gives it back when the disk is full. Best effort: a folder
    that cannot take it now is what ``record`` will report."""
    if options.run_id is None:
        return
    path = reserve_path(options.state_dir, options.run_id)
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | O_NOFOLLOW | O_CLOEXEC | O_BINARY, 0o600)
        try:
            if hasattr(os, "posix_fallocate"):
                os.posix_fallocate(fd, 0, RESERVE)
            else:  # written out: the blocks are taken either way
                os.write(fd, bytes(RESERVE))
        finally:
            os.close(fd)


def unreserve(options: ApplyOptions) -> bool:
    """Give the reserved space back; whether there was any."""
    if options.run_id is None:
        return False
    try:
        os.remove(reserve_path(options.state_dir, options.run_id))
    except OSError:
        return False
    return True


def record(options: ApplyOptions, line: dict[str, Any], *results: DeviceResult) -> bool:
    """Append a window's journal line. A full disk gets the reserved space (``reserve``) and one more try;
    a line that still cannot be written never stops the window (a rollback goes on): each of ``results``
    says what could not be recorded (the run exits 4). Whether it was written."""
    path = journal.path_of(options.state_dir)
    try:
        append_lines(path, [line])
        return True
    except OSError as e:
        err = e
    if err.errno == errno.ENOSPC and unreserve(options):
        try:
            append_lines(path, [line])
            return True
        except OSError as e:
            err = e
    what = f"the journal {path} could not record the {line.get('event')} line: {disk_error(err)}"
    for r in results:
        r.unrecorded.append(what)
    return False
