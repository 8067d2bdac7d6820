"""Planning time from 1k to 1M parameters (about linear), and plan size vs one request per parameter.

Modes: ``write_all`` (no current values: greedy packing, O(n)); ``diff_aware`` (a third of the
parameters changed: the exact dynamic program, O(n * k)); ``dp_worst`` (one long run of 16-bit
parameters, every other one changed: k = 123 parameters fit in a request, the DP's worst case).
The algorithm is linear (plus a sort that is O(n) on recipe order); the time per parameter
still grows about 2x from 1k to 1M (a step between 10k and 100k, then flat) because a million
live Python objects defeat the CPU caches and lengthen the garbage collector's passes, not
because of the planner's work per parameter.
"""

from __future__ import annotations

import gc
import json
import random
import time
from collections.abc import Callable
from typing import Any

from deployer.planning.planner import plan_writes
from deployer.profile import Limits, Parameter
from deployer.recipe.loader import Desired

TYPES = ("uint16", "uint32", "uint16", "int32", "uint64")
Current = dict[str, tuple[int, ...]] | None


def make(n: int, seed: int = 1) -> list[Desired]:
    """n parameters in runs of contiguous registers with gaps, like a drive's parameter groups.

    Above 65536 registers the addresses model many devices' worth of parameters planned at once;
    the planner's work per parameter is the same.
    """
    rnd = random.Random(seed)
    out = []
    address = 0
    for i in range(n):
        t = TYPES[rnd.randrange(len(TYPES))]
        p = Parameter(name=f"p{i}", address=address, type=t)
        out.append(Desired(p, "1", tuple([0] * (p.count - 1) + [1])))
        address += p.count + (rnd.randrange(1, 20) if rnd.random() < 0.05 else 0)
    return out


def write_all(n: int) -> tuple[list[Desired], Current]:
    return make(n), None


def diff_aware(n: int) -> tuple[list[Desired], Current]:
    ds = make(n)
    return ds, {d.name: (d.registers if i % 3 else tuple(0 for _ in d.registers)) for i, d in enumerate(ds)}


def dp_worst(n: int) -> tuple[list[Desired], Current]:
    ds = [Desired(Parameter(name=f"p{i}", address=i, type="uint16"), "1", (1,)) for i in range(n)]
    return ds, {d.name: ((0,) if i % 2 == 0 else d.registers) for i, d in enumerate(ds)}


def bench(n: int, build: Callable[[int], tuple[list[Desired], Current]]) -> dict[str, Any]:
    ds, current = build(n)
    dt = float("inf")
    for _ in range(3 if n <= 100_000 else 1):  # best of three: the machine is shared and noisy
        gc.collect()
        t = time.perf_counter()
        params, writes = plan_writes(ds, Limits(), current)
        dt = min(dt, time.perf_counter() - t)
    naive = n if current is None else sum(1 for d in ds if current[d.name] != d.registers)
    return {
        "parameters": n,
        "seconds": round(dt, 4),
        "parameters_per_second": round(n / dt),
        "microseconds_per_parameter": round(dt / n * 1e6, 3),
        "requests": len(writes),
        "naive_requests": naive,
        "requests_vs_naive": round(len(writes) / naive, 4),
        "registers_written": sum(w.count for w in writes),
        "bridged": sum(1 for p in params if p.action == "bridge"),
    }


def run(quick: bool = False) -> dict[str, Any]:
    sizes = [1_000, 10_000, 100_000] + ([] if quick else [1_000_000])
    out: dict[str, Any] = {}
    for name, build in (("write_all", write_all), ("diff_aware", diff_aware), ("dp_worst", dp_worst)):
        rows = [bench(n, build) for n in sizes]
        per = [r["seconds"] / r["parameters"] for r in rows]
        out[name] = rows
        # about 1.0 means linear; noise and cache effects move it by a few tenths
        out[f"{name}_linearity"] = round(per[-1] / per[0], 2)
    out["linearity_largest_vs_smallest_time_per_parameter"] = out["write_all_linearity"]
    out["against_yaml"] = against_yaml()
    return out


def against_yaml(n: int = 5000) -> dict[str, Any]:
    """A whole device plan (every step: checks, writes, read-back) of the benchmark drive's ``n`` parameters,
    offline and against values held (a third changed), beside PyYAML's pure-Python loader reading the same
    profile and recipe files: the target is at most a quarter of that time (issue #46)."""
    import tempfile

    import yaml

    from benchmarks import drive
    from deployer.planning.model import Target
    from deployer.planning.steps import make_plan
    from deployer.recipe.loader import load_recipe

    with tempfile.TemporaryDirectory() as work:
        files = drive.write(work, n, wide_every=4)
        texts = []
        for k in ("profile", "recipe"):
            with open(files[k], encoding="utf-8") as f:
                texts.append(f.read())
        rec = load_recipe(files["recipe"])

    def best(f: Callable[[], object], times: int = 5) -> float:
        dt = float("inf")
        for _ in range(times):
            gc.collect()
            t = time.perf_counter()
            f()
            dt = min(dt, time.perf_counter() - t)
        return dt

    parse = best(lambda: [yaml.load(t, Loader=yaml.SafeLoader) for t in texts], 3)
    held = {d.name: (d.registers if i % 3 else tuple(0 for _ in d.registers)) for i, d in enumerate(rec.desired)}
    target = Target("tcp://127.0.0.1:502", 1, "drive")
    offline = best(lambda: make_plan(rec, target, None))
    diff = best(lambda: make_plan(rec, target, held))
    return {
        "parameters": n,
        "yaml_pure_python_seconds": round(parse, 4),
        "plan_offline_seconds": round(offline, 4),
        "plan_diff_aware_seconds": round(diff, 4),
        "offline_vs_yaml": round(offline / parse, 3),
        "diff_aware_vs_yaml": round(diff / parse, 3),
    }


if __name__ == "__main__":
    res = run()
    print(json.dumps(res, indent=2))
    print(
        f"\n{'mode':<11}{'parameters':>11}{'seconds':>9}{'params/s':>10}{'us/param':>9}{'requests':>9}"
        f"{'naive':>8}{'registers':>10}{'bridged':>8}"
    )
    for mode in ("write_all", "diff_aware", "dp_worst"):
        for r in res[mode]:
            print(
                f"{mode:<11}{r['parameters']:>11}{r['seconds']:>9}{r['parameters_per_second']:>10}"
                f"{r['microseconds_per_parameter']:>9}{r['requests']:>9}{r['naive_requests']:>8}"
                f"{r['registers_written']:>10}{r['bridged']:>8}"
            )
        print(f"{mode} linearity (time per parameter, largest / smallest): {res[f'{mode}_linearity']}")
