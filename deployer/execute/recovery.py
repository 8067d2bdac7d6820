"""What a refused or failed write request left on the device, found out by reading it; and what a
device's refusals teach about limits its profile does not state.

Devices differ in what a refusal means. Most write in address order and stop at the bad value:
the values before it took, the one that did not is the culprit. Others refuse the whole request
and write nothing of it: for one bad value (Yaskawa documents this), or because the request is
longer than they take, or because they lack Function 16. A refused request of which nothing took
is therefore split in two at a parameter boundary and sent again, recursively, until each refused
request carries one parameter: only the values the device itself refuses end ``failed``, and
one bad value among n costs about 2 log2(n) extra requests (a write and a read-back per level).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace

from ..errors import DeviceGone, ExceptionResponse
from ..planning.model import WriteRequest
from ..planning.planner import merge_fields, plan_reads
from ..profile import Parameter, Profile
from ..report import ParameterResult
from .session import Session
from .verify import _attempted, values_of


async def _remerge(
    session: Session,
    prof: Profile,
    req: WriteRequest,
    desired: dict[str, tuple[int, ...]],
    results: dict[str, ParameterResult],
) -> WriteRequest:
    """Bit fields: read their registers right before the write and merge the new bits into what the
    device holds now (another field may have changed since the snapshot: keep it, never guess)."""
    readable = prof.readable_fields()
    if not readable:  # most profiles: no bit field, nothing to look up per parameter
        return req
    fields = [prof.parameter(n) for n in req.parameters if n in readable]
    if not fields:
        return req
    fresh = await session.read_blocks(plan_reads(prof, [f.name for f in fields]))
    regs = list(req.registers)
    for a in sorted({f.address for f in fields}):
        mates = [prof.parameter(n) for n in req.parameters if prof.parameter(n).address == a]
        word = merge_fields(mates, [desired[m.name][0] for m in mates], fresh[a])
        regs[a - req.address] = word
        for m in mates:
            desired[m.name] = results[m.name].desired_raw = (word,)
    return replace(req, registers=tuple(regs))


def _groups(prof: Profile, req: WriteRequest) -> list[list[Parameter]]:
    """The request's parameters in address order, those sharing registers (bit fields) in one group:
    the places a request may be cut."""
    groups: list[list[Parameter]] = []
    end = -1
    for p in sorted({prof.parameter(n) for n in req.parameters}, key=lambda p: (p.address, p.name)):
        if groups and p.address < end:
            groups[-1].append(p)
        else:
            groups.append([p])
        end = max(end, p.end)
    return groups


def _part(req: WriteRequest, groups: list[list[Parameter]]) -> WriteRequest:
    lo = groups[0][0].address
    hi = max(p.end for g in groups for p in g)
    return replace(
        req,
        address=lo,
        registers=req.registers[lo - req.address : hi - req.address],
        parameters=tuple(p.name for g in groups for p in g),
    )


def halves(prof: Profile, req: WriteRequest) -> tuple[WriteRequest, WriteRequest] | None:
    """``req`` cut in two at the parameter boundary nearest its middle (never inside a value), or None
    when it carries one parameter (or one register's bit fields)."""
    groups = _groups(prof, req)
    if len(groups) < 2:
        return None
    mid = len(groups) // 2
    return _part(req, groups[:mid]), _part(req, groups[mid:])


def chunks(prof: Profile, req: WriteRequest, cap: int) -> list[WriteRequest]:
    """``req`` as consecutive requests of at most ``cap`` registers, cut at parameter boundaries only."""
    out: list[list[list[Parameter]]] = [[]]
    size = 0
    for g in _groups(prof, req):
        n = max(p.end for p in g) - g[0].address
        if out[-1] and size + n > cap:
            out.append([])
            size = 0
        out[-1].append(g)
        size += n
    return [_part(req, gs) for gs in out]


def single_writes(prof: Profile, req: WriteRequest) -> list[WriteRequest]:
    """``req`` as Function 06 requests, one per register in ascending address order (the planner's
    way for devices without Function 16)."""
    params = [prof.parameter(n) for n in req.parameters]
    return [
        WriteRequest(6, a, (w,), tuple(p.name for p in params if p.address <= a < p.end), req.stage)
        for a, w in zip(range(req.address, req.address + req.count), req.registers, strict=True)
    ]


@dataclass
class Learning:
    """What one apply's refusals taught about the device: limits its profile does not state."""

    accepted: int = 0  # registers in the longest Function 16 request the device took
    refused: list[tuple[int, tuple[str, ...]]] = field(default_factory=list)  # refused whole, then split
    fc06: bool = False  # Function 16 answered 01: the writes go as Function 06
    fc06_took: bool = False  # ... and a Function 06 write was taken
    cap: int = 0  # registers per Function 16 request from now on (0: as planned)
    refusals: int = 0  # writes answered with an exception (any)

    def took(self, req: WriteRequest) -> None:
        if req.function == 16:
            self.accepted = max(self.accepted, req.count)
        else:
            self.fc06_took = True

    def length_refusals(self, results: Mapping[str, ParameterResult], done: Iterable[str] | None = None) -> list[int]:
        """Sizes of the requests refused for their length alone: every value in them was taken
        afterwards (of those written so far, with ``done``)."""
        taken = None if done is None else set(done)
        return [
            size
            for size, names in self.refused
            if size > self.accepted > 0
            and all(results[n].status != "failed" and (taken is None or n in taken) for n in names)
        ]

    def update_cap(self, results: Mapping[str, ParameterResult], written: Iterable[str]) -> int:
        """Once a refusal proved to be for length alone, later requests go in pieces the device takes.

        Between the longest request taken and the shortest refused for length, the next piece tries
        the middle size: where the run has longer requests to send anyway, this finds the device's
        limit at the cost of at most one refused request per halving; else the pieces stay at the
        size known to be taken.
        """
        if not self.refused:
            return 0
        refused = self.length_refusals(results, written)
        if not refused:
            return self.cap
        low, high = self.accepted, min(refused)
        self.cap = low if high - low <= 1 else (low + high) // 2
        return self.cap

    def limits(self, results: Mapping[str, ParameterResult]) -> dict[str, int]:
        """The profile limits that would have avoided the refusals (empty: nothing learned)."""
        if self.fc06 and self.fc06_took:
            return {"write_function": 6}
        if self.length_refusals(results):
            return {"max_write_registers": self.accepted}
        return {}

    def notices(self, results: Mapping[str, ParameterResult], profile: str) -> list[str]:
        if self.fc06 and self.fc06_took:
            return [
                "the device refused Function 16 writes (exception 01) and took Function 06; "
                f"set limits.write_function: 6 in profile {profile}"
            ]
        refused = self.length_refusals(results)
        if refused:
            return [
                f"the device took {self.accepted}-register writes and refused {min(refused)}; "
                f"set limits.max_write_registers: {self.accepted} in profile {profile}"
            ]
        return []

    def explain(self, results: Mapping[str, ParameterResult]) -> None:
        """A parameter the device refused that is longer than every write it took: its length may be the reason (a
        string of 8 registers where the device takes 2 at a time, which no split can help), and its error says so
        where it would otherwise read as a bad value."""
        if self.fc06 or not self.accepted or not self.refusals:  # a fleet's devices: nothing refused, no loop
            return
        for r in results.values():
            if r.status == "failed" and r.count > self.accepted and (r.error or "").startswith("exception 03"):
                r.error = (
                    f"{r.error}: the device took writes of up to {self.accepted} registers in this run, and "
                    f"{r.name} needs {r.count} in one request (its length may be what it refused)"
                )


@dataclass(frozen=True)
class Recovery:
    follow_up: WriteRequest | None = None  # what is still to be sent after the refused value
    halves: tuple[WriteRequest, WriteRequest] | None = None  # nothing took: send these instead, in order
    took_all: bool = False  # the device complained, yet every value is there: go on as after a plain answer


async def _recover(
    session: Session,
    prof: Profile,
    req: WriteRequest,
    exc: ExceptionResponse,
    desired: Mapping[str, tuple[int, ...]],
    results: dict[str, ParameterResult],
    written: set[str],
    notices: list[str] | None = None,
) -> Recovery:
    """After an exception: read the request's registers back to see which took.

    A device may answer an exception (04, server device failure) to a write it carried out: the
    read-back decides (``took_all``), and ``notices`` gets a word of it.

    A device that writes in address order stops at the bad value, so the first parameter that
    does not hold its desired value is the rejected one; the ones after it were not written
    and go into a follow-up request. Write-only parameters cannot be read: they count as
    taken when a later parameter took. When nothing of a request of several parameters took
    (a parameter already holding its value before proves nothing), the device refused it whole:
    it is split in halves instead, and nothing is blamed yet.
    """
    params = sorted({prof.parameter(n) for n in req.parameters}, key=lambda p: p.address)
    error = f"exception {exc.code:02d} ({ExceptionResponse.NAMES.get(exc.code, 'unknown')})"
    try:
        now = values_of(
            params, await session.read_blocks(plan_reads(prof, [p.name for p in params if p.readable]), prof)
        )
    except (DeviceGone, ExceptionResponse) as e:  # cannot tell what took: say so, send nothing more of it
        _attempted(results, req.parameters, written, f"{error}; reading back failed: {e}")
        return Recovery()
    rejected: Parameter | None = None
    unknown: list[str] = []  # write-only parameters seen so far
    took: list[str] = []
    proof = False  # a parameter that did not hold its value before holds it now: something took
    for p in params:
        if not p.readable:
            unknown.append(p.name)
            continue
        if p.same_value(now.get(p.name), desired[p.name]):
            took += [*unknown, p.name]
            unknown = []
            before = results[p.name].before_raw
            proof = proof or before is None or not p.same_value(before, desired[p.name])
            continue
        rejected = p
        break
    if rejected is not None and not proof and req.function == 16:
        split = halves(prof, req)
        if split is not None:  # refused whole: find the culprit, blame nobody yet
            return Recovery(halves=split)
    _attempted(results, took, written)
    _attempted(results, unknown, written, f"write-only, next to a rejected value ({error})")
    if rejected is None:  # everything took although the device complained: the read-back decides
        if notices is not None:
            notices.append(
                f"the device answered {error} to the write of {', '.join(req.parameters)} at "
                f"0x{req.address:04X}, but reading back shows the values took: reported by the "
                "read-back (check the device's diagnostics)"
            )
        return Recovery(took_all=True)
    results[rejected.name].status, results[rejected.name].error = "failed", error
    for p in params:  # bit fields of the rejected register went with it
        if p.mask and p.address == rejected.address and p is not rejected:
            results[p.name].status, results[p.name].error = "failed", f"{error} (register of {rejected.name})"
    rest = [p for p in params if p.address > rejected.address]
    if not rest or req.function == 6:  # an FC06 request carries one register: nothing after it
        return Recovery()
    regs = req.registers[rest[0].address - req.address :]  # bit fields of one register share its word
    return Recovery(replace(req, address=rest[0].address, registers=regs, parameters=tuple(p.name for p in rest)))
