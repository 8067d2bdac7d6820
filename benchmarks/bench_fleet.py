"""A fleet apply: 200 devices x 100 parameters, each device answering after 20 ms, at --parallel 1, 8, 32, 128.

The devices run in another process (benchmarks/fleet_devices.py), so the figures are the
deployer's own: each run is the real command line (`deployer apply --inventory ... --yes`)
started as a child process, measured from the outside (wall time; CPU time and peak memory
from the child's rusage). The `fleet_seconds` are the report's own time for the parallel
phase, without start-up, loading and the final output. The package is byte-compiled first, as an
install leaves it (this machine sets PYTHONDONTWRITEBYTECODE: every run would compile our modules).
Each run writes new values (the recipe alternates), so every device really is written and
verified. Last, the scale check: 1,000 such devices at --parallel 256 (open-file limit, memory
per device).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from typing import Any

from benchmarks.bench_apply import as_installed
from benchmarks.child import measured

DEVICES = 200
PARAMETERS = 100
LATENCY_MS = 20
PARALLEL = (1, 8, 32, 128)
SCALE = (1000, 256)  # and then: this many devices at this --parallel (memory should grow linearly)


def _profile(n: int) -> str:
    lines = ["profile: bench-drive", "description: a drive with many parameters (benchmark)", "parameters:"]
    address = 0
    for i in range(n):
        t = "uint32" if i % 4 == 0 else "uint16"
        lines.append(f"  p{i}: {{register: {address}, type: {t}, unit: s, scale: 0.01, min: 0, max: 600}}")
        address += (2 if t == "uint32" else 1) + (5 if i % 50 == 49 else 0)  # two groups with a gap
    return "\n".join(lines) + "\n"


def _recipe(n: int, variant: int) -> str:
    body = "".join(f"  p{i}: {(i % 50) + 1 + variant / 10} s\n" for i in range(n))
    return f"recipe: bench-{variant}\nprofile: profile.yaml\nparameters:\n{body}"


def _run(cmd: list[str], cwd: str) -> tuple[float, float, float, int]:
    """Wall seconds, CPU seconds (user + system), peak RSS in MB (the command's own: see child.py), exit code."""
    wall, cpu, rss, code, _ = measured(cmd, cwd)
    return wall, cpu, rss / 1024, code


def _inventory(work: str, name: str, urls: list[str]) -> str:
    path = os.path.join(work, name)
    with open(path, "w") as f:
        f.write("defaults: {timeout: 3.0, retries: 1}\ndevices:\n")
        f.writelines(f"  dev{i:04d}: {{url: '{u}'}}\n" for i, u in enumerate(urls))
    return name


def _apply(work: str, inventory: str, variant: int, parallel: int, devices: int) -> dict[str, Any]:
    recipe = os.path.join(work, f"recipe{variant}.yaml")
    with open(recipe, "w") as f:
        f.write(_recipe(PARAMETERS, variant))
    report = os.path.join(work, f"report{variant}.json")
    deployer = os.path.join(os.path.dirname(sys.executable), "deployer")
    wall, cpu, rss, code = _run(
        [
            deployer,
            "apply",
            recipe,
            "--inventory",
            inventory,
            "--yes",
            "--parallel",
            str(parallel),
            "--report",
            report,
            "--state-dir",
            "state",
        ],
        work,
    )
    with open(report) as f:
        summary = json.load(f)["summary"]
    assert code == 0 and summary["ok"] == devices, (code, summary)
    return {
        "wall": wall,
        "cpu": cpu,
        "rss": rss,
        "fleet": summary["seconds"],
        "requests": summary["write_requests"] + summary["read_requests"],
    }


def _bare_client(urls: list[str], parallel: int) -> float:
    """The devices' floor: a bare pymodbus client sending each device deployer's 6 requests (no snapshot,
    journal, report or start-up), ``parallel`` devices at once, in this process. Seconds."""
    import asyncio

    from pymodbus.client import AsyncModbusTcpClient

    async def device(url: str, gate: asyncio.Semaphore) -> None:
        host, port = url.split("//", 1)[1].rsplit(":", 1)
        async with gate:
            client = AsyncModbusTcpClient(host, port=int(port))
            await client.connect()
            for _ in range(6):
                await client.read_holding_registers(0, count=60, device_id=1)
            client.close()

    async def main() -> float:
        gate = asyncio.Semaphore(parallel)
        t = time.perf_counter()
        await asyncio.gather(*(device(u, gate) for u in urls))
        return time.perf_counter() - t

    return asyncio.run(main())


def run(quick: bool = False) -> dict[str, Any]:
    devices = 40 if quick else DEVICES
    parallel = (1, 8, 32) if quick else PARALLEL
    scale = None if quick else SCALE
    as_installed()  # like the apply benchmark: an install leaves the package byte-compiled
    work = tempfile.mkdtemp(prefix="bench-fleet-")
    with open(os.path.join(work, "profile.yaml"), "w") as f:
        f.write(_profile(PARAMETERS))
    served = max(devices, scale[0] if scale else 0)
    server = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "benchmarks.fleet_devices",
            os.path.join(work, "profile.yaml"),
            str(served),
            str(LATENCY_MS),
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert server.stdout is not None
        urls = json.loads(server.stdout.readline())
        inventory = _inventory(work, "inventory.yaml", urls[:devices])
        startup = _run([os.path.join(os.path.dirname(sys.executable), "deployer"), "--help"], work)
        results: dict[str, Any] = {
            "devices": devices,
            "parameters": PARAMETERS,
            "latency_ms": LATENCY_MS,
            "startup_seconds": round(startup[0], 3),
        }
        base: dict[str, Any] = {}
        for variant, p in enumerate(parallel, 1):
            m = _apply(work, inventory, variant, p, devices)
            base = base or m
            results[f"parallel_{p}"] = {
                "wall_seconds": round(m["wall"], 2),
                "speedup": round(base["wall"] / m["wall"], 1),
                "fleet_seconds": round(m["fleet"], 2),
                "fleet_speedup": round(base["fleet"] / m["fleet"], 1),
                "cpu_ms_per_device": round(m["cpu"] * 1000 / devices, 1),
                "cpu_ms_per_device_after_startup": round((m["cpu"] - startup[1]) * 1000 / devices, 1),
                "peak_rss_mb": round(m["rss"], 1),
                "requests_per_device": round(m["requests"] / devices, 1),
            }
            if p > 8:  # a bare client's time at this --parallel: what the devices alone allow (the floor)
                results[f"parallel_{p}"]["bare_client_seconds"] = round(_bare_client(urls[:devices], p), 2)
        if scale:
            n, p = scale
            m = _apply(work, _inventory(work, "inventory-scale.yaml", urls[:n]), len(parallel) + 1, p, n)
            small = results[f"parallel_{parallel[-1]}"]
            results[f"scale_{n}_devices_parallel_{p}"] = {
                "wall_seconds": round(m["wall"], 2),
                "fleet_seconds": round(m["fleet"], 2),
                "cpu_ms_per_device": round(m["cpu"] * 1000 / n, 1),
                "peak_rss_mb": round(m["rss"], 1),
                "memory_kb_per_extra_device": round((m["rss"] - small["peak_rss_mb"]) * 1024 / (n - devices), 1),
            }
        return results
    finally:
        if server.stdin:
            server.stdin.close()
        try:
            server.wait(timeout=60)
        except subprocess.TimeoutExpired:
            server.kill()


if __name__ == "__main__":
    print(json.dumps(run("--quick" in sys.argv), indent=2))
