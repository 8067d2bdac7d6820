"""The three pages, each one HTML file: the page skeleton in Python, the data as embedded JSON, the
tables drawn by the embedded script (assets.JS)."""

from __future__ import annotations

import html
import json
import os
from collections.abc import Mapping, Sequence
from typing import Any

from ..load.messages import printable
from ..report import Report
from .assets import CSS, JS
from .bidi import isolated as _isolated
from .signatures import change_block

# a device's parameters that did not end at their desired value
_BAD = ("failed", "mismatch", "unverified")


def _json_for_script(data: Any) -> str:
    # every "<" as \u003c: inside <script>, "</script" ends the element early, and "<!--" then "<script"
    # makes the HTML parser swallow the page's own script up to a later "</script>". JSON has "<" only
    # inside strings, where \u003c reads back as the same text.
    return json.dumps(data, separators=(",", ":"), ensure_ascii=False).replace("<", "\\u003c")


def _meta(rows: Sequence[tuple[str, Any]]) -> str:
    """The page's header: label, value; a value is user text (a list: items, each isolated)."""
    return (
        "<dl class=meta>"
        + "".join(
            f"<dt>{html.escape(k)}</dt><dd>"
            + (
                ", ".join(_isolated(x) for x in v)
                if isinstance(v, list)
                else _command(v)
                if k == "command"
                else _isolated(v)
            )
            + "</dd>"
            for k, v in rows
            if v not in (None, "", [])
        )
        + "</dl>"
    )


def _command(line: object) -> str:
    """A command line that wraps at its spaces: each word kept whole (a browser also breaks after a '-'), only
    a word longer than a line (a long path) may break inside."""
    return " ".join(
        _isolated(w) if len(w) > 40 else f"<span class=word>{_isolated(w)}</span>" for w in str(line).split(" ")
    )


def _css_string(text: str) -> str:
    """User text as a CSS string inside <style>: quotes, backslashes and line ends escaped, and '<' too (a
    '</style' would end the element)."""
    out = []
    for c in printable(text):
        out.append(f"\\{ord(c):x} " if c in '"\\<>\n\r' else c)
    return '"' + "".join(out) + '"'


def _print_frame(meta: Sequence[tuple[str, str]], run_id: str | None) -> str:
    """Every printed page: site, project, customer and line at the top, the run id and 'page N of M' below."""
    top = "  \u00b7  ".join(f"{k}: {v}" for k, v in meta)
    return (
        "@page { margin: 16mm 12mm 16mm 12mm;"
        + (f" @top-left {{ content: {_css_string(top)}; font: 9pt system-ui, sans-serif; }}" if top else "")
        + (
            f" @bottom-left {{ content: {_css_string('run ' + run_id)}; font: 8pt system-ui, sans-serif; }}"
            if run_id
            else ""
        )
        + ' @bottom-right { content: "page " counter(page) " of " counter(pages); font: 8pt system-ui, '
        "sans-serif; } }"
    )


def _page(title: str, header: str, main: str, data: Mapping[str, Any], frame: str = "") -> str:
    # the title bar shows no markup: control and bidi characters there are escaped as on a terminal
    return (
        "<!DOCTYPE html>\n<html lang=en><head><meta charset=utf-8>"
        "<meta name=viewport content='width=device-width, initial-scale=1'>"
        f"<title>{html.escape(printable(title))}</title><style>{CSS}{frame}</style></head><body>"
        f"<header><h1>{_isolated(title)}</h1>{header}</header><main>{main}</main>"
        f"<script type=application/json id=data>{_json_for_script(data)}</script>"
        f"<script>{JS}</script></body></html>\n"
    )


def _text(value: str | None, raw: Sequence[int] | None) -> str:
    if value is not None:
        return value
    return "-" if raw is None else " ".join(str(w) for w in raw)


