"""What a refused or failed write request left on the device, found out by reading it."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

from ..planning.model import WriteRequest
from ..planning.planner import merge_fields, plan_reads
from ..profile import Parameter, Profile
from ..report import ParameterResult
from ..transport import clients as tp
from .session import DeviceGone, Session
from .verify import _attempted, values_of


async def _remerge(session: Session, prof: Profile, req: WriteRequest, desired: dict[str, tuple[int, ...]],
                   results: dict[str, ParameterResult]) -> WriteRequest:
    """Bit fields: read their registers right before the write and merge the new bits into what the
    device holds now (another field may have changed since the snapshot: keep it, never guess)."""
    fields = [p for p in (prof.parameter(n) for n in req.parameters) if p.mask and p.readable]
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


async def _recover(session: Session, prof: Profile, req: WriteRequest, exc: tp.ExceptionResponse,
                   desired: Mapping[str, tuple[int, ...]], results: dict[str, ParameterResult],
                   written: set[str], notices: list[str] | None = None) -> tuple[WriteRequest | None, bool]:
    """After an exception: read the request's registers back to see which took. Returns the follow-up
    request (the parameters after a rejected one), and whether everything took after all: a device may
    answer an exception (04, server device failure) to a write it carried out; the read-back decides,
    and ``notices`` gets a word of it.

    Devices write in address order and stop at the bad value, so the first parameter that
    does not hold its desired value is the rejected one; the ones after it were not written
    and go into a follow-up request. Write-only parameters cannot be read: they count as
    taken when a later parameter took.
    """
    params = sorted({prof.parameter(n) for n in req.parameters}, key=lambda p: p.address)
    error = f"exception {exc.code:02d} ({tp.ExceptionResponse.NAMES.get(exc.code, 'unknown')})"
    try:
        now = values_of(params, await session.read_blocks(plan_reads(prof, [p.name for p in params if p.readable]),
                                                           prof))
    except (DeviceGone, tp.ExceptionResponse) as e:  # cannot tell what took: say so, send nothing more of it
        _attempted(results, req.parameters, written, f"{error}; reading back failed: {e}")
        return None, False
    rejected: Parameter | None = None
    unknown: list[str] = []  # write-only parameters seen so far
    for p in params:
        if not p.readable:
            unknown.append(p.name)
            continue
        if p.same_value(now.get(p.name), desired[p.name]):
            _attempted(results, [*unknown, p.name], written)
            unknown = []
            continue
        rejected = p
        break
    _attempted(results, unknown, written, f"write-only, next to a rejected value ({error})")
    if rejected is None:  # everything took although the device complained: the read-back decides
        if notices is not None:
            notices.append(f"the device answered {error} to the write of {', '.join(req.parameters)} at "
                           f"0x{req.address:04X}, but reading back shows the values took: reported by the "
                           "read-back (check the device's diagnostics)")
        return None, True
    results[rejected.name].status, results[rejected.name].error = "failed", error
    for p in params:  # bit fields of the rejected register went with it
        if p.mask and p.address == rejected.address and p is not rejected:
            results[p.name].status, results[p.name].error = "failed", f"{error} (register of {rejected.name})"
    rest = [p for p in params if p.address > rejected.address]
    if not rest or req.function == 6:  # an FC06 request carries one register: nothing after it
        return None, False
    regs = tuple(w for p in rest for w in desired[p.name])
    return replace(req, address=rest[0].address, registers=regs, parameters=tuple(p.name for p in rest)), False
