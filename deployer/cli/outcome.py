"""A run's report on the terminal: what apply, rollback, report and the agent client print at the end."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

from .base import _n, console, echo, safe
from .tables import show

if TYPE_CHECKING:
    from rich.console import Console

    from ..api import DeviceResult, Report


_STATUS_ORDER = {"failed": 0, "mismatch": 1, "unverified": 2, "rolled-back": 3, "skipped": 4, "ok": 5, "unchanged": 6}
_STATUS_STYLE = {
    "ok": "green",
    "unchanged": "dim",
    "failed": "bold red",
    "mismatch": "bold red",
    "unverified": "yellow",
    "skipped": "yellow",
    "partial": "yellow",
    "unreachable": "bold red",
    "sent": "cyan",
    "interrupted": "bold red",
    "rolled-back": "bold yellow",
}


def _words(raw: tuple[int, ...] | None) -> str:
    """Register words where no profile says what they mean (``-``: not read)."""
    return "-" if raw is None else " ".join(str(w) for w in raw)


def print_report(report: Report, out: Console, *, only_not_ok: bool = False) -> None:
    """Per device, every parameter; ``only_not_ok`` (fleets): only the devices that need a look, by parameter."""
    from .text import styled

    for d in report.devices:
        if only_not_ok and d.status in ("ok", "skipped"):
            continue
        out.print(
            styled(
                (d.name, "bold"),
                f" {d.url} unit {d.unit} ({d.profile}): ",
                (d.status, _STATUS_STYLE.get(d.status, "")),
                f" - {d.error}" if d.error else "",
            )
        )
        rows = sorted(d.parameters, key=lambda p: (_STATUS_ORDER.get(p.status, 9), p.address))
        if only_not_ok:
            rows = [p for p in rows if p.status not in ("ok", "unchanged")]
        if d.status != "unreachable" and rows:
            show(
                out,
                ["parameter", "before", "desired", "after", "status", ""],
                [
                    [
                        p.name,
                        p.before or _words(p.before_raw),
                        p.desired,
                        p.after or _words(p.after_raw),
                        (p.status, _STATUS_STYLE.get(p.status, "")),
                        p.error or "",
                    ]
                    for p in rows
                ],
            )
        if d.status == "sent":
            out.print(
                "broadcast sent: every request went out; no device answers a broadcast, so nothing was "
                "read back or verified"
            )
        if d.identity:
            out.print("identity: " + ", ".join(f"{safe(k)} {safe(repr(v))}" for k, v in d.identity.items()))
        for note in d.notices:
            out.print(f"note: {safe(note)}")
        deviated = deviations_text(d)
        if deviated:
            out.print(f"requests the device decided (deviations from the plan): {deviated}", soft_wrap=True)
        if d.status == "rolled-back" and d.commit == "not sent":
            out.print("commit: not sent (the profile's commit steps)")
        elif d.commit in ("held", "not sent"):
            out.print(
                f"commit: {safe(d.commit)} (the profile's commit steps): the values written are not stored to "
                "non-volatile memory; on devices that keep Modbus writes in RAM they revert at a power cycle"
            )
        if d.snapshot and d.status != "rolled-back":
            out.print(f"snapshot: {safe(d.snapshot)}  (undo with: deployer rollback {safe(d.snapshot)})")
        out.print(requests_text(d), soft_wrap=True)
    s = report.summary()
    if len(report.devices) > 1 and not only_not_ok:
        out.print(
            f"{_n(s['devices'], 'device')}: {s['ok']} ok, "
            + (f"{s['sent']} sent, " if s["sent"] else "")
            + f"{s['partial']} partial, {s['failed']} failed, {s['unreachable']} unreachable"
            + (f", {s['rolled-back']} rolled back" if s["rolled-back"] else "")
            + (f", {s['interrupted']} interrupted" if s["interrupted"] else "")
            + f" in {s['seconds']:.2f} s"
        )


def deviations_text(d: DeviceResult) -> str:
    """'step 7: 2 function-06; step 9: 2 split, 1 recovery-read': the requests of the report that are not their
    plan step as planned, by the step they stand in for and by kind."""
    by_step: dict[int, dict[str, int]] = {}
    for r in d.requests:
        if r.deviation is not None and r.step is not None:
            kinds = by_step.setdefault(r.step, {})
            kinds[r.deviation] = kinds.get(r.deviation, 0) + r.attempts
    parts = []
    for step, kinds in sorted(by_step.items()):
        parts.append(f"step {step}: " + ", ".join(f"{n} {k}" for k, n in kinds.items()))
    return "; ".join(parts)


def requests_text(d: DeviceResult) -> str:
    """'13 requests: 8 reads, 4 writes, 1 device identification': what the device received, each attempt counted."""
    ids = d.request_count - d.write_requests - d.read_requests
    parts = [_n(d.read_requests, "read"), _n(d.write_requests, "write")]
    if ids:
        parts.append(f"{ids} device identification")
    again = d.repeated
    return f"{_n(d.request_count, 'request')}: {', '.join(parts)}" + (
        f" ({again} of them sent again after no answer or a busy answer)" if again else ""
    )


def print_outcome(report: Report, *, fleet_run: bool, as_json: bool, report_path: str | None) -> None:
    """The report on stdout: JSON (``--json``), or the table (a fleet's: only the devices that need a look)."""
    out = console()
    if as_json:
        if fleet_run:
            from ..api.commands import report_text

            echo(report_text(report), nl=False)
        else:
            echo(json.dumps(report.to_json(), indent=2))
    elif fleet_run:
        from .progress import fleet_summary

        print_report(report, out, only_not_ok=True)
        fleet_summary(report, out)
    else:
        print_report(report, out)
