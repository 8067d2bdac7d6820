"""`deployer profiles import` on the worst inputs of issue #24, at their full size: time and peak memory.

Each command runs as a fresh process started by the small launcher (benchmarks/child.py: its own
``ru_maxrss``, not its parent's), limited to 2 GiB of address space. The inputs are made by
tests/hostile_imports.py (an xlsx whose dimension says A1:XFD1048576 with a cell at XFD1048576,
5M rows, a 400 MB shared string, 2M empty cells in a row; a CSV row of 30M cells, an 8 MB header
of commas, 1M rows, a 1M-column header, the largest valid list of 65,536 rows; SunSpec groups
repeating 100,000,000 times). ``--quick`` uses the tests' smaller inputs of the same kinds.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.child import measured

ROOT = Path(__file__).resolve().parent.parent


def run(quick: bool = False) -> dict[str, Any]:
    sys.path.insert(0, str(ROOT))
    from tests.hostile_imports import WORST

    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as work:
        for w in WORST:
            f = Path(work) / w.file if w.file else None
            t = time.perf_counter()
            if f is not None:
                (w.quick if quick and w.quick else w.make)(f)
            made = time.perf_counter() - t
            args = [a.replace("{f}", str(f)) for a in w.args]
            wall, cpu, kb, code, err = measured(
                [sys.executable, "-m", "deployer", "profiles", "import", *args], cwd=str(ROOT), max_bytes=2 << 30
            )
            out[w.name] = {
                "input_mb": round(f.stat().st_size / 1e6, 3) if f is not None else 0,
                "make_seconds": round(made, 2),
                "seconds": round(wall, 2),
                "cpu_seconds": round(cpu, 2),
                "peak_mb": round(kb / 1024, 1),
                "exit": code,
                "as_expected": code == w.code and w.expect in err and "Traceback" not in err,
                "message": (err.strip().splitlines() or [""])[0][-160:],
            }
        for n in (2_000, 8_000) if quick else (8_000, 20_000):  # issue #28: was quadratic in the renaming
            out[f"wb-template, {n} channels of one name"] = one_name(Path(work), n)
    return out


def one_name(work: Path, n: int) -> dict[str, Any]:
    """``profiles import wb-template`` of ``n`` channels all named ``Temp`` (each renamed Temp_2, Temp_3 ...).

    Before issue #28 the renaming tried every taken suffix again for each entry (quadratic): 8,000 took
    5.1 s of CPU and 20,000 took 29.4 s; now each name remembers its next suffix: 1.0 s and 2.4 s
    (benchmarks/RESULTS.md)."""
    import json

    f = work / f"one-name-{n}.json"
    f.write_text(
        json.dumps(
            {
                "device_type": "x",
                "device": {"channels": [{"name": "Temp", "reg_type": "input", "address": i} for i in range(n)]},
            }
        )
    )
    wall, cpu, kb, code, err = measured(
        [
            sys.executable,
            "-m",
            "deployer",
            "profiles",
            "import",
            "wb-template",
            str(f),
            "-o",
            str(work / f"one-name-{n}.yaml"),
            "--force",
        ],
        cwd=str(ROOT),
        max_bytes=2 << 30,
    )
    return {
        "input_mb": round(f.stat().st_size / 1e6, 3),
        "seconds": round(wall, 2),
        "cpu_seconds": round(cpu, 2),
        "peak_mb": round(kb / 1024, 1),
        "exit": code,
        "as_expected": code == 0 and "Traceback" not in err,
        "renamed": err.count("is taken: imported as"),
    }


if __name__ == "__main__":
    import json

    print(json.dumps(run(quick="--quick" in sys.argv), indent=2))
