"""Write and read planning: which requests carry the values, which blocks read them.

The fewest write requests for a recipe's values, and the fewest read blocks for its parameters; the
steps around them (checks, unlock, commit ...) are ``steps.py``'s. Pure: no I/O.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..errors import UsageError
from ..profile.model import READ_FUNCTION, SPACE, TYPE_OF_READ
from .model import Action, PlannedParameter, ReadRequest, WriteRequest

if TYPE_CHECKING:
    from ..profile import Limits, Parameter, Profile
    from ..recipe.loader import Desired


# ---- write planning ------------------------------------------------------------------------
#
# Within one stage, parameters split into maximal runs of contiguous registers (p.address ==
# previous end). A request can only cover registers of one run (it may not write a register
# the recipe does not name), so runs are planned independently.
#
# Every parameter known to need writing is "must"; with current values known, the others are
# "optional": they may be rewritten with their (unchanged) value to bridge two must-parameters.
# For a run p[0..n) and L registers per request, an exact dynamic program over positions:
#
#     best[0] = (0, 0)
#     best[i+1] <- best[i]                                  if p[i] is optional (left out)
#     best[j]   <- best[i] + (1, regs(p[i..j)))              for every j with regs(p[i..j)) <= L
#
# where costs compare lexicographically as (requests, registers written). Each request is a
# contiguous slice of whole parameters, so no parameter is ever split, and every way to cover
# the must-parameters is one path through the DP: the result is optimal. It costs O(n * k),
# k = parameters that fit in one request (<= 123): the inner loop stops once the slice passes L.
# (Requests only start and end on must-parameters: see _plan_run.)
#
# Without optional parameters (no current values, or --write-all) the DP reduces to greedy
# packing left to right, O(n). Proof that greedy is optimal ("greedy stays ahead", an exchange
# argument): let any valid plan cut the run into requests ending at o1 < o2 < ... < om, greedy's
# at g1 < g2 < .... Greedy's first request is the longest prefix of whole parameters that fits
# in L, so g1 >= o1. If g(i-1) >= o(i-1), the plan's i-th request [o(i-1), oi) fits in L, so
# its sub-slice [g(i-1), oi) fits too, and greedy, taking the longest slice that fits from
# g(i-1), ends at gi >= oi. So greedy has covered the run after at most m requests: no plan
# needs fewer. All registers are written either way, so the register count ties.
# tests/test_planner.py checks both against brute force on random small profiles.

_REQUEST = 1 << 40  # cost = requests * _REQUEST + registers: one int compares like (requests, registers)


def _plan_run(sizes: Sequence[int], must: Sequence[bool], limit: int) -> list[tuple[int, int]]:
    """Slices [i, j) of a run (parameter sizes in registers) to write: fewest requests, then registers."""
    n = len(sizes)
    if all(must):  # greedy is optimal here (exchange argument above) and O(n)
        slices: list[tuple[int, int]] = []
        start, regs = 0, 0
        for k, size in enumerate(sizes):
            if regs + size > limit:
                slices.append((start, k))
                start, regs = k, 0
            regs += size
        slices.append((start, n))
        return slices
    if not any(must):
        return []
    # An optimal plan never starts or ends a request on an optional parameter: trimming it keeps
    # the request count and writes fewer registers. So requests run from a must-parameter i to a
    # must-parameter j-1; every other position is only "skip". Same optimum, far fewer candidates.
    pre = [0] * (n + 1)  # prefix sums: registers of run[i:j] = pre[j] - pre[i]
    for k, size in enumerate(sizes):
        pre[k + 1] = pre[k] + size
    inf = 1 << 62
    best = [inf] * (n + 1)
    back = [-1] * (n + 1)  # previous position; negative -(i + 1) marks "skipped run[i]", no request
    best[0] = 0
    for i in range(n):
        here = best[i]
        if here == inf:
            continue
        if not must[i]:
            if here < best[i + 1]:
                best[i + 1], back[i + 1] = here, -(i + 1)
            continue
        base = here + _REQUEST - pre[i]
        for j in range(i + 1, n + 1):
            if pre[j] - pre[i] > limit:
                break
            if must[j - 1]:
                cost = base + pre[j]
                if cost < best[j]:
                    best[j], back[j] = cost, i
    slices = []
    j = n
    while j > 0:
        i = back[j]
        if i < 0:
            j = -i - 1
        else:
            slices.append((i, j))
            j = i
    slices.reverse()
    return slices


def merge_fields(fields: Sequence[Parameter], bits: Sequence[int], current: int | None) -> int:
    """One register's word: the fields' new bits over what the device holds (0 where unknown)."""
    mask = 0
    word = 0
    for p, b in zip(fields, bits, strict=True):
        mask |= p.mask
        word |= b & p.mask
    return ((current or 0) & ~mask & 0xFFFF) | word


@dataclass
class _Units:
    """The parameters to write, in write order, as flat lists (attributes read once: at 1M parameters the
    properties cost more than the planning itself). Bit fields of one register form one unit (one merged
    word, written or left together): unit u is parameters bounds[u]:bounds[u + 1]."""

    ordered: list[Desired]
    params: list[Parameter]
    names: list[str]
    addrs: list[int]  # keys: a table's addresses never run on into another table's
    sizes: list[int]
    stages: list[int]
    regs: list[tuple[int, ...]]
    bounds: Sequence[int]
    fields: bool
    coils: bool

    @classmethod
    def of(cls, desired: Sequence[Desired]) -> _Units:
        # holding registers before coils within a stage (each table its own requests), ascending addresses
        ordered = sorted(desired, key=lambda d: (d.parameter.stage, d.parameter.key))
        params = [d.parameter for d in ordered]
        addrs = [p.key for p in params]
        stages = [p.stage for p in params]
        n = len(ordered)
        fields = any(p.mask for p in params)
        bounds: Sequence[int] = range(n + 1)
        if fields:
            bounds = [
                0,
                *(
                    k
                    for k in range(1, n)
                    if not (
                        params[k].mask
                        and params[k - 1].mask
                        and addrs[k] == addrs[k - 1]
                        and stages[k] == stages[k - 1]
                    )
                ),
                n,
            ]
        return cls(
            ordered,
            params,
            [p.name for p in params],
            addrs,
            [p.count for p in params],
            stages,
            [tuple(d.registers) for d in ordered],
            bounds,
            fields,
            any(p.register_type != "holding" for p in params),
        )

    def check(self, limit: int, fc6: bool) -> None:
        """Refuse what no plan can carry: read-only, too big for one request, wrong size, overlapping."""
        names, sizes, addrs, stages, regs, bounds = (
            self.names,
            self.sizes,
            self.addrs,
            self.stages,
            self.regs,
            self.bounds,
        )
        for u in range(len(bounds) - 1):
            k = bounds[u]
            if not self.params[k].writable:
                raise UsageError(f"{names[k]} is a read-only {self.params[k].register_type}: it cannot be written")
            if not fc6 and sizes[k] > limit:
                raise UsageError(
                    f"{names[k]} needs {sizes[k]} registers in one request, but the device takes "
                    f"at most {limit} per request (limits.max_write_registers)"
                )
            for m in range(k, bounds[u + 1]):
                if len(regs[m]) != sizes[m]:
                    raise UsageError(f"{names[m]}: {len(regs[m])} register values for a {sizes[m]}-register parameter")
            # two values for one register would make the plan's outcome depend on request order
            h = k - 1
            if u and stages[h] == stages[k] and addrs[k] < addrs[h] + sizes[h]:
                raise UsageError(
                    f"{names[k]} overlaps {names[h]} (registers {addrs[k]} and "
                    f"{addrs[h]}..{addrs[h] + sizes[h] - 1}): each register may be planned once"
                )

    def must_write(self, current: Mapping[str, tuple[int, ...]] | None, write_all: bool) -> list[bool]:
        """Per parameter: whether the device does not hold it already (unknown counts as not)."""
        n, names, regs = len(self.names), self.names, self.regs
        if write_all or current is None:
            return [True] * n
        if self.fields:
            return [not self.params[k].same_value(current.get(names[k]), regs[k]) for k in range(n)]
        return [current.get(names[k]) != regs[k] for k in range(n)]

    def merge_fields(self, current: Mapping[str, tuple[int, ...]] | None) -> None:
        """Each bit-field unit's one word: the fields' new bits over what the device holds."""
        names, regs, bounds = self.names, self.regs, self.bounds
        for u in range(len(bounds) - 1):
            lo, hi = bounds[u], bounds[u + 1]
            if self.params[lo].mask:
                known = (
                    None
                    if current is None
                    else next((current[names[k]][0] for k in range(lo, hi) if names[k] in current), None)
                )
                merged = (merge_fields(self.params[lo:hi], [regs[k][0] for k in range(lo, hi)], known),)
                for k in range(lo, hi):
                    regs[k] = merged

    def run_end(self, i: int) -> int:
        """The end of the maximal run of units from ``i``: same stage, same table, contiguous registers."""
        stages, addrs, sizes, bounds, coils = self.stages, self.addrs, self.sizes, self.bounds, self.coils
        nu = len(bounds) - 1
        j = i + 1
        while (
            j < nu
            and stages[bounds[j]] == stages[bounds[i]]
            and addrs[bounds[j]] == addrs[bounds[j - 1]] + sizes[bounds[j - 1]]
            and (not coils or addrs[bounds[j]] >> 16 == addrs[bounds[j - 1]] >> 16)
        ):
            j += 1
        return j


def _coil_run(
    t: _Units, i: int, j: int, must: list[bool], must_p: list[bool], actions: list[Action], limits: Limits
) -> list[WriteRequest]:
    """Coils (FC15, FC05 for a single coil): no fields, one bit each; a coil is a unit of its own."""
    out: list[WriteRequest] = []
    for a, b in _plan_run([1] * (j - i), must[i:j], limits.write_coils):
        ks = [t.bounds[u] for u in range(i + a, i + b)]
        for k in ks:
            if not must_p[k]:
                actions[k] = "bridge"
        out.append(
            WriteRequest(
                5 if len(ks) == 1 else 15,
                t.addrs[ks[0]] & 0xFFFF,
                tuple(t.regs[k][0] for k in ks),
                tuple(t.names[k] for k in ks),
                t.stages[ks[0]],
            )
        )
    return out


def _fc6_run(
    t: _Units, i: int, j: int, must: list[bool], must_p: list[bool], actions: list[Action]
) -> list[WriteRequest]:
    """FC06 carries one register, so the "never split" rule cannot hold on such devices: a 2/4-register
    value goes as one FC06 per word, in ascending address order (the word at the lower address first,
    whatever the word order), the words of one parameter back to back with nothing in between. No
    bridges: one request per register saves nothing."""
    out: list[WriteRequest] = []
    for u in range(i, j):
        if must[u]:
            k = t.bounds[u]
            out.extend(
                WriteRequest(6, (t.addrs[k] & 0xFFFF) + w, (word,), tuple(t.names[k : t.bounds[u + 1]]), t.stages[k])
                for w, word in enumerate(t.regs[k])
            )
            for m in range(k, t.bounds[u + 1]):
                if not must_p[m]:
                    actions[m] = "bridge"
    return out


def _fc16_run(
    t: _Units, i: int, j: int, must: list[bool], must_p: list[bool], actions: list[Action], limit: int
) -> list[WriteRequest]:
    """Holding registers: the fewest FC16 requests over the run (``_plan_run``), bridging what is right."""
    out: list[WriteRequest] = []
    bounds = t.bounds
    sizes_u = t.sizes[i:j] if not t.fields else [t.sizes[bounds[u]] for u in range(i, j)]
    for a, b in _plan_run(sizes_u, must[i:j], limit):
        lo, hi = bounds[i + a], bounds[i + b]
        for k in range(lo, hi):
            if not must_p[k]:
                actions[k] = "bridge"
        words = tuple(w for u in range(i + a, i + b) for w in t.regs[bounds[u]])
        out.append(WriteRequest(16, t.addrs[lo] & 0xFFFF, words, tuple(t.names[lo:hi]), t.stages[lo]))
    return out


def plan_writes(
    desired: Sequence[Desired],
    limits: Limits,
    current: Mapping[str, tuple[int, ...]] | None = None,
    *,
    write_all: bool = False,
) -> tuple[tuple[PlannedParameter, ...], tuple[WriteRequest, ...]]:
    """The fewest write requests carrying ``desired`` (see the proof above).

    ``current``: parameter name -> registers the device holds; a missing name (or None for all)
    means unknown, so that parameter is written. Returns the parameters in write order (stage,
    address) with their action, and the requests in the order to send them.
    """
    limit = limits.write_registers
    fc6 = limits.write_function == 6
    t = _Units.of(desired)
    t.check(limit, fc6)
    must_p = t.must_write(current, write_all)
    must = must_p
    nu = len(t.bounds) - 1
    if t.fields:
        t.merge_fields(current)
        must = [any(must_p[t.bounds[u] : t.bounds[u + 1]]) for u in range(nu)]
    actions: list[Action] = ["write" if m else "unchanged" for m in must_p]
    writes: list[WriteRequest] = []
    i = 0
    while i < nu:
        j = t.run_end(i)
        if t.coils and t.addrs[t.bounds[i]] >> 16:
            writes += _coil_run(t, i, j, must, must_p, actions, limits)
        elif fc6:
            writes += _fc6_run(t, i, j, must, must_p, actions)
        else:
            writes += _fc16_run(t, i, j, must, must_p, actions, limit)
        i = j
    planned = tuple(
        PlannedParameter(
            t.names[k],
            t.addrs[k] & 0xFFFF,
            t.sizes[k],
            t.ordered[k].text,
            t.regs[k],
            None if current is None or t.names[k] not in current else tuple(current[t.names[k]]),
            actions[k],
            t.stages[k],
            t.params[k].register_type,
        )
        for k in range(len(t.names))
    )
    return planned, tuple(writes)


# ---- read planning -------------------------------------------------------------------------


def plan_reads(profile: Profile, names: Iterable[str], *, gaps: bool = True) -> tuple[ReadRequest, ...]:
    """FC03 blocks covering ``names`` with the fewest requests, spanning declared readable registers only.

    A block may only span a maximal run of contiguous declared readable registers (reading an
    undeclared gap or a write-only register can fail the whole read), may cover parameters the
    caller did not ask for, and never cuts a parameter. With the profile's ``max_read_gap`` N > 0
    (and ``gaps``), a run also continues across at most N consecutive undeclared registers (never
    across a declared write-only one): the device answers them, the values are ignored. Greedy per
    run: open a block at the first parameter still to read and stretch it over every needed
    parameter that still fits. Optimal by the interval-covering argument: any cover has a block
    containing that first parameter, which can start no earlier, so it reaches no further than
    greedy's block; induction on the rest. tests/test_planner.py checks it against every partition
    of the needed parameters.
    """
    wanted = set(names)
    max_gap = profile.limits.max_read_gap if gaps else 0
    reads: list[ReadRequest] = []
    # profiles built in code need not be sorted; loaded ones are (cheap to be sure). Keys order the
    # four tables one after the other; a read never spans two (see joins).
    params = sorted((p for p in profile.parameters if p.readable), key=lambda p: p.key)
    missing = wanted - {p.name for p in params}
    if missing:
        raise UsageError(f"not readable in profile {profile.id}: {', '.join(sorted(missing))}")
    barriers: list[int] = []  # start keys of write-only parameters: a read never spans them
    if max_gap:
        barriers = sorted(p.key for p in profile.parameters if not p.readable)

    def joins(prev: Parameter, nxt: Parameter) -> bool:
        if prev.register_type != nxt.register_type:
            return False
        if nxt.address in (prev.end, prev.address):  # adjacent, or bit fields sharing one register
            return True
        if nxt.address - prev.end > max_gap:
            return False
        k = bisect.bisect_left(barriers, prev.key + prev.count)
        return k == len(barriers) or barriers[k] >= nxt.key

    i = 0
    while i < len(params):
        j = i + 1
        while j < len(params) and joins(params[j - 1], params[j]):
            j += 1
        table = params[i].register_type
        limit = profile.limits.read_limit(table)
        function = READ_FUNCTION[table]
        start: int | None = None
        end = 0
        for p in params[i:j]:
            if p.name not in wanted:
                continue
            if p.count > limit:
                raise UsageError(f"{p.name} needs {p.count} registers, the device reads at most {limit} at once")
            if start is not None and p.end - start <= limit:
                end = p.end
                continue
            if start is not None:
                reads.append(ReadRequest(start, end - start, function))
            start, end = p.address, p.end
        if start is not None:
            reads.append(ReadRequest(start, end - start, function))
        i = j
    return tuple(reads)


def read_key(r: ReadRequest) -> int:
    """A read's first register in the keys of a register map of all four tables (Parameter.key)."""
    return SPACE[TYPE_OF_READ[r.function]] << 16 | r.address


def gap_free_reads(profile: Profile, reads: Sequence[ReadRequest]) -> tuple[ReadRequest, ...]:
    """The blocks that replace ``reads`` on a device that refuses reads across gaps (DESIGN rule 5)."""
    spans = sorted((read_key(r), read_key(r) + r.count) for r in reads)
    starts = [a for a, _ in spans]
    inside = []
    for p in profile.parameters:
        k = bisect.bisect_right(starts, p.key) - 1
        if p.readable and k >= 0 and p.key + p.count <= spans[k][1]:
            inside.append(p.name)
    return plan_reads(profile, inside, gaps=False)
