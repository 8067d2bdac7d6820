"""The plan contract, checked against what a device received: every request apply sends is a step of the plan,
in the plan's order, as planned, or a deviation the report names (docs/design.md#the-plan-is-the-contract)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Protocol

from deployer.execute.executor import DEVIATIONS


class Logged(Protocol):
    """A request as a device logged it: the simulator's ``LogEntry``, or one of another server's."""

    @property
    def function(self) -> int: ...

    @property
    def address(self) -> int: ...

    @property
    def count(self) -> int: ...

    @property
    def values(self) -> list[int] | None: ...


def check(plan: Mapping[str, Any], device: Mapping[str, Any], log: Sequence[Logged], *, complete: bool = True) -> None:
    """Raise AssertionError unless ``log`` (the requests the device received during one apply, in order) is
    exactly ``plan``'s steps plus the deviations the report's ``device`` names.

    - The report's requests, each as many times as its attempts, are the log: function, address, count.
    - A request without a deviation is its step as planned (function, address, count, the values written) and
      the steps such requests execute come in the plan's order, each once.
    - A request with a deviation names a known kind and the step it stands in for.
    - ``complete``: the device ended ok, so every step of the plan went out (the commit steps unless a window
      held them: its end executes them in a plan of its own, the report's ``window`` requests).
    """
    steps = plan["steps"]
    records = [r for r in device["requests"] if not r.get("window")]  # a window's end executes a plan of its own
    sent = [(r["function"], r["address"], r["count"]) for r in records for _ in range(r["attempts"])]
    got = [(e.function, e.address, e.count) for e in log]
    assert sent == got, f"the report's requests are not what the device received:\n{sent}\n{got}"
    logged = iter(log)
    done: list[int] = []
    covered: set[int] = set()  # the steps a request executed, or deviations stood in for
    for r in records:
        entries = [next(logged) for _ in range(r["attempts"])]
        n = r.get("step")
        assert n is not None and 1 <= n <= len(steps), f"a request of no step: {r}"
        covered.add(n)
        if r.get("deviation") is not None:
            assert r["deviation"] in DEVIATIONS, r
            continue
        s = steps[n - 1]
        assert (r["function"], r["address"], r["count"]) == (s["function"], s["address"], s["count"]), (r, s)
        if s.get("values") is not None:  # a device whose log has no values (umodbus's here) is checked without
            for e in entries:
                assert e.values is None or e.values == s["values"], (n, e.values, s["values"])
        done.append(n)
    assert done == sorted(done) and len(done) == len(set(done)), f"steps out of order or twice: {done}"
    if complete:
        # a safe change holds its commit steps: its end sends them in a plan of its own (``window`` requests)
        held = device.get("commit") == "held" or any(r.get("window") for r in device["requests"])
        owed = {n for n, s in enumerate(steps, 1) if not (held and s["kind"] == "commit")}
        assert covered == owed, f"steps not sent: {sorted(owed - covered)}"