def _controls(statuses: Sequence[str], batches: Sequence[int]) -> str:
    opts = "".join(f"<option>{html.escape(s)}</option>" for s in statuses)
    batch = (
        (
            "<label>batch <select id=batch><option value=''>all</option>"
            + "".join(f"<option>{b}</option>" for b in batches)
            + "</select></label>"
        )
        if batches
        else ""
    )
    return (
        "<div class=controls><input type=search id=q placeholder='filter devices (name, URL, profile)'>"
        f"<label>status <select id=status><option value=''>all</option>{opts}</select></label>{batch}"
        "<label><input type=checkbox id=changed> changed</label>"
        "<label><input type=checkbox id=bad> not ok</label><span id=shown class=muted></span></div>"
    )


def _devices(statuses: Sequence[str], batches: Sequence[int], *, as_found: bool = False, compact: bool = False) -> str:
    """The device table (its rows drawn by the script) with its filters; the as-found page has no batch,
    seconds or requests (nothing was run); a compact record prints it as the list of devices."""
    run_cols = (
        ""
        if as_found
        else "<th class='sort num' data-key=batch>batch</th>"
        "<th class='sort num' data-key=changed>changed</th><th class='sort num' data-key=failed>failed</th>"
        "<th class='sort num' data-key=requests>requests</th>"
        "<th class='sort num' data-key=seconds>seconds</th>"
    )
    return (
        f"<section id=devices{' class=compact' if compact else ''}><h2 class=noprint>Devices</h2>"
        + _controls(statuses, batches)
        + "<table id=device-table><thead><tr><th class=sort data-key=name>device</th>"
        "<th class=sort data-key=status>status</th>"
        + run_cols
        + "<th class=sort data-key=profile>profile</th></tr></thead><tbody id=device-rows></tbody></table>"
        "</section>"
    )


_SIGN = (
    "<div class=signoff><h2>Sign-off</h2><div class=sign><div>Commissioned by (name, signature)</div>"
    "<div>Checked by (name, signature)</div><div>Date</div></div></div>"
)


def _outcome(report: Report, devices: Sequence[Mapping[str, Any]]) -> str:
    """Page 1 of the record: how the run ended (devices per status, the soak and confirmation, the commit),
    and the one sign-off block for the run."""
    by_status: dict[str, int] = {}
    for entry in devices:
        by_status[entry["status"]] = by_status.get(entry["status"], 0) + 1
    rows = "".join(
        f"<tr><td><span class='st st-{html.escape(k)}'>{html.escape(k)}</span></td><td class=num>{n}</td></tr>"
        for k, n in sorted(by_status.items(), key=lambda kv: -kv[1])
    )
    window = []
    soaked = sum(1 for d in report.devices if any(n.startswith("soak passed") for n in d.notices))
    watched = sum(1 for d in report.devices if any(n.startswith("the confirmation wait passed") for n in d.notices))
    unhealthy = sum(1 for d in report.devices if d.error and "health check failed" in d.error)
    unconfirmed = sum(1 for d in report.devices if d.error and "not confirmed within" in d.error)
    for n, what in (
        (soaked, "passed the soak"),
        (watched, "stayed healthy until the confirmation"),
        (unhealthy, "failed a health check and {} rolled back"),
        (unconfirmed, "{} not confirmed in time and rolled back"),
    ):
        if n:
            window.append(f"<li>{n} device{'s' if n != 1 else ''} {what.format('was' if n == 1 else 'were')}</li>")
    commits: dict[str, int] = {}
    for d in report.devices:
        if d.commit is not None:
            commits[d.commit] = commits.get(d.commit, 0) + 1
    commit = ", ".join(f"{n} {html.escape(k)}" for k, n in sorted(commits.items())) or "no commit steps"
    unknown = sum(1 for entry in devices if entry.get("unknown"))
    return (
        "<section class=outcome><h2>Outcome</h2><div class=outcome-grid>"
        f"<table class=statuses><thead><tr><th>status</th><th class=num>devices</th></tr></thead><tbody>{rows}"
        "</tbody></table><div>"
        + (f"<p><b>Soak and confirmation</b></p><ul>{''.join(window)}</ul>" if window else "")
        + f"<p><b>Commit</b>: {commit}</p>"
        + (
            f"<p class=error>{unknown} device{'s' if unknown != 1 else ''} in a state nobody knows: their "
            "values show as unknown, with the last value seen and when</p>"
            if unknown
            else ""
        )
        + "</div></div>"
        + change_block((report.run or {}).get("change"))
        + _SIGN
        + "</section>"
    )


