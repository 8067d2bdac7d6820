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

# a device's parameters that did not end at their desired value
_BAD = ("failed", "mismatch", "unverified")


def _json_for_script(data: Any) -> str:
    # every "<" as \u003c: inside <script>, "</script" ends the element early, and "<!--" then "<script"
    # makes the HTML parser swallow the page's own script up to a later "</script>". JSON has "<" only
    # inside strings, where \u003c reads back as the same text.
    return json.dumps(data, separators=(",", ":"), ensure_ascii=False).replace("<", "\\u003c")


# bidi embeddings and overrides (closed by U+202C), isolates (closed by U+2069)
_OPENS = {**{chr(c): "\u202c" for c in (0x202A, 0x202B, 0x202D, 0x202E)},
          **{chr(c): "\u2069" for c in (0x2066, 0x2067, 0x2068)}}


def _isolated(value: object) -> str:
    """User text as HTML inside ``<bdi>``, its bidi controls balanced (an unmatched closer dropped, what
    is left open closed at its end): a U+202E in a name cannot reorder the page's text after it (as
    the script's txt())."""
    opened: list[str] = []
    out = []
    for c in str(value):
        if c in _OPENS:
            opened.append(_OPENS[c])
        elif c == "\u202c":
            if not opened or opened[-1] != c:
                continue
            opened.pop()
        elif c == "\u2069":
            if c not in opened:
                continue
            del opened[len(opened) - 1 - opened[::-1].index(c):]
        out.append(c)
    return f"<bdi>{html.escape(''.join(out) + ''.join(reversed(opened)))}</bdi>"


def _meta(rows: Sequence[tuple[str, Any]]) -> str:
    """The page's header: label, value; a value is user text (a list: items, each isolated)."""
    return "<dl class=meta>" + "".join(
        f"<dt>{html.escape(k)}</dt><dd>"
        + (", ".join(_isolated(x) for x in v) if isinstance(v, list) else _isolated(v)) + "</dd>"
        for k, v in rows if v not in (None, "", [])) + "</dl>"


def _page(title: str, header: str, main: str, data: Mapping[str, Any]) -> str:
    # the title bar shows no markup: control and bidi characters there are escaped as on a terminal
    return ("<!DOCTYPE html>\n<html lang=en><head><meta charset=utf-8>"
            "<meta name=viewport content='width=device-width, initial-scale=1'>"
            f"<title>{html.escape(printable(title))}</title><style>{CSS}</style></head><body>"
            f"<header><h1>{_isolated(title)}</h1>{header}</header><main>{main}</main>"
            f"<script type=application/json id=data>{_json_for_script(data)}</script>"
            f"<script>{JS}</script></body></html>\n")


def _text(value: str | None, raw: Sequence[int] | None) -> str:
    if value is not None:
        return value
    return "-" if raw is None else " ".join(str(w) for w in raw)


def _controls(statuses: Sequence[str], batches: Sequence[int]) -> str:
    opts = "".join(f"<option>{html.escape(s)}</option>" for s in statuses)
    batch = ("<label>batch <select id=batch><option value=''>all</option>"
             + "".join(f"<option>{b}</option>" for b in batches) + "</select></label>") if batches else ""
    return ("<div class=controls><input type=search id=q placeholder='filter devices (name, URL, profile)'>"
            f"<label>status <select id=status><option value=''>all</option>{opts}</select></label>{batch}"
            "<label><input type=checkbox id=changed> changed</label>"
            "<label><input type=checkbox id=bad> not ok</label><span id=shown class=muted></span></div>")


def _devices(statuses: Sequence[str], batches: Sequence[int]) -> str:
    """The device table (its rows drawn by the script) with its filters."""
    return ("<section id=devices><h2 class=noprint>Devices</h2>" + _controls(statuses, batches)
            + "<table id=device-table><thead><tr><th class=sort data-key=name>device</th>"
            "<th class=sort data-key=status>status</th><th class='sort num' data-key=batch>batch</th>"
            "<th class='sort num' data-key=changed>changed</th><th class='sort num' data-key=failed>failed</th>"
            "<th class='sort num' data-key=requests>requests</th><th class='sort num' data-key=seconds>seconds</th>"
            "<th class=sort data-key=profile>profile</th></tr></thead><tbody id=device-rows></tbody></table>"
            "</section>")


