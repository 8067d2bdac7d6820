"""The fleet report file while the run goes on: one line per device appended as it finishes.

During a run the ``--report`` file is a stream (docs/reference/report.md, "The report file while
a fleet runs"): a first line ``{"schema": "deployer.report-stream/3", "recipe": ..., "run": ...}``,
then one small line per selected device (``skipped``, "not finished"), then each device's report
JSON appended as a line of its own when it finishes; a later line for a device replaces an earlier
one (a device that starts writing gets an ``interrupted`` line naming its snapshot; a soak, a
confirmation or ``--rollback-on-failure`` change a finished device later). A writer thread appends
and fsyncs what is pending, so the file is durable a moment after each device, however big the
fleet (the old file was the whole document rewritten 30-45 times). ``report.read_report`` reads a
stream as the document it stands for, so ``deployer report``, ``rollback --from-report`` and
``--limit @FILE`` work on the file of a run that was killed.

At the end the final document is assembled from the stream (each device's last line, in the run's
order, copied in pieces: never every device in memory) into a temporary file that replaces the
stream (``write_atomic``).
"""

from __future__ import annotations

import contextlib
import json
import os
import threading
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, Any

from ..portable import writev_all
from ..report import STREAM_SCHEMA, device_json, parameter_view, report_parts

if TYPE_CHECKING:
    from ..execute.job import Job
    from ..report import DeviceResult, Report


NOT_FINISHED = "not finished (interrupted run)"
WRITING = "interrupted while writing (the run did not finish): some parameters may hold new values"


def profiles_of(jobs: Sequence[Job]) -> dict[str, Any]:
    """The report's ``profiles`` (``report.profiles_json``) from the jobs: each recipe's parameters, once
    per profile (a report is read without opening the files it names)."""
    from ..profile import profile_ref

    out: dict[str, Any] = {}
    seen: set[int] = set()
    for j in jobs:
        if id(j.recipe) in seen:
            continue
        seen.add(id(j.recipe))
        prof = j.recipe.profile
        entry = out.setdefault(profile_ref(prof), {"id": prof.id, "sha256": prof.digest, "parameters": {}})
        for d in j.recipe.desired:
            if d.parameter.name not in entry["parameters"]:
                entry["parameters"][d.parameter.name] = parameter_view(d.parameter)
    return out


def placeholder(job: Job, batch: int | None) -> bytes:
    """A device not finished yet: its line of the stream's first state (no parameters: the journal's
    ``device-started`` line says what recovery needs)."""
    from .rollout import skipped_result

    return device_json(skipped_result(job, NOT_FINISHED, batch, parameters=False))


