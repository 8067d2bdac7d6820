"""What a person sees while a fleet runs, and the summary at the end (command-line output only).

On a terminal: a live display (done, failed, in flight, a bar, elapsed and ETA, the devices
being worked on now). Without one: a line per device as it finishes, for logs and CI.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Sequence
from types import TracebackType
from typing import TYPE_CHECKING

from .base import _n, console, echo, safe

if TYPE_CHECKING:
    from rich.console import Console, RenderableType
    from rich.live import Live
    from rich.progress import Progress

    from ..api import DeviceResult, Plan, Report
    from ..api.commands import Job, ReadJob
    from .tables import Cell

STYLE = {
    "rolled-back": "bold yellow",
    "interrupted": "bold red",
    "ok": "green",
    "unchanged": "dim",
    "failed": "bold red",
    "mismatch": "bold red",
    "unverified": "yellow",
    "skipped": "yellow",
    "partial": "yellow",
    "unreachable": "bold red",
    "drift": "yellow",
    "sent": "cyan",
}


class FleetProgress:
    """Feed it ``start(name)`` and ``done(name, status, detail)``; use it as a context manager."""

    def __init__(
        self,
        total: int,
        err: Console,
        *,
        live: bool,
        verb: str = "writing",
        lines: bool = True,
        staged: bool = False,
        later: bool = False,
    ) -> None:
        self.total = total
        self.staged = staged  # --batch: each device's line says its batch
        self.err = err
        self.verb = verb
        self.lines = lines
        self.in_flight: dict[str, float] = {}
        self.counts: dict[str, int] = {}
        self._live: Live | None = None
        self._shown = False  # the live display started (``_show``)
        self._later = later
        self._bar: Progress | None = None
        # logs and CI (no terminal): plain lines, unwrapped and without markup (a per-device rich render
        # was a visible share of a big fleet's CPU)
        self._plain = None if err.is_terminal else err.file
        if live:  # rich's live display is only imported for a terminal (logs and CI runs start faster)
            from rich.live import Live
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            self._bar = Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeElapsedColumn(),
                TextColumn("ETA"),
                TimeRemainingColumn(),
                console=err,
            )
            self._task = self._bar.add_task(self._description(), total=total)
            self._live = Live(self, console=err, refresh_per_second=8, transient=False)

    def __enter__(self) -> FleetProgress:
        if not self._later:
            self._show()
        return self

    def __exit__(self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None) -> None:
        if self._live is not None and self._shown:
            self.in_flight.clear()
            self._live.__exit__(t, e, tb)

    def _show(self) -> None:
        """Start the live display (``later``: with the first device, not before: its refresh thread must not exist
        while a run forks its worker processes, ``fleet.workers``, which it does before any device starts)."""
        if self._live is not None and not self._shown:
            self._shown = True
            self._live.__enter__()

    def _description(self) -> str:
        bad = sum(n for s, n in self.counts.items() if s not in ("ok", "skipped"))
        return f"{self.counts.get('ok', 0)} ok, {bad} not ok, {len(self.in_flight)} in flight"

    def __rich__(self) -> RenderableType:
        from rich.console import Group
        from rich.text import Text

        assert self._bar is not None
        self._bar.update(self._task, description=self._description())
        now = sorted(self.in_flight, key=self.in_flight.__getitem__)
        shown = ", ".join(safe(n) for n in now[:8]) + (f" and {len(now) - 8} more" if len(now) > 8 else "")
        return Group(
            self._bar, Text(f"{self.verb}: {shown}" if now else "", style="dim", overflow="ellipsis", no_wrap=True)
        )

    def start(self, name: str) -> None:
        self._show()
        self.in_flight[name] = time.monotonic()

    def done(self, name: str, status: str, detail: str = "") -> None:
        self._show()
        self.in_flight.pop(name, None)
        self.counts[status] = self.counts.get(status, 0) + 1
        if self._bar is not None:
            self._bar.advance(self._task)
        elif self.lines and self._plain is not None:
            self._plain.write(f"{safe(name)}: {status}" + (f" {safe(detail)}" if detail else "") + "\n")
        elif self.lines:
            from .text import styled

            self.err.print(styled(name, ": ", (status, STYLE.get(status, "")), f" {detail}" if detail else ""))

    def device_done(self, r: DeviceResult) -> None:
        where = f"batch {r.batch}, " if self.staged and r.batch is not None else ""
        self.done(r.name, r.status, f"({where}{_n(r.write_requests, 'write')})" + (f" - {r.error}" if r.error else ""))


def fleet_summary(report: Report, out: Console) -> None:
    """One row per device (its batch in a staged run, status, parameters changed and failed, requests,
    seconds), then the totals."""
    from .tables import show

    staged = len({d.batch for d in report.devices}) > 1
    rows: list[list[Cell]] = []
    for d in report.devices:
        secs = "-" if d.seconds is None else f"{d.seconds:.2f}"
        rows.append(
            [
                d.name,
                *([str(d.batch or "-")] if staged else []),
                (d.status, STYLE.get(d.status, "")),
                str(d.changed_count),
                str(d.failed_count),
                str(d.request_count),
                secs,
                d.error or "",
            ]
        )  # escaped by show
    show(
        out, ["device", *(["batch"] if staged else []), "status", "changed", "failed", "requests", "seconds", ""], rows
    )
    s = report.summary()
    parts = [
        f"{s[k]} {k}"
        for k in ("ok", "sent", "partial", "failed", "unreachable", "rolled-back", "interrupted", "skipped")
        if s[k] or k == "ok"
    ]
    ids = s["requests"] - s["write_requests"] - s["read_requests"]
    out.print(
        f"{_n(s['devices'], 'device')}: {', '.join(parts)}; {_n(s['requests'], 'request')} ("
        f"{_n(s['read_requests'], 'read')}, {_n(s['write_requests'], 'write')}"
        + (f", {ids} device identification" if ids else "")
        + f") in {s['seconds']:.2f} s",
        soft_wrap=True,
    )


def read_fleet(jobs: Sequence[ReadJob], parallel: int) -> dict[str, dict[str, tuple[int, ...]] | Exception]:
    """Current values of every device (a live display on a terminal); errors are said on stderr."""
    from ..api.commands import read_fleet_async

    err = console(stderr=True)
    progress = FleetProgress(len(jobs), err, live=err.is_terminal, verb="reading", lines=False)
    with progress:
        values = asyncio.run(
            read_fleet_async(
                jobs, parallel=parallel, on_done=lambda n, e: progress.done(n, "unreachable" if e else "ok")
            )
        )
    for name, v in values.items():
        if isinstance(v, Exception):
            echo(f"{safe(name)}: unreachable - {safe(v)}", err=True)
    return dict(values)


def plan_fleet(
    jobs: Sequence[Job], parallel: int, *, write_all: bool, state_dir: str, window: bool = False
) -> dict[str, Plan | Exception]:
    """Every device's plan against what it holds (a live display on a terminal); errors are said on stderr."""
    from ..api.commands import plan_fleet_async

    err = console(stderr=True)
    progress = FleetProgress(len(jobs), err, live=err.is_terminal, verb="reading", lines=False)
    with progress:
        plans = asyncio.run(
            plan_fleet_async(
                jobs,
                parallel=parallel,
                write_all=write_all,
                state_dir=state_dir,
                window=window,
                on_done=lambda n, e: progress.done(n, "unreachable" if e else "ok"),
            )
        )
    for name, v in plans.items():
        if isinstance(v, Exception):
            echo(f"{safe(name)}: unreachable - {safe(v)}", err=True)
    return dict(plans)
