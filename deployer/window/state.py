"""A window's state, in one place: whose run, soak or confirm, which devices, until when, the report that holds
their snapshots, the boot it was opened in, and whether it is open or how it closed.

The site agent keeps it in its database (``agent/store.py``, the windows table) and its run points to it (the
run's ``window``); the held devices' files (``held.py``: the pending report) are named from it. Closing it is the
store's (``Store.close_window``): the row and this object change together.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from .held import pending_path

KINDS = ("soak", "confirm")


@dataclass
class WindowState:
    run: str
    kind: str  # soak or confirm
    devices: list[str]
    deadline_epoch: float  # the wall clock's deadline (a live wait counts on the monotonic clock)
    report: str  # the run's report so far (held.pending_path): what a rollback restores from
    boot_id: str  # the machine's boot it was opened in: another boot means the devices were not watched
    state: str = "open"  # open; a soak passed or ended; a confirm window confirmed; either expired
    options: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def opened(
        cls, run: str, kind: str, devices: Sequence[str], deadline: float, *, state_dir: str, boot_id: str
    ) -> WindowState:
        return cls(run, kind, list(devices), deadline, pending_path(state_dir, run), boot_id)

    @property
    def deadline(self) -> str:
        return _iso(self.deadline_epoch)

    def expired_why(self, boot_id: str, now: float) -> str | None:
        """Found open at an agent's start: why it is over (rolled back), or None (it has time left: it waits)."""
        if self.boot_id != boot_id:
            return "the machine restarted (another boot) during the window"
        if self.kind == "soak":
            return "the agent stopped during the soak (a soak not watched to its end did not pass)"
        if self.deadline_epoch <= now:
            return "the window ran out while the agent was down"
        return None

    def run_json(self) -> dict[str, Any]:
        """What a run says of its window."""
        out: dict[str, Any] = {
            "kind": self.kind,
            "devices": self.devices,
            "deadline": self.deadline,
            "deadline_epoch": self.deadline_epoch,
        }
        if self.state != "open":
            out["state"] = self.state
        return out

    def to_json(self, now: float) -> dict[str, Any]:
        """What ``GET /v1/windows`` says of it."""
        return {
            "run": self.run,
            "kind": self.kind,
            "devices": self.devices,
            "deadline_epoch": self.deadline_epoch,
            "deadline": _iso(self.deadline_epoch, millis=True),
            "boot_id": self.boot_id,
            "report": self.report,
            "state": self.state,
            "seconds_left": max(0.0, self.deadline_epoch - now),
        }


def _iso(t: float, *, millis: bool = False) -> str:
    text = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t))
    return text + (f".{int(t % 1 * 1000):03d}Z" if millis else "Z")
