"""`deployer validate`, `plan` and `apply` at 500, 5,000 and 50,000 parameters, end to end.

Each command runs as a fresh process (interpreter start-up, imports, profile and recipe
loading, schema and unit checks, planning, printing to a pipe); wall seconds are the best
of a few runs, peak memory is the child's ru_maxrss. The recipes are the benchmark drive with
every 4th parameter 32-bit at all sizes (so that 50,000 parameters fit in 65,536 registers).
Targets (issue #9): 5,000 within 0.5 s, 50,000 within 5 s, time and memory linear. ``apply``
(every parameter changed each run) goes to a simulator in another process answering at once.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
from typing import Any

from benchmarks import drive
from benchmarks.bench_apply import as_installed, device, timed


def run(quick: bool = False) -> dict[str, Any]:
    sizes = [500, 5000] if quick else [500, 5000, 50000]
    repeats = 2 if quick else 3
    out: dict[str, Any] = {}
    as_installed()
    with tempfile.TemporaryDirectory() as work:
        # warm the caches a first run of a fresh install fills (pint's, the units'): not measured
        warm = drive.write(work, 50, wide_every=4, name="warm")
        timed([sys.executable, "-m", "deployer", "validate", warm["recipe"]])
        startup = min(timed([sys.executable, "-c", "pass"])[0] for _ in range(3))
        help_s = min(timed([sys.executable, "-m", "deployer", "--help"])[0] for _ in range(3))
        out["python_startup_seconds"] = round(startup, 3)
        out["deployer_help_seconds"] = round(help_s, 3)
        for n in sizes:
            files = drive.write(work, n, wide_every=4, name=f"s{n}")
            row: dict[str, Any] = {}
            for cmd in ("validate", "plan"):
                runs = [timed([sys.executable, "-m", "deployer", cmd, files["recipe"]]) for _ in range(repeats)]
                row[f"{cmd}_seconds"] = round(min(r[0] for r in runs), 3)
                row[f"{cmd}_peak_mb"] = round(max(r[2] for r in runs) / 1024, 1)
            row["profile_bytes"] = os.path.getsize(files["profile"])
            applies = []
            with device(files["profile"], 0.0, os.path.join(work, f"s{n}.log")) as port:
                for r in range(repeats):  # new values each run: everything is written
                    changed = drive.write(work, n, wide_every=4, name=f"s{n}", salt=r + 1)
                    applies.append(
                        timed(
                            [
                                sys.executable,
                                "-m",
                                "deployer",
                                "apply",
                                changed["recipe"],
                                "--device",
                                f"tcp://127.0.0.1:{port}",
                                "--yes",
                                "--state-dir",
                                os.path.join(work, "state"),
                            ]
                        )
                    )
            row["apply_seconds"] = round(min(a[0] for a in applies), 3)
            row["apply_peak_mb"] = round(max(a[2] for a in applies) / 1024, 1)
            out[str(n)] = row
    if "5000" in out and "500" in out:
        for cmd in ("validate", "plan"):  # time per parameter beyond the 500-parameter run
            a, b = out["500"][f"{cmd}_seconds"], out["5000"][f"{cmd}_seconds"]
            out[f"{cmd}_ms_per_1000_parameters"] = round((b - a) / 4.5 * 1000, 1)
    return out


if __name__ == "__main__":
    print(json.dumps(run("--quick" in sys.argv), indent=2))
