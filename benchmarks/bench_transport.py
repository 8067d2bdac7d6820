"""Transport overhead: our transport vs a bare pymodbus client on the same simulator (FC16, 10 registers).

Over rtu+tcp the transport keeps the 3.5-character silence between frames that a real serial
line needs (pymodbus does not); over plain TCP there is no gap, so the ratio is the layer's cost.
"""

from __future__ import annotations

import asyncio
import json
import statistics
import time
from typing import Any

from pymodbus import FramerType
from pymodbus.client import AsyncModbusTcpClient

from deployer.profile import Parameter, Profile
from deployer.testing.simulator import Simulator
from deployer.transport.clients import open_transport


def _profile() -> Profile:
    return Profile(id="bench", parameters=tuple(Parameter(name=f"r{i}", address=i, type="uint16") for i in range(10)))


async def _ours(url: str, n: int) -> float:
    t = open_transport(url)
    await t.connect()
    start = time.perf_counter()
    for i in range(n):
        await t.write_registers(0, [i % 65536] * 10, 1)
    dt = time.perf_counter() - start
    await t.close()
    return n / dt


async def _bare(url: str, n: int, framer: FramerType) -> float:
    host, port = url.split("://", 1)[1].rsplit(":", 1)
    c = AsyncModbusTcpClient(host, port=int(port), framer=framer, retries=0, timeout=5)
    assert await c.connect()
    start = time.perf_counter()
    for i in range(n):
        r = await c.write_registers(0, [i % 65536] * 10, device_id=1)
        assert not r.isError()
    dt = time.perf_counter() - start
    c.close()
    return n / dt


async def _measure(scheme: str, n: int, rounds: int) -> dict[str, Any]:
    """Rounds alternate between the two clients on one simulator, so neither gets the warm-up or a
    quieter moment of the shared machine to itself; the best round of each is compared (the least
    disturbed one), the medians too."""
    framer = FramerType.SOCKET if scheme == "tcp" else FramerType.RTU
    ours: list[float] = []
    bare: list[float] = []
    async with Simulator(_profile(), listen=f"{scheme}://127.0.0.1:0") as sim:
        await _bare(sim.url, max(50, n // 10), framer)  # warm-up, not counted
        for i in range(rounds):
            first, second = (_ours, _bare) if i % 2 == 0 else (_bare, _ours)
            for fn in (first, second):
                rate = await (_ours(sim.url, n) if fn is _ours else _bare(sim.url, n, framer))
                (ours if fn is _ours else bare).append(rate)
    return {
        "ours_requests_per_second": round(max(ours)),
        "bare_pymodbus_requests_per_second": round(max(bare)),
        "ours_vs_bare": round(max(ours) / max(bare), 3),
        "ours_vs_bare_median": round(statistics.median(ours) / statistics.median(bare), 3),
        "rounds": rounds,
        "requests_per_round": n,
    }


def run(quick: bool = False) -> dict[str, Any]:
    n, rounds = (300, 2) if quick else (1000, 6)
    return {
        "tcp": asyncio.run(_measure("tcp", n, rounds)),
        "rtu+tcp": asyncio.run(_measure("rtu+tcp", n // 5, 2)),
    }  # 1.8 ms of line silence a frame: fewer


if __name__ == "__main__":
    res = run()
    print(json.dumps(res, indent=2))
    for scheme, r in res.items():
        ours, bare = r["ours_requests_per_second"], r["bare_pymodbus_requests_per_second"]
        print(f"{scheme:<8} ours {ours:>7}/s  bare {bare:>7}/s  ratio {r['ours_vs_bare']}")
