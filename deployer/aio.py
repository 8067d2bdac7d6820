"""deployer's operations as coroutines, for callers with their own event loop: ``await deployer.aio.plan(...)``.

The same operations, arguments and results as ``deployer.plan``, ``apply``, ``rollback``, ``diff``, ``pull``,
``confirm`` and ``status`` (those run these in an event loop of their own); the loading functions and the types
are ``deployer``'s. A run cancelled while it writes raises ``RunInterrupted`` with the report of what every device
holds as far as known. ``confirm`` and ``status`` read and write files only: they run in a worker thread here.
"""

from __future__ import annotations

import asyncio
import os

from .api.reading import diff, pull
from .api.running import apply, plan, rollback
from .api.runs import RunStatus
from .api.runs import confirm as _confirm
from .api.runs import status as _status
from .calls import checked

__all__ = ["apply", "confirm", "diff", "plan", "pull", "rollback", "status"]


@checked("deployer.aio.confirm")
async def confirm(
    run: str | None = None, *, state_dir: str | os.PathLike[str] = ".deployer", wait: bool = False
) -> str:
    """``deployer.confirm`` for callers with their own event loop (``wait`` does not block the loop)."""
    return await asyncio.to_thread(_confirm, run, state_dir=state_dir, wait=wait)


@checked("deployer.aio.status")
async def status(state_dir: str | os.PathLike[str] = ".deployer") -> RunStatus:
    """``deployer.status`` for callers with their own event loop."""
    return await asyncio.to_thread(_status, state_dir)


_SERVED = (apply, diff, plan, pull, rollback)  # the coroutines, defined with their blocking twins in deployer.api
