"""What a careful user would write instead of deployer for a fleet: a bare pymodbus asyncio client.

    python -m benchmarks.bare_fleet SPEC.json

SPEC: {"urls": [...], "parallel": P, "requests": [[function, address, count], ...], "out": FILE}. Each device
gets the same requests deployer sent to one device of the same run (its report's ``requests``:
Function 43, the snapshot reads, the writes, the read-back), ``parallel`` devices at once, one
connection each, no retries; nothing is saved. Writes {"seconds": ...} to FILE (the devices' phase, as
the report's ``summary.seconds`` is deployer's); run as its own process, so it is measured as deployer is.
"""

from __future__ import annotations

import asyncio
import json
import sys
import time


async def _device(url: str, gate: asyncio.Semaphore, requests: list[list[int]]) -> None:
    from pymodbus.client import AsyncModbusTcpClient

    host, port = url.split("//", 1)[1].rsplit(":", 1)
    async with gate:
        client = AsyncModbusTcpClient(host, port=int(port), retries=0, timeout=3)
        if not await client.connect():
            raise SystemExit(f"cannot connect to {url}")
        try:
            for fc, address, count in requests:
                if fc == 3:
                    r = await client.read_holding_registers(address, count=count, device_id=1)
                elif fc == 16:
                    r = await client.write_registers(address, [0] * count, device_id=1)
                elif fc == 6:
                    r = await client.write_register(address, 0, device_id=1)
                elif fc == 43:
                    r = await client.read_device_information(device_id=1)
                    continue  # a device without identification answers 01, as deployer expects
                else:
                    raise SystemExit(f"function {fc} is not in this benchmark")
                if r.isError():
                    raise SystemExit(f"{url}: function {fc} at {address} answered {r}")
        finally:
            client.close()


async def main(spec: dict[str, object]) -> float:
    urls = spec["urls"]
    requests = spec["requests"]
    assert isinstance(urls, list) and isinstance(requests, list)
    gate = asyncio.Semaphore(int(str(spec["parallel"])))
    t = time.perf_counter()
    await asyncio.gather(*(_device(u, gate, requests) for u in urls))
    return time.perf_counter() - t


if __name__ == "__main__":
    with open(sys.argv[1]) as f:
        spec = json.load(f)
    seconds = asyncio.run(main(spec))
    with open(spec["out"], "w") as f:
        json.dump({"seconds": seconds}, f)