class LiveReport:
    """The ``--report`` file of a fleet run, readable at every moment, even after a ``kill -9``.

    ``finished``, ``writing`` and ``update`` encode the device's line at once (the caller may drop
    its details afterwards) and hand it to the writer thread; ``close`` assembles the final document.
    """

    def __init__(
        self,
        path: str,
        recipe: str | None,
        jobs: Sequence[Job],
        batches: Sequence[int] | None = None,
        *,
        run: dict[str, Any] | None = None,
    ) -> None:
        from .rollout import batch_numbers

        self.path = path
        self.recipe = recipe
        self.run = run  # who, what, where and when (report.run_info)
        self._order = [j.name for j in jobs]
        self._at: dict[str, tuple[int, int]] = {}  # device -> offset and length of its last line
        self._final: set[str] = set()  # devices whose line is their result (finished, updated)
        self._pending: list[tuple[str, bytes]] = []
        self._cond = threading.Condition()
        self._closing = False
        self._idle = False  # the writer thread waits for lines (notify it), else it pauses or writes
        self._error: OSError | None = None
        self._size = 0
        self.profiles = profiles_of(jobs)
        head = (
            json.dumps({"schema": STREAM_SCHEMA, "recipe": recipe, "run": run, "profiles": self.profiles}).encode()
            + b"\n"
        )
        batch_of = batch_numbers(jobs, batches)
        first: list[tuple[str, bytes]] = [(j.name, placeholder(j, batch_of.get(j.name))) for j in jobs]
        self._fd = self._create(head, first)  # on disk before the first device starts
        self._thread = threading.Thread(target=self._loop, name="deployer-report", daemon=True)
        self._thread.start()

    def _create(self, head: bytes, lines: list[tuple[str, bytes]]) -> int:
        """The stream's first state, written whole to a temporary file and renamed over ``path``
        (``write_atomic``); then kept open for appending."""
        from ..state.durable import write_atomic

        pieces = [head]
        offset = len(head)
        for name, line in lines:
            self._at[name] = (offset, len(line))
            pieces.append(line + b"\n")
            offset += len(line) + 1
        write_atomic(self.path, pieces, what="the report")
        self._size = offset
        return os.open(self.path, os.O_WRONLY | os.O_APPEND | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0))

    def _add(self, name: str, line: bytes, final: bool) -> None:
        with self._cond:
            self._pending.append((name, line))
            if final:
                self._final.add(name)
            if self._idle:  # the writer waits for work (not its pause between writes): wake it
                self._cond.notify()

    def finished(self, result: DeviceResult) -> None:
        self._add(result.name, device_json(result), True)

    def writing(self, result: DeviceResult) -> None:
        """A device's snapshot is on disk and its writes start: until it finishes, its line says
        ``interrupted`` with its snapshot, which is what it is if the run dies now. (The file may lag
        the run: the journal's ``device-started`` line, on disk before the first write, is what
        ``rollback --from-report`` trusts.)"""
        r = result.head()
        r.status = "interrupted"
        r.error = f"{WRITING}; restore it with: deployer rollback {result.snapshot}"
        self._add(result.name, device_json(r), False)

    def update(self, result: DeviceResult) -> None:
        """A finished device changed since (a soak rolled it back, its held commit was sent): its line anew."""
        self._add(result.name, device_json(result), True)

    def _flush(self) -> None:
        """Append what is pending and fsync (the writer thread, and ``stop``)."""
        with self._cond:
            batch, self._pending = self._pending, []
        if not batch or self._fd < 0:
            return
        pieces: list[bytes] = []
        offset = self._size
        at = {}
        for name, line in batch:  # the lines as they are, no copy (this thread holds the GIL while it copies)
            at[name] = (offset, len(line))
            pieces += (line, b"\n")
            offset += len(line) + 1
        try:
            writev_all(self._fd, pieces)
            os.fsync(self._fd)
        except OSError as e:  # the run goes on (the journal has what recovery needs); the lines are kept
            self._error = e  # for the next write, and close() says so if the disk never takes them
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, self._size)  # no line cut short in the middle of the stream
            with self._cond:
                self._pending[:0] = batch
            return
        with self._cond:
            self._error = None
            self._at.update(at)
            self._size = offset

    def _loop(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not self._closing:
                    self._idle = True
                    self._cond.wait()
                self._idle = False
                if not self._pending:
                    return
            self._flush()
            # a moment for more devices to finish: one write and fsync takes many devices' lines (only
            # stop() wakes it early: a device's line does not)
            with self._cond:
                self._cond.wait_for(lambda: self._closing, timeout=0.05)

    def stop(self) -> None:
        """Stop the writer thread after writing what is pending (the stream stays as it is)."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join()
        self._flush()
        with contextlib.suppress(OSError):
            os.close(self._fd)
        self._fd = -1

    def close(self, report: Report) -> None:
        """Write the final report: each device's last line (devices the rollout never started as the
        report has them), the final summary; assembled from the stream, which it then replaces."""
        from ..state.durable import write_atomic

        with self._cond:
            for d in report.devices:
                if d.name not in self._final:  # skipped by the rollout: never reported as finished
                    self._pending.append((d.name, device_json(d)))
                    self._final.add(d.name)
        if self._fd < 0 and self._pending:  # stopped before (a caller's own stop): append these too
            self._fd = os.open(
                self.path, os.O_WRONLY | os.O_APPEND | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)
            )
        self.stop()
        if self._error is not None:  # lines the disk did not take: the stream is not the run's report
            from ..errors import UsageError
            from ..state.durable import disk_error

            raise UsageError(f"cannot write the report {self.path}: {disk_error(self._error)}")
        head, *_, tail = report_parts(self.recipe, [], report.summary(), report.run_doc(), self.profiles)
        write_atomic(self.path, self._assembled(head, tail), what="the report")

    def _assembled(self, head: bytes, tail: bytes) -> Iterator[bytes]:
        """The final document in pieces: read back from the stream in runs of about a megabyte."""
        yield head
        with open(self.path, "rb") as f:
            for i, name in enumerate(self._order):
                offset, length = self._at[name]
                f.seek(offset)
                line = f.read(length)
                yield b",\n" + line if i else line
        yield tail
