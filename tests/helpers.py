"""Shared test helpers: profiles from text, simulator runs, request counting from the device's log."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any, TypeVar

from deployer.profile import Profile, load_profile
from deployer.simulator import LogEntry, Simulator

T = TypeVar("T")


def profile_from(tmp: Path, text: str, name: str = "dev.yaml") -> Profile:
    p = tmp / name
    p.write_text(text)
    return load_profile(str(p))


def run_with(sim: Simulator, body: Callable[[Simulator], Awaitable[T]]) -> T:
    async def main() -> T:
        async with sim:
            return await body(sim)
    return asyncio.run(main())


def count(log: list[LogEntry], function: int, **where: Any) -> int:
    return sum(1 for e in log if e.function == function and all(getattr(e, k) == v for k, v in where.items()))
