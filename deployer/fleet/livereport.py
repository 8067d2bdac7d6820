"""The fleet report file, rewritten as devices finish (--limit @REPORT works after a crash).

The document itself is written by ``deployer.report`` (``report_parts``), as every report is."""

from __future__ import annotations

import contextlib
import json
import threading
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from ..report import device_json, report_parts

if TYPE_CHECKING:
    from ..execute.job import Job
    from ..report import DeviceResult, Report


# ---- the report file of a running fleet ------------------------------------------------------

NOT_FINISHED = "not finished (interrupted run)"
WRITING = "interrupted while writing (the run did not finish): some parameters may hold new values"


def not_finished(jobs: Sequence[Job], batches: Sequence[int] | None = None) -> list[DeviceResult]:
    """Every job as ``skipped``, "not finished" (with its batch): the report file's first state. The
    devices of one recipe share one (read-only) parameter list, so its JSON is made once (``LiveReport``)."""
    from ..transport.clients import describe
    from .rollout import batch_numbers, skipped_result

    first: dict[int, DeviceResult] = {}
    batch_of = batch_numbers(jobs, batches)
    out = []
    for j in jobs:
        proto = first.get(id(j.recipe))
        if proto is None:
            proto = first[id(j.recipe)] = skipped_result(j, NOT_FINISHED)
        out.append(replace(proto, name=j.name, url=describe(j.url), unit=j.unit, requests=[], notices=[],
                           batch=batch_of.get(j.name)))
    return out


class LiveReport:
    """The ``--report`` file of a fleet run, true at every moment, even after a ``kill -9``.

    Before the first device starts, every selected device is in it as ``skipped`` with the error
    "not finished (interrupted run)"; as devices finish the file is rewritten atomically
    (``report.write_atomic``: temporary file, fsync, rename) so ``--limit @FILE`` retries exactly
    the devices that did not end ok. Each device's JSON is built once; a writer thread rewrites
    the file while the run goes on, taking in every device that finished meanwhile, so a big
    fleet does not wait for its own report: for a small report that is a write per device, for a
    huge one the file lags the run by at most a few write times (devices that ended ok in that
    window would be retried by ``@FILE``, which writes nothing to a device that already matches).
    """

    def __init__(self, path: str, recipe: str | None, skeleton: Sequence[DeviceResult], *,
                 run: dict[str, Any] | None = None) -> None:
        self.path = path
        self.recipe = recipe
        self.run = run  # who, what, where and when (report.run_info)
        self._order = [d.name for d in skeleton]
        made: dict[int, str] = {}  # the skeleton's devices share their parameter lists (not_finished)
        self._parts = {d.name: device_json(d, made) for d in skeleton}
        self._finished: list[DeviceResult] = []
        self._writing: set[str] = set()  # started writing, not finished yet
        self._cond = threading.Condition()
        self._dirty = False
        self._closing = False
        self._started = time.monotonic()
        self._write(self._document())  # on disk before the first device starts
        self._thread = threading.Thread(target=self._loop, name="deployer-report", daemon=True)
        self._thread.start()

    def finished(self, result: DeviceResult) -> None:
        part = device_json(result)
        with self._cond:
            self._parts[result.name] = part
            self._finished.append(result)
            self._dirty = True
            self._cond.notify()

    def writing(self, result: DeviceResult) -> None:
        """A device's snapshot is on disk and its writes start: until it finishes, the file says
        ``interrupted`` with its snapshot, which is what it is if the run dies now. (The file may lag
        the run: the journal's ``device-started`` line, on disk before the first write, is what
        ``rollback --report`` trusts.)"""
        doc = replace(result, status="interrupted", requests=[], notices=[],
                      error=f"{WRITING}; restore it with: deployer rollback {result.snapshot}").to_json()
        doc["parameters"] = [{**p, "status": "unverified" if p["status"] != "unchanged" else p["status"],
                              "error": "the run did not finish: not read back" if p["status"] != "unchanged"
                              else None} for p in doc["parameters"]]
        part = json.dumps(doc).encode()  # ASCII (ensure_ascii), as device_json's
        with self._cond:  # always before the same device's ``finished`` (one coroutine calls both)
            self._writing.add(result.name)
            self._parts[result.name] = part
            self._dirty = True
            self._cond.notify()

    def update(self, result: DeviceResult) -> None:
        """A finished device changed since (a soak rolled it back, its held commit was sent): write it anew."""
        part = device_json(result)
        with self._cond:
            self._parts[result.name] = part
            self._dirty = True
            self._cond.notify()

    def stop(self) -> None:
        """Stop the writer thread (what is on disk stays: at worst one write behind)."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join()

    def close(self, report: Report) -> None:
        """Write the final report: the devices' JSON as built when they finished, the final summary."""
        from ..report import write_atomic

        self.stop()
        with self._cond:
            done = {r.name for r in self._finished}
            for d in report.devices:
                if d.name not in done:  # skipped by the rollout: never reported as finished
                    self._parts[d.name] = device_json(d)
        write_atomic(self.path, self._document(report.summary(), report))

    def _document(self, summary: dict[str, Any] | None = None, report: Report | None = None) -> list[bytes]:
        from ..report import Report

        with self._cond:
            parts = [self._parts[n] for n in self._order]
            finished = list(self._finished)
            writing = len(self._writing - {r.name for r in finished})
        if summary is None:  # finished devices count for real, the rest as the file says (skipped or writing)
            summary = Report(self.recipe, finished, time.monotonic() - self._started).summary()
            summary["devices"] = len(self._order)
            summary["interrupted"] += writing
            summary["skipped"] += len(self._order) - len(finished) - writing
        return report_parts(self.recipe, parts, summary, self.run if report is None else report.run_doc())

    def _write(self, text: list[bytes]) -> None:
        from ..report import write_atomic

        write_atomic(self.path, text)

    def _loop(self) -> None:
        while True:
            with self._cond:
                while not self._dirty and not self._closing:
                    self._cond.wait()
                if not self._dirty:  # closing, and the file already says everything
                    return
                self._dirty = False
            t = time.monotonic()
            with contextlib.suppress(OSError):  # keep the fleet running; close() raises if the disk stays bad
                self._write(self._document())
            # pace: a write that took d seconds is followed by at least 4d of run, so a huge report
            # (36 MB for 1,000 devices x 100 parameters) costs the run at most a fifth of its time
            with self._cond:
                self._cond.wait_for(lambda: self._closing, timeout=4 * (time.monotonic() - t))
