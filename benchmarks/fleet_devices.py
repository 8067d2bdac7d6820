"""Serve N simulated devices from this process (for bench_fleet): one event loop, one port each.

    python -m benchmarks.fleet_devices PROFILE.yaml N LATENCY_MS

Prints one JSON line with the devices' URLs once all listen, then serves until stdin closes.
Run as a separate process so the measured deployer does not share its CPU or event loop with
the devices it talks to.
"""

from __future__ import annotations

import asyncio
import json
import sys

from deployer.profile import load_profile
from deployer.testing.simulator import Faults, Simulator


async def main(profile_path: str, n: int, latency_ms: float) -> None:
    prof = load_profile(profile_path)
    sims = [Simulator(prof, faults=Faults(latency_ms=latency_ms)) for _ in range(n)]
    for s in sims:
        s.log = _NoLog()  # a long benchmark would keep every request in memory
    await asyncio.gather(*(s.start() for s in sims))
    print(json.dumps([s.url for s in sims]), flush=True)
    loop = asyncio.get_running_loop()
    await loop.run_in_executor(None, sys.stdin.read)  # until the benchmark closes our stdin
    await asyncio.gather(*(s.stop() for s in sims))


class _NoLog(list):  # type: ignore[type-arg]
    def append(self, _item: object) -> None:
        pass


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1], int(sys.argv[2]), float(sys.argv[3])))
