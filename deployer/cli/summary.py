"""Fleet plan and diff summaries that stay readable at 200 devices: devices with identical changes together.

Ten identical tables for ten identical changes say less than one line naming the ten devices;
``--per-device`` still prints every device's own table.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

from .base import _n, safe

if TYPE_CHECKING:
    from rich.console import Console

    from ..api import Drift, Plan, Profile

INLINE = 4  # up to this many changes on the group's own line; more go into a table under it


def grouped(changes: Mapping[str, tuple[str, ...]]) -> list[tuple[tuple[str, ...], list[str]]]:
    """Devices (name -> their changes, in inventory order) grouped by identical changes: the largest
    group first, equal sizes in the order of their first device."""
    groups: dict[tuple[str, ...], list[str]] = {}
    for name, key in changes.items():
        groups.setdefault(key, []).append(name)
    return sorted(groups.items(), key=lambda kv: -len(kv[1]))  # stable: first seen first among equals


def plan_changes(plan: Plan, profile: Profile) -> tuple[str, ...]:
    """What a plan changes on its device, one text per parameter: ``F07 10 s -> 12 s``."""
    out = []
    for pp in plan.parameters:
        if pp.action != "write":  # unchanged, or rewritten with its own value to save a request (bridge)
            continue
        cur = profile.parameter(pp.name).format_registers(pp.current_raw) if pp.current_raw is not None else "?"
        out.append(f"{pp.name} {cur} -> {pp.desired}")
    return tuple(out)


def drift_changes(rows: Sequence[Drift]) -> tuple[str, ...]:
    """How a device differs from its recipe, one text per parameter: ``F08 10 s (recipe 12 s)``."""
    return tuple(
        f"{d.name} {d.device} (recipe {d.desired})"
        if d.device_raw is not None
        else f"{d.name} not readable (recipe {d.desired})"
        for d in rows
    )


def print_groups(out: Console, changes: Mapping[str, tuple[str, ...]], down: Sequence[str], *, same: str) -> None:
    """``36 devices: F07 10 s -> 12 s, F08 ...`` and the devices' names, one group after the other;
    ``same`` says what devices without changes are (``as desired``); then the unreachable ones."""
    from .tables import show

    for key, names in grouped(changes):
        head = f"{_n(len(names), 'device')}: "
        if not key:
            out.print(head + same)
        elif len(key) <= INLINE:
            out.print(head + ", ".join(safe(k) for k in key))
        else:
            out.print(head + _n(len(key), "change"))
            show(out, ["", "change"], [["", k] for k in key])
        out.print("  " + ", ".join(safe(n) for n in compact(names)))
    if down:
        out.print(f"{len(down)} unreachable: {', '.join(safe(n) for n in down)}")


_NUMBERED = re.compile(r"^(.*?)(\d+)$")


def compact(names: Sequence[str]) -> list[str]:
    """``press-001, press-002, ..., press-036`` as ``press-001..press-036``: a run of three or more
    names, next to each other, with one prefix and consecutive numbers (zero-padded ones of one
    width); other names as they are."""
    out: list[str] = []
    run: list[str] = []

    def close() -> None:
        out.extend([f"{run[0]}..{run[-1]}"] if len(run) >= 3 else run)
        run.clear()

    for name in names:
        if run and _follows(run[-1], name):
            run.append(name)
            continue
        close()
        run.append(name)
    close()
    return out


def _follows(before: str, name: str) -> bool:
    a, b = _NUMBERED.match(before), _NUMBERED.match(name)
    return (
        a is not None
        and b is not None
        and a[1] == b[1]
        and int(b[2]) == int(a[2]) + 1
        and (len(a[2]) == len(b[2]) or not (a[2].startswith("0") or b[2].startswith("0")))
    )


def drift_matrix(
    rows: Mapping[str, Sequence[Drift]], wanted: Mapping[str, Mapping[str, str]]
) -> tuple[list[str], list[list[str]]]:
    """Headers and rows of a parameter x device table of drift: the drifted devices as columns, in
    inventory order; a cell holds the device's value where it drifts, ``=`` where the device holds its
    recipe's value, ``?`` where it cannot be read, and nothing where the device's recipe lacks the
    parameter; the ``recipe`` column has the value the recipes want (``(varies)`` when the devices'
    recipes differ: then each cell says its own). ``wanted``: device -> parameter -> the recipe's value."""
    drifted = [n for n, r in rows.items() if r]
    params: dict[str, None] = {}
    for n in drifted:
        params.update((d.name, None) for d in rows[n])
    body = []
    for p in params:
        wants = {wanted[n][p] for n in drifted if p in wanted[n]}
        varies = len(wants) != 1  # then each drifted cell says its own recipe's value too
        cells = []
        for n in drifted:
            d = next((d for d in rows[n] if d.name == p), None)
            if d is not None:
                cells.append(("?" if d.device is None else d.device) + (f" (recipe {d.desired})" if varies else ""))
            else:
                cells.append("=" if p in wanted[n] else "")
        body.append([p, "(varies)" if varies else wants.pop(), *cells])
    return ["parameter", "recipe", *drifted], body
