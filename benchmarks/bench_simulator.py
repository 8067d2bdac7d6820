"""Simulator throughput: sequential FC16 of 123 registers, and 50 concurrent clients."""

from __future__ import annotations

import asyncio
import json
import time
from typing import Any

from pymodbus.client import AsyncModbusTcpClient

from deployer.profile import Parameter, Profile
from deployer.testing.simulator import Simulator


def profile(n: int = 123) -> Profile:
    return Profile(id="bench", parameters=tuple(Parameter(name=f"r{i}", address=i, type="uint16") for i in range(n)))


async def _client(url: str) -> AsyncModbusTcpClient:
    host, port = url.removeprefix("tcp://").rsplit(":", 1)
    c = AsyncModbusTcpClient(host, port=int(port), retries=0, timeout=10)
    assert await c.connect()
    return c


async def sequential(n: int) -> float:
    async with Simulator(profile()) as sim:
        c = await _client(sim.url)
        t = time.perf_counter()
        for i in range(n):
            r = await c.write_registers(0, [i % 65536] * 123, device_id=1)
            assert not r.isError()
        dt = time.perf_counter() - t
        c.close()
        return n / dt


async def concurrent(clients: int, per_client: int) -> float:
    async with Simulator(profile()) as sim:
        cs = [await _client(sim.url) for _ in range(clients)]

        async def work(c: AsyncModbusTcpClient) -> None:
            for i in range(per_client):
                r = await (
                    c.write_registers(0, [i] * 10, device_id=1)
                    if i % 2
                    else c.read_holding_registers(0, count=10, device_id=1)
                )
                assert not r.isError()

        t = time.perf_counter()
        await asyncio.gather(*(work(c) for c in cs))
        dt = time.perf_counter() - t
        for c in cs:
            c.close()
        return clients * per_client / dt


def run(quick: bool = False) -> dict[str, Any]:
    n = 300 if quick else 2000
    return {
        "sequential_fc16_123_registers_per_second": round(asyncio.run(sequential(n))),
        "concurrent_50_clients_requests_per_second": round(asyncio.run(concurrent(50, 40 if quick else 200))),
    }


if __name__ == "__main__":
    res = run()
    print(json.dumps(res, indent=2))
    for k, v in res.items():
        print(f"{k:<45}{v:>10}")