def _identity(identity: Mapping[str, str] | None) -> str | None:
    if not identity:
        return None
    keys = ("vendor", "product_code", "product_name", "model_name", "revision", "serial")
    shown = [f"{k.replace('_', ' ')} {identity[k]}" for k in keys if identity.get(k)]
    shown += [f"{k} {v}" for k, v in identity.items() if k not in keys]
    return ", ".join(shown)


# a device whose final state nobody knows: its values are shown as unknown, never as "ok"
_UNKNOWN_DEVICE = ("interrupted",)


def _as_left(d: Any, p: Any, unknown: bool) -> str:
    text = _text(p.after, p.after_raw)
    if not unknown and p.status != "unverified":
        return text
    seen = f" at {d.seen}" if d.seen else ""
    return f"unknown (last seen {text}{seen})" if p.after_raw is not None else "unknown"


def run_page(
    report: Report, *, title: str | None = None, meta: Sequence[tuple[str, str]] = (), compact: bool = False
) -> str:
    """A run's report as a page: the run, status counts, a device table that sorts and filters, and
    each device's parameters (as found / desired / as left / status), failures first. Printed, it is
    the commissioning record: page 1 the outcome and one sign-off block for the run, ``meta`` (site,
    project, customer, line) at the top of every page, the run id and 'page N of M' at the bottom.
    ``compact``: the device table, and parameters only for devices that changed or did not end ok."""
    devices = []
    for d in report.devices:
        unknown = d.status in _UNKNOWN_DEVICE or (
            d.snapshot is not None and d.error is not None and "did not verify" in d.error
        )
        params = [
            [
                p.name,
                _text(p.before, p.before_raw),
                p.desired,
                _as_left(d, p, unknown),
                "unknown" if unknown or p.status == "unverified" else p.status,
                p.error or "",
                p.parameter.manual if p.parameter is not None else "",
            ]  # "3-41 Ramp 1 Ramp Up Time"
            for p in d.parameters
        ]
        devices.append(
            {
                "identity": _identity(d.identity),
                "unknown": unknown or any(p.status == "unverified" for p in d.parameters),
                "name": d.name,
                "url": d.url,
                "unit": d.unit,
                "profile": d.profile,
                "status": d.status,
                "batch": d.batch,
                "seconds": None if d.seconds is None else round(d.seconds, 3),
                "requests": len(d.requests),
                "error": d.error,
                "notices": d.notices,
                "snapshot": d.snapshot,
                "commit": d.commit,
                "sha": d.profile_sha256,
                "changed": sum(1 for p in d.parameters if p.status == "ok" and p.before_raw != p.after_raw),
                "failed": sum(1 for p in d.parameters if p.status in _BAD),
                "params": params,
            }
        )
    summary = report.summary()
    run = report.run or {}
    statuses = [
        s
        for s in ("failed", "partial", "unreachable", "interrupted", "rolled-back", "skipped", "sent", "ok")
        if any(d["status"] == s for d in devices)
    ]
    counts = "".join(
        f"<button class=count data-status='{html.escape(s)}'><b>"
        f"{sum(1 for d in devices if d['status'] == s)}</b><span class='st st-{html.escape(s)}'>"
        f"{html.escape(s)}</span></button>"
        for s in statuses
    )
    profiles = sorted(
        {f"{d.profile} {d.profile_sha256[:12]}" if d.profile_sha256 else d.profile for d in report.devices}
    )
    recipes = sorted({d.recipe for d in report.devices if d.recipe} | ({report.recipe} if report.recipe else set()))
    batches = sorted({d.batch for d in report.devices if d.batch is not None})
    header = _meta(
        [
            *meta,
            ("command", run.get("command")),
            ("recipe", recipes),
            ("who", run.get("user")),
            ("when", run.get("started")),
            ("where", run.get("host")),
            ("deployer", run.get("version")),
            ("run", run.get("id")),
            ("profiles", profiles),
            ("batches", len(batches) if batches else None),
            (
                "devices",
                f"{summary['devices']}; {summary.get('requests', '?')} requests ({summary['read_requests']} reads, "
                f"{summary['write_requests']} writes) in {summary['seconds']:.2f} s",
            ),
        ]
    )
    main = (
        f"{_outcome(report, devices)}<section class=counts>{counts}</section>"
        f"{_devices(statuses, batches, compact=compact)}"
        "<section><h2>Parameters, device by device</h2><div id=records></div></section>"
    )
    name = title or "deployer run: " + (", ".join(os.path.basename(r) for r in recipes) or "report")
    return _page(
        name, header, main, {"kind": "run", "devices": devices, "compact": compact}, _print_frame(meta, run.get("id"))
    )


