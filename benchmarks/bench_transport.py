"""Transport overhead: our transport vs a bare pymodbus client on the same simulator (FC16, 10 registers).

Over rtu+tcp the transport keeps the 3.5-character silence between frames that a real serial
line needs (pymodbus does not); over plain TCP there is no gap, so the ratio is the layer's cost.
"""

from __future__ import annotations

import asyncio
import json
import time
from typing import Any

from pymodbus import FramerType
from pymodbus.client import AsyncModbusTcpClient

from deployer.profile import Parameter, Profile
from deployer.simulator import Simulator
from deployer.transport import open_transport


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


async def _measure(scheme: str, n: int) -> dict[str, Any]:
    framer = FramerType.SOCKET if scheme == "tcp" else FramerType.RTU
    async with Simulator(_profile(), listen=f"{scheme}://127.0.0.1:0") as sim:
        ours = await _ours(sim.url, n)
        bare = await _bare(sim.url, n, framer)
    return {"ours_requests_per_second": round(ours), "bare_pymodbus_requests_per_second": round(bare),
            "ours_vs_bare": round(ours / bare, 3)}


def run(quick: bool = False) -> dict[str, Any]:
    n = 300 if quick else 2000
    return {scheme: asyncio.run(_measure(scheme, n)) for scheme in ("tcp", "rtu+tcp")}


if __name__ == "__main__":
    res = run()
    print(json.dumps(res, indent=2))
    for scheme, r in res.items():
        ours, bare = r["ours_requests_per_second"], r["bare_pymodbus_requests_per_second"]
        print(f"{scheme:<8} ours {ours:>7}/s  bare {bare:>7}/s  ratio {r['ours_vs_bare']}")
