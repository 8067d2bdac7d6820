"""Saved fleet plans (``plan --inventory --out FLEET.json``): how large they are and how long ``validate`` takes to
check one, for 10,000 devices that hold the same values (one plan, written once, the others naming it:
``plan_of``) and for 300 devices with plans of their own, each of the benchmark drive's 100 parameters.

The plans are an offline plan of the drive's recipe (``deployer plan RECIPE --json``, no device needed), made
device by device as ``plan --out`` writes them; ``validate`` runs as its own process (start-up included), best
of a few runs, with its peak memory.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from typing import Any

from benchmarks import drive
from benchmarks.bench_apply import as_installed, timed


def _document(plan: dict[str, Any], devices: int, distinct: bool) -> dict[str, Any]:
    """A fleet plan of ``devices`` devices: each its own copy of ``plan`` (``distinct``), else the first one's."""
    entries: list[dict[str, Any]] = []
    for i in range(devices):
        device = {**plan["device"], "url": f"tcp://10.{i // 65536}.{i // 256 % 256}.{i % 256}:502", "unit": 1}
        if distinct or i == 0:
            entries.append({"name": f"d{i:05d}", "group": None, "plan": {**plan, "device": device}})
        else:
            entries.append({"name": f"d{i:05d}", "group": None, "plan_of": "d00000", "device": device})
    return {"schema": "deployer.fleetplan/1", "recipe": plan["recipe"], "inventory": "fleet.yaml", "devices": entries}


def run(quick: bool = False) -> dict[str, Any]:
    as_installed()
    repeats = 1 if quick else 3
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as work:
        files = drive.write(work, 100, name="fleetplan", url="tcp://10.0.0.1:502")  # planned offline for that device
        made = subprocess.run(
            [sys.executable, "-m", "deployer", "plan", files["recipe"], "--json"],
            capture_output=True,
            text=True,
            check=True,
        )
        plan = json.loads(made.stdout)
        for name, devices, distinct in (("alike_10000", 10000, False), ("distinct_300", 300, True)):
            if quick:
                devices //= 10
            path = os.path.join(work, f"{name}.json")
            with open(path, "w") as f:
                f.write(json.dumps(_document(plan, devices, distinct), indent=2) + "\n")
            runs = [timed([sys.executable, "-m", "deployer", "validate", path]) for _ in range(repeats)]
            out[name] = {
                "devices": devices,
                "megabytes": round(os.path.getsize(path) / 1e6, 2),
                "validate_seconds": round(min(r[0] for r in runs), 2),
                "validate_peak_mb": round(max(r[2] for r in runs) / 1024, 1),
            }
    return out


if __name__ == "__main__":
    print(json.dumps(run("--quick" in sys.argv), indent=2))
