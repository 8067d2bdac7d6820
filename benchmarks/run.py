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


def _get(results: dict[str, Any], path: str) -> Any:
    cur: Any = results
    for part in path.split("/"):
        if not isinstance(cur, dict) or part not in cur:
            return None
        cur = cur[part]
    return cur


# issue #9's and #10's targets: (what, result path, comparison, target)
TARGETS = [
    ("validate, 5,000 parameters (s)", "scale/5000/validate_seconds", "<=", 0.5),
    ("plan, 5,000 parameters (s)", "scale/5000/plan_seconds", "<=", 0.5),
    # issue #46: a whole device plan (every step) within a quarter of PyYAML's pure-Python read of the files
    ("plan of 5,000 parameters / pure-Python YAML read, offline", "planner/against_yaml/offline_vs_yaml", "<=", 0.25),
    (
        "plan of 5,000 parameters / pure-Python YAML read, diff-aware",
        "planner/against_yaml/diff_aware_vs_yaml",
        "<=",
        0.25,
    ),
    ("validate, 50,000 parameters (s)", "scale/50000/validate_seconds", "<=", 5.0),
    ("plan, 50,000 parameters (s)", "scale/50000/plan_seconds", "<=", 5.0),
    ("apply @5 ms: naive script / deployer", "apply/5ms/deployer_vs_naive", ">=", 10.0),
    ("apply @5 ms: deployer / (floor + start-up)", "apply/5ms/deployer/vs_floor_plus_startup", "<=", 1.3),
    ("apply @0 ms: CPU per parameter (ms)", "apply/phases_0ms/cpu_ms_per_parameter", "<", 0.2),
    ("tcp transport vs bare pymodbus", "transport/tcp/ours_vs_bare", ">=", 0.83),
    ("FC03 of a full apply with gap reads", "apply/5ms/deployer_gap_reads/fc03", "<=", 12),
    # issue #10: 200 devices x 100 parameters answering after 20 ms, the command timed from outside
    ("fleet --parallel 32: speed-up over 1", "fleet/parallel_32/speedup", ">=", 20.0),
    ("fleet --parallel 128: speed-up over 1", "fleet/parallel_128/speedup", ">=", 40.0),
    # issue #30: fleets at scale, the light device farm, --parallel 256, with --report
    ("fleet, 10,000 devices: wall (s)", "fleetscale/scale_10000/wall_seconds", "<=", 20.0),
    ("fleet, 10,000 devices: peak RSS (MB)", "fleetscale/scale_10000/peak_rss_mb", "<=", 300.0),
    ("fleet phase / bare client, 20 ms, --parallel 32", "fleetscale/side_20ms_1000_parallel_32/ratio", "<=", 1.3),
    ("fleet phase / bare client, 20 ms, --parallel 128", "fleetscale/side_20ms_1000_parallel_128/ratio", "<=", 1.3),
    ("fleet phase / bare client, 20 ms, --parallel 256", "fleetscale/side_20ms_1000_parallel_256/ratio", "<=", 1.3),
    ("fleet, memory per further device (KB)", "fleetscale/kb_per_device", "<=", 10.0),
    ("fleet phase / bare client, at once, --parallel 32", "fleetscale/side_0ms_2000_parallel_32/ratio", "<=", 3.0),
    ("fleet phase / bare client, at once, --parallel 128", "fleetscale/side_0ms_2000_parallel_128/ratio", "<=", 3.0),
    ("fleet phase / bare client, at once, --parallel 256", "fleetscale/side_0ms_2000_parallel_256/ratio", "<=", 3.0),
    ("request CPU: ours / bare pymodbus", "fleetscale/request_cpu/ratio", "<=", 1.05),
    # issue #23: the run report page of 1,000 devices x 100 parameters
    ("report page, 1,000 x 100: browser opens it (s)", "pages/1000/load_seconds", "<=", 2.0),
    ("report page, 1,000 x 100: size / report JSON", "pages/1000/page_vs_json", "<=", 1.1),
]


def targets(results: dict[str, Any]) -> list[dict[str, Any]]:
    out = []
    for what, path, op, target in TARGETS:
        got = _get(results, path)
        if got is None:
            continue
        ok = {"<=": got <= target, ">=": got >= target, "<": got < target}[op]
        out.append({"target": f"{what} {op} {target}", "measured": got, "met": ok})
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("only", nargs="*", help="benchmark names (e.g. planner simulator)")
    args = ap.parse_args(argv)
    results: dict[str, Any] = {"python": sys.version.split()[0], "time": time.strftime("%Y-%m-%dT%H:%M:%SZ")}
    for mod in sorted(m.name for m in pkgutil.iter_modules(benchmarks.__path__) if m.name.startswith("bench_")):
        name = mod[len("bench_") :]
        if args.only and name not in args.only:
            continue
        module = importlib.import_module(f"benchmarks.{mod}")
        results[name] = module.run(quick=args.quick)
    results["targets"] = targets(results)
    print(json.dumps(results, indent=2))
    rows = _rows("", {k: v for k, v in results.items() if k not in ("python", "time", "targets")})
    width = max((len(k) for k, _ in rows), default=10)
    print()
    for k, v in rows:
        print(f"{k:<{width}}  {v}")
    if results["targets"]:
        print("\ntargets (issues #9, #10, #23 and #30)")
        tw = max(len(t["target"]) for t in results["targets"])
        for t in results["targets"]:
            print(f"  {t['target']:<{tw}}  {t['measured']!s:>8}  {'met' if t['met'] else 'MISSED'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
