"""Register values of parameters, and verification of read-back values against the plan."""

from __future__ import annotations

from collections.abc import Collection, Iterable, Mapping
from typing import cast

from ..profile import Parameter, Profile
from ..report import ParameterResult, show_registers


def values_of(params: Iterable[Parameter], regs: Mapping[int, int]) -> dict[str, tuple[int, ...]]:
    """Parameter name -> registers, for every parameter whose registers were all read (``regs`` by key)."""
    return _values(((p.name, p.key, p.count) for p in params), regs)


def _values(layout: Iterable[tuple[str, int, int]], regs: Mapping[int, int]) -> dict[str, tuple[int, ...]]:
    out: dict[str, tuple[int, ...]] = {}
    get = regs.get
    for name, a, n in layout:  # a fleet does this twice per device: no generator per value
        if n == 1:
            w = get(a)
            if w is not None:
                out[name] = (w,)
        elif n == 2:
            w, x = get(a), get(a + 1)
            if w is not None and x is not None:
                out[name] = (w, x)
        else:
            words = tuple(map(get, range(a, a + n)))
            if None not in words:
                out[name] = cast(tuple[int, ...], words)  # no None left
    return out


PENDING = "not read back yet"


def _attempted(
    results: dict[str, ParameterResult], names: Collection[str], written: set[str], error: str = PENDING
) -> None:
    """Mark parameters as sent: unverified until the read-back says ok or mismatch."""
    written.update(names)
    for n in names:
        r = results[n]
        r.status, r.error = "unverified", error


def _verify(
    results: dict[str, ParameterResult],
    prof: Profile,
    after: Mapping[str, tuple[int, ...]],
    written: set[str],
    unanswered: Collection[str] = (),
) -> None:
    """Statuses from the read-back: what was sent must read back equal; the rest is reported as is.

    ``unanswered``: parameters of a write the device did not answer (it may not have applied it).
    """
    for n, r in results.items():
        got = after.get(n)
        if got is not None:
            r.after_raw = got
        if r.status in ("failed", "skipped"):
            continue
        if got is None:  # not read back: sent ones stay unverified, with the reason
            if n in written and r.error == PENDING:
                r.error = "write-only: cannot be read back"
            continue
        # the same registers are the same value whatever the parameter (most of them: no profile lookup)
        if got == r.desired_raw or prof.parameter(n).same_value(got, r.desired_raw):
            r.status, r.error = ("ok" if n in written else "unchanged"), None
            continue
        p = prof.parameter(n)
        reads_back = f"reads back {show_registers(p, got)} ({' '.join(f'{w:04X}h' for w in got)})"
        if n in unanswered:
            r.error = f"{r.error}; {reads_back}"  # no answer and not applied: unverified, not "accepted"
        else:
            r.status, r.error = "mismatch", reads_back