def run_page(report: Report, *, title: str | None = None) -> str:
    """A run's report as a page: the run, status counts, a device table that sorts and filters, and
    each device's parameters (as found / desired / as left / status), failures first. Printed, it is
    the commissioning record: a section per device with a signature line."""
    devices = []
    for d in report.devices:
        params = [[p.name, _text(p.before, p.before_raw), p.desired, _text(p.after, p.after_raw), p.status,
                   p.error or ""] for p in d.parameters]
        devices.append({
            "name": d.name, "url": d.url, "unit": d.unit, "profile": d.profile, "status": d.status,
            "batch": d.batch, "seconds": None if d.seconds is None else round(d.seconds, 3),
            "requests": len(d.requests), "error": d.error, "notices": d.notices, "snapshot": d.snapshot,
            "commit": d.commit, "sha": d.profile_sha256,
            "changed": sum(1 for p in d.parameters if p.status == "ok" and p.before_raw != p.after_raw),
            "failed": sum(1 for p in d.parameters if p.status in _BAD), "params": params})
    summary = report.summary()
    run = report.run or {}
    statuses = [s for s in ("failed", "partial", "unreachable", "interrupted", "rolled-back", "skipped", "sent", "ok")
                if any(d["status"] == s for d in devices)]
    counts = "".join(f"<button class=count data-status='{html.escape(s)}'><b>"
                     f"{sum(1 for d in devices if d['status'] == s)}</b><span class='st st-{html.escape(s)}'>"
                     f"{html.escape(s)}</span></button>" for s in statuses)
    profiles = sorted({f"{d.profile} {d.profile_sha256[:12]}" if d.profile_sha256 else d.profile
                       for d in report.devices})
    recipes = sorted({d.recipe for d in report.devices if d.recipe} | ({report.recipe} if report.recipe else set()))
    batches = sorted({d.batch for d in report.devices if d.batch is not None})
    header = _meta([
        ("command", run.get("command")), ("recipe", recipes), ("who", run.get("user")),
        ("when", run.get("started")), ("where", run.get("host")), ("deployer", run.get("version")),
        ("run", run.get("id")), ("profiles", profiles),
        ("batches", len(batches) if batches else None),
        ("devices", f"{summary['devices']}; {summary['write_requests']} write and {summary['read_requests']} read "
                    f"requests in {summary['seconds']:.2f} s"),
    ])
    main = (f"<section class=counts>{counts}</section>{_devices(statuses, batches)}"
            "<section><h2>Parameters, device by device</h2><div id=records></div></section>")
    name = title or "deployer run: " + (", ".join(os.path.basename(r) for r in recipes) or "report")
    return _page(name, header, main, {"kind": "run", "devices": devices})


def as_found_page(devices: Sequence[Mapping[str, Any]], *, command: str | None = None,
                  run: Mapping[str, Any] | None = None) -> str:
    """The as-found half of a commissioning record (``pull --html``): per device, what it held.

    ``devices``: ``{name, url, unit, profile, values: [(parameter, text, registers)], error}`` each.
    """
    data = []
    for d in devices:
        params = [[n, t, " ".join(str(w) for w in regs)] for n, t, regs in d.get("values", ())]
        data.append({"name": d["name"], "url": d["url"], "unit": d["unit"], "profile": d["profile"],
                     "status": "unreachable" if d.get("error") else "ok", "batch": None, "seconds": None,
                     "requests": 0, "error": d.get("error"), "notices": [], "snapshot": None, "commit": None,
                     "sha": d.get("sha"), "changed": 0, "failed": 0, "params": params})
    info = dict(run or {})
    header = _meta([("command", command or info.get("command")), ("who", info.get("user")),
                    ("when", info.get("started")), ("where", info.get("host")),
                    ("deployer", info.get("version")), ("devices", len(data))])
    statuses = [s for s in ("unreachable", "ok") if any(d["status"] == s for d in data)]
    main = (_devices(statuses, [])
            + "<section><h2>As found, device by device</h2><div id=records></div></section>")
    return _page("deployer: as-found record", header, main, {"kind": "as-found", "devices": data})


def drift_page(devices: Sequence[str], parameters: Sequence[str],
               cells: Sequence[Sequence[tuple[str] | tuple[str, str] | None]], *,
               command: str | None = None, run: Mapping[str, Any] | None = None) -> str:
    """A fleet's drift as a parameters x devices matrix (``diff --inventory ... --html``).

    ``cells[i][j]``: parameter i on device j: ``(held,)`` as desired, ``(held, desired)`` drifted,
    None where the device's recipe does not set it (or the device could not be read).
    """
    info = dict(run or {})
    drifted = sum(1 for row in cells for c in row if c is not None and len(c) > 1)
    header = _meta([("command", command or info.get("command")), ("who", info.get("user")),
                    ("when", info.get("started")), ("where", info.get("host")), ("deployer", info.get("version")),
                    ("drift", f"{drifted} values on {len(devices)} devices, {len(parameters)} parameters")])
    main = ("<div class=controls><input type=search id=q placeholder='filter parameters'>"
            "<input type=search id=dq placeholder='filter devices'>"
            "<label><input type=checkbox id=only-drift checked> drifted only</label>"
            "<span id=shown class=muted></span></div><div style='overflow:auto'><table id=matrix></table></div>")
    return _page("deployer: drift", header, main,
                 {"kind": "drift", "devices": list(devices), "parameters": list(parameters),
                  "cells": [[None if c is None else list(c) for c in row] for row in cells]})
