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
            wall, cpu, kb, code, err = measured([sys.executable, "-m", "deployer", "profiles", "import", *args],
                                                cwd=str(ROOT), max_bytes=2 << 30)
            out[w.name] = {"input_mb": round(f.stat().st_size / 1e6, 3) if f is not None else 0,
                           "make_seconds": round(made, 2), "seconds": round(wall, 2), "cpu_seconds": round(cpu, 2),
                           "peak_mb": round(kb / 1024, 1), "exit": code,
                           "as_expected": code == w.code and w.expect in err and "Traceback" not in err,
                           "message": (err.strip().splitlines() or [""])[0][-160:]}
    return out


if __name__ == "__main__":
    import json

    print(json.dumps(run(quick="--quick" in sys.argv), indent=2))
