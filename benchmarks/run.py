"""Run every benchmark (benchmarks/bench_*.py) and print JSON and a table.

    python -m benchmarks.run            # full sizes
    python -m benchmarks.run --quick    # smaller sizes, for a smoke run
"""

from __future__ import annotations

import argparse
import importlib
import json
import pkgutil
import sys
import time
from typing import Any

import benchmarks


def _rows(prefix: str, value: Any) -> list[tuple[str, str]]:
    if isinstance(value, dict):
        out = []
        for k, v in value.items():
            out.extend(_rows(f"{prefix}.{k}" if prefix else str(k), v))
        return out
    if isinstance(value, list):
        out = []
        for i, v in enumerate(value):
            out.extend(_rows(f"{prefix}[{i}]", v))
        return out
    if isinstance(value, float):
        return [(prefix, f"{value:,.4g}")]
    return [(prefix, str(value))]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("only", nargs="*", help="benchmark names (e.g. planner simulator)")
    args = ap.parse_args(argv)
    results: dict[str, Any] = {"python": sys.version.split()[0], "time": time.strftime("%Y-%m-%dT%H:%M:%SZ")}
    for mod in sorted(m.name for m in pkgutil.iter_modules(benchmarks.__path__) if m.name.startswith("bench_")):
        name = mod[len("bench_"):]
        if args.only and name not in args.only:
            continue
        module = importlib.import_module(f"benchmarks.{mod}")
        results[name] = module.run(quick=args.quick)
    print(json.dumps(results, indent=2))
    rows = _rows("", {k: v for k, v in results.items() if k not in ("python", "time")})
    width = max((len(k) for k, _ in rows), default=10)
    print()
    for k, v in rows:
        print(f"{k:<{width}}  {v}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
