"""Planning time from 1k to 1M parameters (about linear), and plan size vs one request per parameter."""

from __future__ import annotations

import gc
import json
import random
import time
from typing import Any

from deployer.planner import plan_writes
from deployer.profile import Limits, Parameter
from deployer.recipe import Desired

TYPES = ("uint16", "uint32", "uint16", "int32", "uint64")


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


def bench(n: int, with_current: bool) -> dict[str, Any]:
    ds = make(n)
    current = {d.name: (d.registers if i % 3 else tuple(0 for _ in d.registers)) for i, d in enumerate(ds)} \
        if with_current else None
    dt = float("inf")
    for _ in range(3 if n <= 100_000 else 1):  # best of three: the machine is shared and noisy
        gc.collect()
        t = time.perf_counter()
        _, writes = plan_writes(ds, Limits(), current)
        dt = min(dt, time.perf_counter() - t)
    naive = n if current is None else sum(1 for d in ds if current[d.name] != d.registers)
    return {"parameters": n, "seconds": round(dt, 4), "parameters_per_second": round(n / dt),
            "requests": len(writes), "naive_requests": naive, "requests_vs_naive": round(len(writes) / naive, 4)}


def run(quick: bool = False) -> dict[str, Any]:
    sizes = [1_000, 10_000, 100_000] + ([] if quick else [1_000_000])
    full = [bench(n, False) for n in sizes]
    diff = [bench(n, True) for n in sizes[:3]]
    per = [r["seconds"] / r["parameters"] for r in full]
    return {"write_all": full, "diff_aware": diff,
            "linearity_largest_vs_smallest_time_per_parameter": round(per[-1] / per[0], 2)}


if __name__ == "__main__":
    res = run()
    print(json.dumps(res, indent=2))
    print(f"\n{'mode':<11}{'parameters':>12}{'seconds':>10}{'params/s':>12}{'requests':>10}{'naive':>10}")
    for mode in ("write_all", "diff_aware"):
        for r in res[mode]:
            print(f"{mode:<11}{r['parameters']:>12}{r['seconds']:>10}{r['parameters_per_second']:>12}"
                  f"{r['requests']:>10}{r['naive_requests']:>10}")
