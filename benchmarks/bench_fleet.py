"""A fleet apply: 200 devices x 100 parameters, each device answering after 20 ms, at --parallel 1, 8, 32, 128.

The devices run in another process (benchmarks/fleet_devices.py), so the figures are the
deployer's own: each run is the real command line (`deployer apply --inventory ... --yes`)
started as a child process, measured from the outside (wall time; CPU time and peak memory
from the child's rusage). The `fleet_seconds` are the report's own time for the parallel
phase, without start-up, loading and the final output. Each run writes new values (the
recipe alternates), so every device really is written and verified.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from typing import Any

DEVICES = 200
PARAMETERS = 100
LATENCY_MS = 20
PARALLEL = (1, 8, 32, 128)


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
    """Wall seconds, CPU seconds (user + system), peak RSS in MB, exit code of one child."""
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            stdin=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    proc.returncode = os.waitstatus_to_exitcode(status)
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024, proc.returncode


def run(quick: bool = False) -> dict[str, Any]:
    devices = 40 if quick else DEVICES
    parallel = (1, 8, 32) if quick else PARALLEL
    work = tempfile.mkdtemp(prefix="bench-fleet-")
    with open(os.path.join(work, "profile.yaml"), "w") as f:
        f.write(_profile(PARAMETERS))
    server = subprocess.Popen([sys.executable, "-m", "benchmarks.fleet_devices", os.path.join(work, "profile.yaml"),
                               str(devices), str(LATENCY_MS)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert server.stdout is not None
        urls = json.loads(server.stdout.readline())
        with open(os.path.join(work, "inventory.yaml"), "w") as f:
            f.write("defaults: {timeout: 2.0, retries: 1}\ndevices:\n")
            f.writelines(f"  dev{i:03d}: {{url: '{u}'}}\n" for i, u in enumerate(urls))
        deployer = os.path.join(os.path.dirname(sys.executable), "deployer")
        start_cpu = _run([deployer, "--help"], work)
        results: dict[str, Any] = {"devices": devices, "parameters": PARAMETERS, "latency_ms": LATENCY_MS,
                                   "startup_seconds": round(start_cpu[0], 3)}
        base_wall = base_fleet = 0.0
        for variant, p in enumerate(parallel, 1):
            recipe = os.path.join(work, f"recipe{variant}.yaml")
            with open(recipe, "w") as f:
                f.write(_recipe(PARAMETERS, variant))
            report = os.path.join(work, f"report{p}.json")
            wall, cpu, rss, code = _run([deployer, "apply", recipe, "--inventory", "inventory.yaml", "--yes",
                                         "--parallel", str(p), "--report", report, "--state-dir", "state"], work)
            with open(report) as f:
                data = json.load(f)
            summary = data["summary"]
            assert code == 0 and summary["ok"] == devices, (code, summary)
            fleet = summary["seconds"]
            if p == 1:
                base_wall, base_fleet = wall, fleet
            results[f"parallel_{p}"] = {
                "wall_seconds": round(wall, 2), "speedup": round(base_wall / wall, 1),
                "fleet_seconds": round(fleet, 2), "fleet_speedup": round(base_fleet / fleet, 1),
                "cpu_ms_per_device": round(cpu * 1000 / devices, 1),
                "cpu_ms_per_device_after_startup": round((cpu - start_cpu[1]) * 1000 / devices, 1),
                "peak_rss_mb": round(rss, 1),
                "requests_per_device": round((summary["write_requests"] + summary["read_requests"]) / devices, 1)}
        return results
    finally:
        if server.stdin:
            server.stdin.close()
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()


if __name__ == "__main__":
    print(json.dumps(run("--quick" in sys.argv), indent=2))