def as_found_page(
    devices: Sequence[Mapping[str, Any]],
    *,
    command: str | None = None,
    run: Mapping[str, Any] | None = None,
    meta: Sequence[tuple[str, str]] = (),
) -> str:
    """The as-found half of a commissioning record (``pull --html``): per device, what it held.

    ``devices``: ``{name, url, unit, profile, values: [(parameter, text, registers[, manual])], error}`` each;
    ``manual``: the parameter as its manual names it ("3-41 Ramp 1 Ramp Up Time"), shown beside the key.
    """
    data = []
    for d in devices:
        params = [[v[0], v[1], " ".join(str(w) for w in v[2]), v[3] if len(v) > 3 else ""] for v in d.get("values", ())]
        data.append(
            {
                "name": d["name"],
                "url": d["url"],
                "unit": d["unit"],
                "profile": d["profile"],
                "status": "unreachable" if d.get("error") else "ok",
                "batch": None,
                "seconds": None,
                "requests": 0,
                "error": d.get("error"),
                "notices": [],
                "snapshot": None,
                "commit": None,
                "sha": d.get("sha"),
                "changed": 0,
                "failed": 0,
                "params": params,
                "identity": _identity(d.get("identity")),
            }
        )
    info = dict(run or {})
    header = _meta(
        [
            *meta,
            ("command", command or info.get("command")),
            ("who", info.get("user")),
            ("when", info.get("started")),
            ("where", info.get("host")),
            ("deployer", info.get("version")),
            ("devices", len(data)),
        ]
    )
    statuses = [s for s in ("unreachable", "ok") if any(d["status"] == s for d in data)]
    main = (
        _devices(statuses, [], as_found=True)
        + _SIGN
        + "<section><h2>As found, device by device</h2><div id=records></div></section>"
    )
    return _page(
        "deployer: as-found record",
        header,
        main,
        {"kind": "as-found", "devices": data},
        _print_frame(meta, info.get("id")),
    )


def drift_page(
    devices: Sequence[str],
    parameters: Sequence[str],
    cells: Sequence[Sequence[tuple[str] | tuple[str, str] | None]],
    *,
    command: str | None = None,
    run: Mapping[str, Any] | None = None,
) -> str:
    """A fleet's drift as a parameters x devices matrix (``diff --inventory ... --html``).

    ``cells[i][j]``: parameter i on device j: ``(held,)`` as desired, ``(held, desired)`` drifted,
    None where the device's recipe does not set it (or the device could not be read).
    """
    info = dict(run or {})
    drifted = sum(1 for row in cells for c in row if c is not None and len(c) > 1)
    header = _meta(
        [
            ("command", command or info.get("command")),
            ("who", info.get("user")),
            ("when", info.get("started")),
            ("where", info.get("host")),
            ("deployer", info.get("version")),
            ("drift", f"{drifted} values on {len(devices)} devices, {len(parameters)} parameters"),
        ]
    )
    main = (
        "<div class=controls><input type=search id=q placeholder='filter parameters'>"
        "<input type=search id=dq placeholder='filter devices'>"
        "<label><input type=checkbox id=only-drift checked> drifted only</label>"
        "<span id=shown class=muted></span></div><div style='overflow:auto'><table id=matrix></table></div>"
    )
    return _page(
        "deployer: drift",
        header,
        main,
        {
            "kind": "drift",
            "devices": list(devices),
            "parameters": list(parameters),
            "cells": [[None if c is None else list(c) for c in row] for row in cells],
        },
    )
