"""The agent itself (docs/agent.md): what it holds (``site.Site``: settings, devices, files, store, events) with
its parts wired, started and stopped. No HTTP here: ``server`` is one client of it (the handlers call the parts),
so the outward side can grow without touching it.

- ``watch``: every device read at its interval; drift, replaced units, the restores they ask for
- ``runs``: runs started, executed and ended; their windows; the windows an earlier agent left open
- ``commands``: what a client asks (apply, restore, a run's rollback, a confirmation), checked first
- ``ledger``: the writes each register took, and the endurance budgets
- ``views``: the JSON the routes answer with

Everything runs on one event loop; the database is written from that loop only.
"""

from __future__ import annotations

import asyncio
import contextlib
import os

from ..errors import StateError
from ..load.durations import format_duration
from ..state import lock
from ..window.recover import recover
from .commands import Commands
from .ledger import Ledger
from .model import ApiError, Device, RunState, Settings
from .runs import Runs
from .site import Site
from .watch import Watch

__all__ = ["Agent", "ApiError", "Device", "RunState", "Settings"]


class Agent(Site):
    def __init__(self, settings: Settings) -> None:
        super().__init__(settings)
        self.ledger = Ledger(self)
        self.runs = Runs(self, self.ledger)
        self.commands = Commands(self, self.runs, self.ledger)
        self.watch = Watch(self, self.runs)
        self._watching: asyncio.Task[None] | None = None

    async def start(self, url: str) -> None:
        """Own the devices (locks with our address), adopt what is new, resume or expire windows, watch."""
        assert self.files is not None and self.store is not None
        self.url = url
        from ..portable import raise_open_files

        # it holds two lock files per device address for as long as it runs, plus a socket per bus being read
        need = sum(2 * len(j.url.lock_keys) for j in self.files.jobs.values()) + self.settings.parallel + 128
        hard = raise_open_files(need)
        if hard is not None:
            raise StateError(
                f"the agent needs about {need} open files for {len(self.files.jobs)} devices, but this "
                f"system allows {hard} (ulimit -Hn; LimitNOFILE= in its systemd unit)"
            )
        lock.set_agent(url)
        self.own()
        self.event(
            "started",
            f"agent started at {url}: {len(self.devices)} devices, check every "
            f"{format_duration(self.settings.check_every)}, on drift {self.settings.on_drift}, "
            f"on replace {self.settings.on_replace}",
            detail={"pid": os.getpid(), "boot_id": self.boot},
        )
        await recover(self.runs, self.store.windows(), self.boot)
        self._watching = asyncio.ensure_future(self.watch.forever())

    async def stop(self) -> None:
        """SIGTERM: stop watching, end the runs safely (their soaks and windows roll back, as on Ctrl-C), let go."""
        if self._watching is not None:
            self._watching.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watching
        running = [r.task for r in self.runs.live.values() if r.task is not None and not r.task.done()]
        for t in [*running, *self.runs.tasks]:
            t.cancel()
        await asyncio.gather(*running, *self.runs.tasks, return_exceptions=True)
        self.close()
