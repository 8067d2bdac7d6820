"""apply vs a hand-written script (one FC16 and one FC03 per parameter), and vs the line's physical limit.

The simulated device delays every answer by the time its request and answer frames take on a
19200-baud 8E1 line (plus the 3.5-character gaps), so wall time behaves like a real RS-485 bus.
"""

from __future__ import annotations

import asyncio
import json
import tempfile
import time
from decimal import Decimal
from typing import Any

from deployer.executor import ApplyOptions, apply_device
from deployer.planner import Target, make_plan
from deployer.profile import Limits, Parameter, Profile
from deployer.recipe import Desired, Recipe
from deployer.simulator import Faults, Simulator
from deployer.transport import open_transport, parse_url

BAUD = 19200


def setup(n: int) -> Recipe:
    params = []
    address = 0
    for i in range(n):
        t = "uint32" if i % 4 == 0 else "uint16"
        params.append(Parameter(name=f"p{i}", address=address, type=t, max=Decimal(60000)))
        address += params[-1].count + (5 if i % 50 == 49 else 0)  # parameter groups with gaps
    prof = Profile(id="bench", parameters=tuple(params), limits=Limits())
    desired = tuple(Desired(p, str(i + 1), p.encode(i + 1)) for i, p in enumerate(params))
    return Recipe("bench", None, prof, desired)


def line_seconds(frames_bytes: int, frames: int) -> float:
    char = 11 / BAUD
    return frames_bytes * char + frames * 3.5 * char


async def ours(recipe: Recipe) -> tuple[float, float, int]:
    async with Simulator(recipe.profile, faults=Faults(baud=BAUD)) as sim:
        t = time.perf_counter()
        res = await apply_device(recipe, parse_url(sim.url), 1,
                                 options=ApplyOptions(state_dir=tempfile.mkdtemp(), write_all=True))
        dt = time.perf_counter() - t
        assert res.status == "ok"
        wire = 0
        for e in sim.log:
            if e.function == 16:
                wire += (9 + 2 * e.count) + 8
            else:
                wire += 8 + (5 + 2 * e.count)
        return dt, line_seconds(wire, 2 * len(sim.log)), len(sim.log)


async def naive(recipe: Recipe) -> tuple[float, int]:
    async with Simulator(recipe.profile, faults=Faults(baud=BAUD)) as sim:
        t = open_transport(sim.url)
        await t.connect()
        start = time.perf_counter()
        for d in recipe.desired:
            await t.write_registers(d.parameter.address, list(d.registers), 1)
        for d in recipe.desired:
            assert tuple(await t.read_holding_registers(d.parameter.address, d.parameter.count, 1)) == d.registers
        dt = time.perf_counter() - start
        await t.close()
        return dt, len(sim.log)


def run(quick: bool = False) -> dict[str, Any]:
    n = 100 if quick else 400
    recipe = setup(n)
    plan = make_plan(recipe, Target(None, 1, "bench"))
    ours_s, physical_s, ours_requests = asyncio.run(ours(recipe))
    naive_s, naive_requests = asyncio.run(naive(recipe))
    return {"parameters": n, "baud": BAUD, "plan_write_requests": len(plan.writes),
            "ours_seconds": round(ours_s, 3), "ours_requests": ours_requests,
            "naive_seconds": round(naive_s, 3), "naive_requests": naive_requests,
            "speedup_vs_naive": round(naive_s / ours_s, 2),
            "line_limit_seconds": round(physical_s, 3),
            "ours_vs_line_limit": round(ours_s / physical_s, 2)}


if __name__ == "__main__":
    res = run()
    print(json.dumps(res, indent=2))
    for k, v in res.items():
        print(f"{k:<24}{v:>12}")
