"""The audit-trail page (``deployer audit show --html``): the records chosen, each with what changed and the
signatures it names (name, time, meaning); printed, the record of the trail with its head, to check it against."""

from __future__ import annotations

import html
from collections.abc import Mapping, Sequence
from typing import Any

from .bidi import isolated
from .render import _meta, _page, _print_frame
from .signatures import signature_rows


def _value(v: Any) -> str:
    return "-" if v is None else " ".join(str(w) for w in v) if isinstance(v, list) else str(v)


def _detail(rec: Mapping[str, Any]) -> str:
    d = rec.get("detail") if isinstance(rec.get("detail"), Mapping) else {}
    assert isinstance(d, Mapping)
    parts = []
    params = d.get("parameters")
    if isinstance(params, list) and params:
        rows = "".join(
            f"<tr><td>{isolated(p.get('name'))}</td><td>{isolated(_value(p.get('old')))}</td>"
            f"<td>{isolated(_value(p.get('new')))}</td><td>{isolated(p.get('status'))}</td></tr>"
            for p in params
            if isinstance(p, Mapping)
        )
        parts.append(
            "<table class=params><thead><tr><th>parameter</th><th>old</th><th>new</th><th>status</th></tr>"
            f"</thead><tbody>{rows}</tbody></table>"
        )
    sigs = [
        s
        for s in ([d] if d.get("signer") and d.get("meaning") else d.get("signatures") or [])
        if isinstance(s, Mapping)
    ]
    if sigs:
        parts.append(signature_rows(sigs, checked=False))
    missing = d.get("missing")
    if isinstance(missing, list) and missing:
        parts.append("<ul>" + "".join(f"<li>{isolated(m)}</li>" for m in missing) + "</ul>")
    rest = [
        (k, v)
        for k, v in d.items()
        if k
        not in (
            "parameters",
            "signatures",
            "missing",
            "signer",
            "meaning",
            "time",
            "attested_by",
            "holds",
            "digest",
            "reason",
        )
        and v not in (None, "", [])
    ]
    if rest:
        parts.append(
            "<div class=muted>" + "; ".join(f"{html.escape(k)}: {isolated(_value(v))}" for k, v in rest) + "</div>"
        )
    return "".join(parts)


def audit_page(
    records: Sequence[Mapping[str, Any]],
    *,
    filters: Sequence[tuple[str, str]],
    head: str | None,
    verified: str,
    command: str | None = None,
    meta: Sequence[tuple[str, str]] = (),
) -> str:
    """``records``: the trail's records chosen; ``head``: ``SEQ:HASH`` of the trail's last record when printed;
    ``verified``: what ``audit verify`` said then."""
    rows = "".join(
        f"<tr class=rec><td class=num>{isolated(r.get('seq'))}</td><td>{isolated(r.get('time'))}</td>"
        f"<td><b>{isolated(r.get('event'))}</b></td><td>{isolated(r.get('user') or '')}"
        f"{' (' + isolated(r['role']) + ')' if r.get('role') else ''}</td>"
        f"<td>{isolated(r.get('device') or '')}</td><td>{isolated(r.get('result') or '')}</td>"
        f"<td>{isolated(r.get('reason') or '')}</td><td>{_detail(r)}"
        + (f"<div class='muted digest'>plan {isolated(r['plan'])}</div>" if r.get("plan") else "")
        + (f"<div class='muted digest'>run {isolated(r['run'])}</div>" if r.get("run") else "")
        + "</td></tr>"
        for r in records
    )
    header = _meta(
        [
            *meta,
            ("command", command),
            *filters,
            ("records", str(len(records))),
            ("trail head", head),
            ("verified", verified),
        ]
    )
    main = (
        "<section><table id=audit><thead><tr><th class=num>seq</th><th>time (UTC)</th><th>event</th><th>user</th>"
        f"<th>device</th><th>result</th><th>reason</th><th>what</th></tr></thead><tbody>{rows}</tbody></table>"
        "</section>"
    )
    return _page("deployer: audit trail", header, main, {"kind": "audit"}, _print_frame(meta, None))
