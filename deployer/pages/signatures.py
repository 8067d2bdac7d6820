"""The electronic signatures on a printed page: who authored, reviewed and approved, when, with which meaning,
and the digest that links the record to the plan (21 CFR 11.50, 11.70)."""

from __future__ import annotations

import html
from collections.abc import Mapping, Sequence
from typing import Any

from .bidi import isolated as _isolated


def _holds(value: Any, why: Any) -> str:
    if value is True:
        return "<span class='st st-ok'>holds</span>"
    if value is False:
        return f"<span class='st st-failed'>does not hold</span> {_isolated(why or '')}"
    return "<span class=muted>not checked (no trusted keys)</span>"


def signature_rows(sigs: Sequence[Mapping[str, Any]], *, checked: bool = True) -> str:
    """A table: name, meaning, time (UTC), attested by, and (``checked``) whether it held."""
    rows = "".join(
        f"<tr><td>{_isolated(s.get('signer', '?'))}</td><td><b>{_isolated(s.get('meaning', '?'))}</b></td>"
        f"<td>{_isolated(s.get('time', '?'))}</td>"
        f"<td>{_isolated(s['attested_by']) if s.get('attested_by') else ''}</td>"
        + (f"<td>{_holds(s.get('holds'), s.get('why'))}</td>" if checked else "")
        + "</tr>"
        for s in sigs
    )
    return (
        "<table class=esig-table><thead><tr><th>name</th><th>meaning</th><th>time (UTC)</th><th>attested by</th>"
        + ("<th>signature</th>" if checked else "")
        + f"</tr></thead><tbody>{rows}</tbody></table>"
    )


def change_block(change: Mapping[str, Any] | None) -> str:
    """The plan that ran: its digest, author, reason and ticket, and its signatures (empty without a plan)."""
    if not change:
        return ""
    said = "".join(
        f"<dt>{html.escape(k)}</dt><dd>{_isolated(change[k])}</dd>"
        for k in ("author", "reason", "ticket")
        if change.get(k)
    )
    sigs = [s for s in change.get("signatures") or [] if isinstance(s, Mapping)]
    table = signature_rows(sigs) if sigs else "<p class=muted>the plan carried no signatures</p>"
    return (
        "<section class=esig><h2>Change and electronic signatures</h2><dl class=meta>"
        f"<dt>plan</dt><dd class=digest>{_isolated(change.get('digest', '?'))}</dd>{said}</dl>{table}"
        "<p class=muted>Each signature covers the plan's digest above, the signer's name, the time and its "
        "meaning; deployer verify PLAN.json checks them again.</p></section>"
    )
